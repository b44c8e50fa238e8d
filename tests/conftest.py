"""Shared fixtures and helpers. Real data lives in ../shared beside the checkout (present in CI)."""

from __future__ import annotations

import json
import os
import signal
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("TUBE_MINER_SHARED", REPO.parent / "shared"))
DATA = SHARED / "data"
MODELS = SHARED / "models"
MODEL = MODELS / "yolov8n-seg_int8.onnx"  # the shared ONNX proposer model (YOLOv8n-seg, int8): user-provided, not bundled

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
# Ray's single-host mode, read when `ray` is first imported (test modules import it at
# collection): every Ray a test starts in this process listens on loopback only, as
# `mine submit` does (mining/pipeline/localray.py). Subprocesses of `mine` get it from there.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")

# A suite started in the background by a non-interactive shell (`scripts/test.sh &`, nohup) starts
# with SIGINT ignored, and every command a test starts would inherit that: the tests of Ctrl-C
# (`mine submit`, `mine view`) then meet commands that cannot be interrupted (two full runs failed
# so; a terminal's foreground run passed). The tests play a terminal's Ctrl-C, so SIGINT is restored
# to Python's default here; children get the OS default after exec.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _require(path: Path) -> Path:
    # Real-data tests may skip only when ../shared/data is absent altogether; when the
    # folder is there, a missing file is a failure.
    if not DATA.is_dir():
        pytest.skip(f"real data not present at {DATA}")
    assert path.exists(), f"expected real data at {path}"
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    return _require(DATA)


@pytest.fixture(scope="session")
def kitti_tracking_root() -> Path:
    return _require(DATA / "kitti_tracking")


@pytest.fixture(scope="session")
def kitti_raw_root() -> Path:
    return _require(DATA / "kitti_raw")


@pytest.fixture(scope="session")
def stereo_gt_root() -> Path:
    return _require(DATA / "stereo_gt")


@pytest.fixture(scope="session")
def oxford_data() -> Path:
    return _require(DATA / "oxford")


def coco_rle(mask) -> dict:
    """The COCO compressed RLE of a boolean mask, as ``pycocotools.mask.encode`` makes it."""
    import numpy as np
    from pycocotools import mask as mask_utils

    return mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))


def kitti_0005_stereo(kitti_tracking_root: Path, n_frames: int):
    """The first ``n_frames`` real KITTI 0005 stereo pairs (RGB) and their StereoCalib,
    read through the project's own KITTI readers."""
    from mining.sources.kitti import read_rgb
    from mining.formats.kitti_calib import read_tracking_calib

    seq = kitti_tracking_root / "training"
    left = [read_rgb(seq / "image_02" / "0005" / f"{i:06d}.png", i) for i in range(n_frames)]
    right = [read_rgb(seq / "image_03" / "0005" / f"{i:06d}.png", i) for i in range(n_frames)]
    h, w = left[0].shape[:2]
    return left, right, read_tracking_calib(seq / "calib" / "0005.txt").stereo(w, h)


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory, kitti_tracking_root):
    """(folder, tables) of a real small catalogue (tests/_catalog_data.py), built once per test module
    (module scope: some tests write into it)."""
    from _catalog_data import build_catalogue

    out = tmp_path_factory.mktemp("catalogue")
    return out, build_catalogue(out, kitti_tracking_root)


