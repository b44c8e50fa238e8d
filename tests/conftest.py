"""Shared fixtures. Real data lives in ../shared beside the checkout (present in CI)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("TUBE_MINER_SHARED", REPO.parent / "shared"))
DATA = SHARED / "data"
MODELS = SHARED / "models"

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
# Ray's single-host mode, read when `ray` is first imported (test modules import it at
# collection): every Ray a test starts in this process listens on loopback only, as
# `mine submit` does (mining/pipeline/localray.py). Subprocesses of `mine` get it from there.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


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


def kitti_0005_stereo(kitti_tracking_root: Path, n_frames: int):
    """The first ``n_frames`` real KITTI 0005 stereo pairs (RGB) and their StereoCalib,
    read through the project's own KITTI readers."""
    from mining.sources.kitti import read_rgb
    from mining.sources.kitti_calib import read_tracking_calib

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
