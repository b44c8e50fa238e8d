"""The torch proposer (MP R-CNN on torchvision's Mask R-CNN) on real KITTI 0005 frames.

No weights are bundled or downloaded: conftest's ``torch_checkpoint`` builds the checkpoint, the
real maskrcnn_resnet50_fpn with random initial weights (fixed seed), saved with torch.save and read
back through the proposer's own loading code. Random weights say nothing about accuracy; they
exercise the output contract, the checkpoint layouts and the pipeline. The network runs on a
frame downscaled by the config's min_size/max_size (128×424) so that the tests stay fast.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from _run import env
from conftest import REPO, TORCH_SMALL, kitti_0005_stereo
from mining.errors import ConfigError
from mining.formats.coco import CLASS_INDEX, COCO_CATEGORY_IDS
from mining.proposals.config import ProposalConfig, TorchConfig
from mining.types import UNKNOWN_CLASS

torch = pytest.importorskip("torch")
pytest.importorskip("torchvision")

from mining.proposals.mprcnn_torch import TorchProposer, read_checkpoint, resolve_device, torchvision_to_two_head

H, W = 375, 1242


@pytest.fixture(scope="module")
def frames(kitti_tracking_root):
    left, _, _ = kitti_0005_stereo(kitti_tracking_root, 3)
    assert left[0].shape == (H, W, 3)
    return left


def _cfg(path: Path, **kw) -> TorchConfig:
    return TorchConfig(model_path=str(path), **{**TORCH_SMALL, **kw})


@pytest.fixture(scope="module")
def proposer(torch_checkpoint) -> TorchProposer:
    return TorchProposer(_cfg(torch_checkpoint))


def _same(a, b) -> None:
    assert a.frame == b.frame and len(a) == len(b) and a.proposer == b.proposer
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.objectness, b.objectness)
    np.testing.assert_array_equal(a.posterior, b.posterior)
    assert a.rles == b.rles


def test_output_contract(proposer, frames):
    # What every proposer keeps (shapes, dtypes, ranges, order, RLEs): tests/test_proposals_contract.py.
    cfg = proposer.cfg
    p = proposer(4, frames[0])
    n = len(p)
    assert 0 < n <= cfg.max_proposals
    assert p.frame == 4
    assert (p.objectness >= cfg.score_threshold).all()
    for rle, box in zip(p.rles, p.boxes):
        m = mask_utils.decode(rle)
        assert m.any()
        ys, xs = np.nonzero(m)
        # The mask head's 28×28 grid is pasted into the box grown by one cell each side.
        pad = (box[2:] - box[:2]) / 28 + 1
        assert xs.min() >= box[0] - pad[0] - 1 and xs.max() <= box[2] + pad[0]
        assert ys.min() >= box[1] - pad[1] - 1 and ys.max() <= box[3] + pad[1]


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_two_runs_and_two_loads_give_the_same_proposals(proposer, torch_checkpoint, frames):
    first = proposer(0, frames[1])
    _same(first, proposer(0, frames[1]))
    _same(first, TorchProposer(_cfg(torch_checkpoint))(0, frames[1]))


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_batched_equals_per_frame(proposer, torch_checkpoint, frames):
    batched = TorchProposer(_cfg(torch_checkpoint, batch_size=2))  # one batch of 2, then one of 1
    together = batched.propose_batch([10, 11, 12], frames)
    assert [p.frame for p in together] == [10, 11, 12]
    for i, p in enumerate(together):
        alone = proposer(10 + i, frames[i])
        assert len(p) == len(alone) > 0
        np.testing.assert_allclose(p.boxes, alone.boxes, atol=1e-3)
        np.testing.assert_allclose(p.objectness, alone.objectness, atol=1e-5)
        np.testing.assert_allclose(p.posterior, alone.posterior, atol=1e-5)
        assert (mask_utils.iou(p.rles, alone.rles, [0] * len(p)).diagonal() > 0.99).all()


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_max_proposals_and_score_threshold_cut(proposer, torch_checkpoint, frames):
    everything = proposer(0, frames[0])
    few = TorchProposer(_cfg(torch_checkpoint, max_proposals=5))(0, frames[0])
    assert len(few) <= 5 < len(everything)
    np.testing.assert_array_equal(few.boxes, everything.boxes[:len(few)])
    cut = float(everything.objectness[len(everything) // 2])
    high = TorchProposer(_cfg(torch_checkpoint, score_threshold=cut))(0, frames[0])
    assert 0 < len(high) < len(everything) and (high.objectness >= cut).all()


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_torchvision_layout_converts_to_two_head_exactly(torch_checkpoint, proposer, frames, tmp_path):
    state = read_checkpoint(torch_checkpoint)
    two = torchvision_to_two_head(state)
    pre = "roi_heads.box_predictor."
    assert two[pre + "objectness.weight"].shape == (91, 1024)
    assert two[pre + "cls_score.weight"].shape == (81, 1024)
    assert two[pre + "bbox_pred.weight"].shape == (4 * 81, 1024)
    assert two["roi_heads.mask_predictor.mask_fcn_logits.weight"].shape == (81, 256, 1, 1)
    # Class-head row 1 + k is COCO class k, i.e. torchvision's row of its COCO category id.
    for name, coco_id in (("person", 1), ("car", 3), ("stop sign", 13), ("toothbrush", 90)):
        k = CLASS_INDEX[name]
        assert COCO_CATEGORY_IDS[k] == coco_id
        torch.testing.assert_close(two[pre + "cls_score.weight"][1 + k], state[pre + "cls_score.weight"][coco_id])
        torch.testing.assert_close(two[pre + "bbox_pred.bias"][4 * (1 + k):4 * (2 + k)],
                                   state[pre + "bbox_pred.bias"][4 * coco_id:4 * (coco_id + 1)])
    path = tmp_path / "two_head.pt"
    torch.save(two, path)
    converted = TorchProposer(_cfg(path))
    for i in range(2):
        _same(proposer(i, frames[i]), converted(i, frames[i]))


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_paper_layout_heads_play_their_own_parts(torch_checkpoint, frames, tmp_path):
    """The paper's MP R-CNN: a 2-way objectness head, box deltas and masks for "object" only.
    Objectness comes from the objectness head alone, the posterior from the class head alone."""
    state = read_checkpoint(torch_checkpoint)
    pre, mk = "roi_heads.box_predictor.", "roi_heads.mask_predictor.mask_fcn_logits."
    base = {k: v for k, v in state.items() if not k.startswith(pre) and not k.startswith(mk)}
    rows = torch.tensor([0, 3])  # background and torchvision's "car" row stand in for background, object
    paper = {**base,
             pre + "objectness.weight": state[pre + "cls_score.weight"][rows],
             pre + "objectness.bias": state[pre + "cls_score.bias"][rows],
             pre + "cls_score.weight": torch.zeros(81, 1024), pre + "cls_score.bias": torch.zeros(81),
             pre + "bbox_pred.weight": state[pre + "bbox_pred.weight"][:8],
             pre + "bbox_pred.bias": state[pre + "bbox_pred.bias"][:8],
             mk + "weight": state[mk + "weight"][rows], mk + "bias": state[mk + "bias"][rows]}
    torch.save(paper, tmp_path / "uniform.pt")
    # Random weights give these two stand-in rows little confidence: keep every RoI.
    uniform = TorchProposer(_cfg(tmp_path / "uniform.pt", score_threshold=0.0))(0, frames[0])
    assert len(uniform) > 0
    np.testing.assert_allclose(uniform.posterior, 1.0 / 81, rtol=1e-5)  # a class head that knows nothing
    # A class head sure of background: every proposal is unknown, its objectness untouched.
    bias = torch.zeros(81)
    bias[0] = 20.0
    torch.save({**paper, pre + "cls_score.bias": bias}, tmp_path / "background.pt")
    unknown = TorchProposer(_cfg(tmp_path / "background.pt", score_threshold=0.0))(0, frames[0])
    np.testing.assert_array_equal(unknown.objectness, uniform.objectness)
    np.testing.assert_array_equal(unknown.boxes, uniform.boxes)
    assert (unknown.posterior[:, UNKNOWN_CLASS] > 0.999).all()
    renorm = TorchProposer(_cfg(tmp_path / "background.pt", score_threshold=0.0, unknown_mass="none"))(0, frames[0])
    assert (renorm.posterior[:, UNKNOWN_CLASS] == 0).all()
    np.testing.assert_allclose(renorm.posterior[:, :80], 1.0 / 80, rtol=1e-4)


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_bad_checkpoints_are_config_errors_naming_the_file(torch_checkpoint, tmp_path):
    def fails(path: Path, reason: str) -> None:
        with pytest.raises(ConfigError, match=reason) as e:
            TorchProposer(_cfg(path))
        assert str(path) in str(e.value)

    fails(tmp_path / "absent.pt", "no such file")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00not a checkpoint" * 64)
    fails(garbage, "not a readable PyTorch state dict")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(torch_checkpoint.read_bytes()[:100_000])
    fails(truncated, "not a readable PyTorch state dict")
    # A pickle that would run code when unpickled is refused, and the code does not run.
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    torch.save({"x": Payload()}, tmp_path / "payload.pt")
    fails(tmp_path / "payload.pt", "not a readable PyTorch state dict")
    assert not marker.exists()
    torch.save({"epoch": 3}, tmp_path / "no_tensors.pt")
    fails(tmp_path / "no_tensors.pt", "expected a state dict")
    state = read_checkpoint(torch_checkpoint)
    pre = "roi_heads.box_predictor."
    two_class = {**state, pre + "cls_score.weight": state[pre + "cls_score.weight"][:2],
                 pre + "cls_score.bias": state[pre + "cls_score.bias"][:2]}
    torch.save(two_class, tmp_path / "two_class.pt")
    fails(tmp_path / "two_class.pt", r"bbox_pred 91")  # a 2-class classifier with 91-class boxes: neither layout
    three_class = {**state, pre + "cls_score.weight": state[pre + "cls_score.weight"][:3],
                   pre + "cls_score.bias": state[pre + "cls_score.bias"][:3]}
    torch.save(three_class, tmp_path / "three_class.pt")
    fails(tmp_path / "three_class.pt", r"expected \(91, 1024\)")
    wrong_shape = {**state, "backbone.body.conv1.weight": torch.zeros(64, 3, 3, 3)}
    torch.save(wrong_shape, tmp_path / "wrong_shape.pt")
    fails(tmp_path / "wrong_shape.pt", "does not fit maskrcnn_resnet50_fpn")
    missing = {k: v for k, v in state.items() if not k.startswith("backbone.fpn.")}
    torch.save(missing, tmp_path / "missing.pt")
    fails(tmp_path / "missing.pt", "missing keys")


def test_class_agnostic_checkpoint_gives_objectness_and_no_posterior(torch_agnostic_checkpoint, frames):
    """A Mask R-CNN trained class-agnostically (torchvision layout, num_classes=2) is a proposer
    without classes: objectness = p(object), posterior None (a union's classifier gives the class)."""
    cfg = _cfg(torch_agnostic_checkpoint)
    p = TorchProposer(cfg)(3, frames[0])
    n = len(p)
    assert 0 < n <= cfg.max_proposals and p.frame == 3 and p.proposer == ["torch"] * n
    assert p.posterior is None and p.class_weight is None
    assert p.objectness.dtype == np.float32 and (np.diff(p.objectness) <= 0).all()
    assert ((p.objectness >= cfg.score_threshold) & (p.objectness <= 1)).all()
    assert p.boxes.shape == (n, 4) and all(mask_utils.area(r) > 0 for r in p.rles)


@pytest.mark.slow  # over ~2.5 s: two model loads
def test_class_agnostic_objectness_is_the_object_heads(torch_agnostic_checkpoint, frames, tmp_path):
    """The same weights in the two-head layout with a class head added: identical rows, and the
    class head then gives a posterior; so the agnostic model's objectness is its object head's."""
    state = read_checkpoint(torch_agnostic_checkpoint)
    pre = "roi_heads.box_predictor."
    two = {k: v for k, v in state.items() if not k.startswith(pre + "cls_score.")}
    two.update({pre + "objectness.weight": state[pre + "cls_score.weight"],
                pre + "objectness.bias": state[pre + "cls_score.bias"],
                pre + "cls_score.weight": torch.zeros(81, 1024), pre + "cls_score.bias": torch.zeros(81)})
    torch.save(two, tmp_path / "with_class_head.pt")
    agnostic = TorchProposer(_cfg(torch_agnostic_checkpoint))(0, frames[1])
    classed = TorchProposer(_cfg(tmp_path / "with_class_head.pt"))(0, frames[1])
    assert agnostic.posterior is None and classed.posterior.shape == (len(classed), 81)
    np.testing.assert_array_equal(agnostic.objectness, classed.objectness)
    np.testing.assert_array_equal(agnostic.boxes, classed.boxes)
    assert agnostic.rles == classed.rles


def test_bad_settings_are_config_errors(torch_checkpoint):
    with pytest.raises(ConfigError, match="model_path is empty"):
        TorchProposer(TorchConfig())
    with pytest.raises(ConfigError, match="proposals.torch.device"):
        resolve_device("tpu")
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device"):
            resolve_device("cuda:0")
    with pytest.raises(ConfigError, match="nms_iou"):
        TorchProposer(_cfg(torch_checkpoint, nms_iou=0.0))
    with pytest.raises(ConfigError, match="unknown_mass"):
        TorchProposer(_cfg(torch_checkpoint, unknown_mass="bg"))


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_without_torch_mining_imports_and_the_proposer_names_the_extra():
    # A fresh interpreter in which torch and torchvision cannot be found, as where the extra is not installed.
    code = """
import importlib, pkgutil, sys

class NotInstalled:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "torchvision"):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)

sys.meta_path.insert(0, NotInstalled())
import mining
for m in pkgutil.walk_packages(mining.__path__, "mining."):
    if m.name != "mining.proposals.mprcnn_torch":
        importlib.import_module(m.name)
from mining.errors import ConfigError
from mining.proposals.config import ProposalConfig
from mining.proposals.make import make_proposer
try:
    make_proposer(ProposalConfig(proposer="torch+stereo"), (375, 1242))
except ConfigError as e:
    print("ConfigError:", e)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env(), cwd=REPO, timeout=120,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert "ConfigError:" in out.stdout and "pip install -e .[torch]" in out.stdout


def test_make_proposer_knows_torch(torch_checkpoint, frames):
    from mining.proposals.make import make_proposer

    cfg = ProposalConfig(proposer="torch", torch=_cfg(torch_checkpoint))
    p = make_proposer(cfg, (H, W))
    frame = dataclasses.make_dataclass("F", [("index", int), ("left", np.ndarray)])(7, frames[0])
    out = p(frame, None)
    assert out.frame == 7 and len(out) > 0 and set(out.proposer) == {"torch"}


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_torch_and_stereo_through_the_image_pipeline(kitti_tracking_root, torch_checkpoint):
    """What `mine track images --set proposals.proposer='"torch+stereo"'` runs, on three frames."""
    from mining.config import load_config
    from mining.pipeline.frames import frame_records
    from mining.pipeline.mine import mine_tubes
    from mining.sources import open_source

    settings = ['proposals.proposer="torch+stereo"', f'proposals.torch.model_path="{torch_checkpoint}"']
    settings += [f"proposals.torch.{k}={v!r}".replace("'", '"') for k, v in TORCH_SMALL.items()]
    cfg = load_config(overrides=settings)
    assert cfg.proposals.torch.max_size == 424 and cfg.proposals.torch.device == "cpu"
    source = open_source("kitti", str(kitti_tracking_root))
    records = list(frame_records(source, source.plan("0005"), 0, 3, cfg))
    assert [r.frame.index for r in records] == [0, 1, 2]
    for r in records:
        names = set(r.proposals.proposer)
        assert names == {"torch", "stereo"}, names
        torch_rows = np.array([n == "torch" for n in r.proposals.proposer])
        # Learned rows carry their posterior into the union at full weight; stereo rows the
        # network did not cover count toward unknown, weighted by detectability (union.py).
        np.testing.assert_allclose(r.proposals.posterior[torch_rows].sum(1), 1.0, atol=1e-5)
        assert (r.proposals.class_weights()[torch_rows] == 1).all()
        assert (r.proposals.posterior[~torch_rows, 80] == 1).all()
        assert ((r.proposals.class_weights()[~torch_rows] > 0) & (r.proposals.class_weights()[~torch_rows] < 1)).all()
        assert np.isfinite(r.localised.position[torch_rows]).all(axis=1).any()  # placed in 3D from stereo depth
    mine_tubes((r.tracking for r in records), cfg)  # tubes → score → select take them (3 frames start no tube)


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_bench_proposals_times_the_torch_proposer(shared_data, tmp_path, capsys):
    from mining.cli import main

    settings = ['proposals.proposer="torch"'] + [f"proposals.torch.{k}={v!r}".replace("'", '"')
                                                 for k, v in {**TORCH_SMALL, "batch_size": 2}.items()]
    args = ["bench", "proposals", "--data", str(shared_data), "--frames", "0:3", "--random-weights",
            "--json", str(tmp_path / "bench.json")]
    for s in settings:
        args += ["--set", s]
    assert main(args) == 0
    assert "frames/s" in capsys.readouterr().out
    rows = json.loads((tmp_path / "bench.json").read_text())["rows"]
    assert [r["mode"] for r in rows] == ["per frame", "batch 2"]
    for r in rows:
        assert r["frames"] == 2 and r["fps"] > 0 and 0 < r["proposals_per_frame"] <= TORCH_SMALL["max_proposals"]
    assert set(rows[1]["ms_per_frame"]) == {"backbone_rpn", "box_head_nms", "mask_head", "paste_encode"}