@pytest.fixture(scope="module")
def every_call(catalogue, tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """(folder, tube id → call) of a copy of ``catalogue`` whose tubes carry every call, rows
    written before the call column among them (tests/_catalog_data.py ``EVERY_CALL``)."""
    from _catalog_data import every_call_catalogue

    out, tables = catalogue
    dest = tmp_path_factory.mktemp("every-call") / "catalogue"
    return dest, every_call_catalogue(out, tables, dest)


@pytest.fixture(scope="session")
def base_catalogue(tmp_path_factory) -> tuple[Path, dict]:
    """(folder, its tables) of the small synthetic job of tests/_jobs.py over frames 0:16, mined
    once per session; tests damage or resubmit to a copy (``_jobs.copy_of``)."""
    from _jobs import mine, tables

    out = tmp_path_factory.mktemp("small_job") / "base"
    s = mine(out)
    assert s.ok == 2 and not s.failed, s.lines()
    t = tables(out)
    assert t["tubes"] and len(t["frames"]) == 16, "the base job found no tubes: comparisons would be empty"
    return out, t


# ── the torch proposer with random weights (tests/test_proposals_torch.py, test_proposals_contract.py) ──

# The network runs on a frame downscaled by min_size/max_size (128×424) so that the tests stay fast.
TORCH_SMALL = {"device": "cpu", "min_size": 128, "max_size": 424, "rpn_post_nms_top_n": 200, "max_proposals": 20}


@pytest.fixture(scope="session")
def torch_checkpoint(tmp_path_factory) -> Path:
    """The real maskrcnn_resnet50_fpn in torchvision's COCO layout (91 classes) with random initial
    weights (seed 0), saved with torch.save: no weights are bundled or downloaded. Random weights say
    nothing about accuracy; they exercise the output contract, the checkpoint layouts and the pipeline."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("torchvision")
    from torchvision.models.detection import maskrcnn_resnet50_fpn

    torch.manual_seed(0)
    model = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None)
    path = tmp_path_factory.mktemp("torch_ckpt") / "maskrcnn_resnet50_fpn_random.pt"
    torch.save(model.state_dict(), path)
    return path


# ── `mine view` (tests/test_view.py, test_view_browser.py, test_view_hardening.py) ──


@pytest.fixture(scope="module")
def chromium() -> str:
    """The path of a headless Chromium for the browser tests (tests/_cdp.py)."""
    from _cdp import find_chromium

    path = find_chromium()
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("no chromium in CI: scripts/setup.sh test installs it (apt-get install chromium)")
        pytest.skip("no chromium on PATH: `apt-get install chromium` (scripts/setup.sh test does it as root)")
    return path


@contextmanager
def serving(out: Path, cache: Path, **kw: Any) -> Iterator[tuple[str, Any]]:
    """(base URL, server) of `mine view`'s server on catalogue ``out``, serving in a thread
    until the block ends; ``kw`` go to ``make_server``."""
    from mining.view.server import make_server

    server = make_server(out, "127.0.0.1", 0, cache, **kw)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", server
    finally:
        server.shutdown()
        server.server_close()
        server.app.browser.close()
        thread.join(5)


def get(base: str, path: str, params: dict | list | None = None, timeout: float = 60) -> tuple[int, dict, bytes]:
    """(status, headers, body) of GET ``base + path`` with ``params``; an error status is an answer too."""
    url = f"{base}{path}" + (f"?{urlencode(params, doseq=True)}" if params else "")
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def json_get(base: str, path: str, params: dict | list | None = None) -> tuple[int, dict]:
    """(status, parsed body) of a GET whose answer must be JSON."""
    status, headers, body = get(base, path, params)
    assert headers["Content-Type"].startswith("application/json"), headers
    return status, json.loads(body)


def count_tubes(out: Path, where: str, values: list | None = None) -> int:
    """How many tubes of catalogue ``out`` DuckDB finds ``WHERE where`` (``?`` bound to ``values``)."""
    from mining.catalog.views import connect

    con = connect(out)
    try:
        return con.execute(f"SELECT count(*) FROM tubes WHERE {where}", values or []).fetchone()[0]
    finally:
        con.close()


# ── Ray stays out of the pytest process (tests/_own_process.py, issue 17) ──────────────
from _own_process import MARKER as _OWN_PROCESS, RAY_IN_PYTEST, in_child, ray_was_started_here  # noqa: E402
from _own_process import protocol as own_process_protocol  # noqa: E402


def pytest_configure(config):
    config.addinivalue_line("markers", f"{_OWN_PROCESS}: runs in a pytest process of its own (it starts Ray in-process); "
                                       "fails if that process ends in a signal")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    if item.get_closest_marker(_OWN_PROCESS) is None or in_child():
        return None
    own_process_protocol(item, nextitem)
    return True


@pytest.fixture(autouse=True)
def _ray_stays_out_of_the_pytest_process():
    before = ray_was_started_here()
    yield
    if not in_child() and not before and ray_was_started_here():
        pytest.fail(RAY_IN_PYTEST, pytrace=False)


# Tiny random-weight models in the real layouts of the class-agnostic proposers (tests/_tiny_models.py).
TINY_SAM_SIZE = 128  # the tiny SAM encoder's input side (SAM's is 1024): embeddings 8×8, low-res masks 32×32


@pytest.fixture(scope="session")
def fastsam_model(tmp_path_factory) -> Path:
    """A FastSAM-layout ONNX model (one class, 32 coefficients, fixed 64×64 input) with random weights."""
    pytest.importorskip("onnx")
    from _tiny_models import fastsam_onnx

    return fastsam_onnx(tmp_path_factory.mktemp("fastsam") / "fastsam_tiny.onnx")


@pytest.fixture(scope="session")
def sam_models(tmp_path_factory) -> dict[str, Path]:
    """SAM-layout ONNX files with random weights: the encoder and the batched and official (B = 1) decoders."""
    pytest.importorskip("onnx")
    from _tiny_models import sam_decoder_onnx, sam_encoder_onnx

    d = tmp_path_factory.mktemp("sam")
    return {"encoder": sam_encoder_onnx(d / "encoder.onnx", TINY_SAM_SIZE),
            "decoder": sam_decoder_onnx(d / "decoder.onnx", TINY_SAM_SIZE),
            "decoder_b1": sam_decoder_onnx(d / "decoder_b1.onnx", TINY_SAM_SIZE, batch=1)}


@pytest.fixture(scope="session")
def torch_agnostic_checkpoint(torch_checkpoint, tmp_path_factory) -> Path:
    """A class-agnostic Mask R-CNN (torchvision layout, num_classes=2: background, object), random weights."""
    torch = pytest.importorskip("torch")
    state = torch.load(torch_checkpoint, map_location="cpu", weights_only=True)
    pre, mk = "roi_heads.box_predictor.", "roi_heads.mask_predictor.mask_fcn_logits."
    torch.manual_seed(1)
    for part, shape in (("cls_score", (2, 1024)), ("bbox_pred", (8, 1024))):
        state[pre + part + ".weight"] = torch.randn(shape) * 0.01
        state[pre + part + ".bias"] = torch.zeros(shape[0])
    state[pre + "cls_score.bias"] = torch.tensor([0.0, 1.0])  # leans to "object": rows pass the score cut
    state[mk + "weight"] = state[mk + "weight"][:2].clone()
    state[mk + "bias"] = state[mk + "bias"][:2].clone()
    path = tmp_path_factory.mktemp("torch_agnostic") / "maskrcnn_agnostic_random.pt"
    torch.save(state, path)
    return path
