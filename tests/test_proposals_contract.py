"""Every proposer keeps the one output contract of ``mining.types.Proposals``, on real KITTI 0005 frames.

Every proposer of the registry (``mining/proposals/registry.py``) is tested alone, and so are the
KITTI detection files as detections-only mode reads them and unions with a classifier. They are
built as the pipeline builds them (``make_proposer`` from a job config) and called on the same two
frames with their geometry. Whatever a proposer measures or not, its rows obey one contract: one COCO RLE of
the frame's size per row, canonical (what ``pycocotools.mask.encode`` makes of the mask); float32
boxes inside the frame and objectness in [0, 1], best first; a posterior of 81 classes whose rows
sum to 1 where a classifier looked and are NaN where none did (None when no proposer classifies);
position and size rows finite where the proposer measures 3D and NaN where it does not; each row
named by its proposer (the ONNX model's generic candidates as ``onnx_generic``, on by default, with
no posterior); evidence weights in [0, 1], 0 where no classifier looked.

The ONNX model is the shared one (tests/conftest.py ``MODEL``); the torch proposer has random
weights (conftest's ``torch_checkpoint``), and so do the class-agnostic ``fastsam`` and ``sam``
(conftest's tiny models in their real layouts, tests/_tiny_models.py; SAM on an 8×8 grid): the
contract, not accuracy, is under test.
"""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from conftest import MODEL, TINY_SAM_SIZE, TORCH_SMALL
from mining.config import load_config
from mining.geometry.stage import GeometryStage
from mining.proposals.make import FrameProposer, make_proposer
from mining.proposals.precomputed import KittiDetections
from mining.proposals.registry import CLASSIFYING as CLASSIFIERS, NAMES, PROPOSERS as REGISTRY
from mining.sources import open_source
from mining.sources.kitti import KittiTrackingSource
from mining.types import N_CLASSES, Proposals

N_FRAMES = 2  # KITTI 0005 frames 0 and 1
CLASSIFYING = {*CLASSIFIERS, "kitti_detections"}  # proposers whose rows carry an 81-way posterior
IN_3D = {"stereo", "kitti_detections"}  # proposers whose rows carry a position and a size
# Each registry entry alone, detections-only mode's reader and the unions with a classifier.
PROPOSERS = [*NAMES, "kitti_detections", "onnx+stereo", "onnx+fastsam", "onnx+fastsam+stereo"]


@pytest.fixture(scope="module")
def kitti(kitti_tracking_root):
    """The first frames of 0005 with their geometry, as the pipeline hands them to a proposer."""
    source = open_source("kitti", str(kitti_tracking_root))
    plan = source.plan("0005")
    stage = GeometryStage(plan.calib)
    return [(frame, stage.run(frame)) for frame in source.read(plan, 0, N_FRAMES)]


def _settings(name: str, request, tmp_path_factory) -> list[str]:
    """The job settings that make proposer ``name`` (a union names its parts): the files of the proposers
    that need a model file or a folder (a new entry of that kind gets its settings here)."""
    settings = [f'proposals.proposer="{name}"']
    parts = name.split("+")
    if "onnx" in parts:
        if not MODEL.is_file():
            pytest.skip(f"shared model not present at {MODEL}")
        cache = tmp_path_factory.mktemp("onnx_cache")
        settings += [f'proposals.onnx.model_path="{MODEL.as_posix()}"', f'proposals.onnx.cache_dir="{cache.as_posix()}"']
    if "torch" in parts:
        checkpoint = request.getfixturevalue("torch_checkpoint")
        settings += [f'proposals.torch.model_path="{checkpoint.as_posix()}"']
        settings += [f"proposals.torch.{k}={v!r}".replace("'", '"') for k, v in TORCH_SMALL.items()]
    if "fastsam" in parts:
        model = request.getfixturevalue("fastsam_model")
        cache = tmp_path_factory.mktemp("fastsam_cache")
        settings += [f'proposals.fastsam.model_path="{model.as_posix()}"',
                     f'proposals.fastsam.cache_dir="{cache.as_posix()}"', "proposals.fastsam.auto_max_side=256"]
    if "sam" in parts:
        models = request.getfixturevalue("sam_models")
        settings += [f'proposals.sam.encoder_path="{models["encoder"].as_posix()}"',
                     f'proposals.sam.decoder_path="{models["decoder"].as_posix()}"',
                     f"proposals.sam.input_size={TINY_SAM_SIZE}", "proposals.sam.points_per_side=8",
                     'proposals.sam.device="cpu"']
    if "json" in parts:
        folder = request.getfixturevalue("shared_data") / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top20"
        settings += [f'proposals.json.folder="{folder.as_posix()}"']
    return settings


@pytest.fixture(scope="module", params=PROPOSERS)
def proposer(request, kitti, kitti_tracking_root, tmp_path_factory):
    """(name, proposer(frame, geometry) -> Proposals) for each proposer."""
    name = request.param
    calib = kitti[0][0].calib
    if name == "kitti_detections":  # detections-only mode's reader (mining/pipeline/detections.py)
        training = kitti_tracking_root / "training"
        dets = KittiDetections(training / "det_pointrcnn", "0005", KittiTrackingSource(training).kitti_calib("0005"),
                               (calib.width, calib.height), load_config().proposals.kitti_detections)
        return name, lambda frame, geometry: dets(frame.index, frame.left)
    cfg = load_config(overrides=_settings(name, request, tmp_path_factory))
    assert "onnx" not in name.split("+") or cfg.proposals.onnx_generic.enabled, "the generic candidates are on by default"
    return name, make_proposer(cfg.proposals, (calib.height, calib.width))


def _rows_finite_or_nan(a: np.ndarray) -> np.ndarray:
    """Which rows are finite; asserts every other row is NaN throughout (no half-known row)."""
    finite = np.isfinite(a).all(axis=1)
    assert np.isnan(a[~finite]).all(), "a row is neither finite nor NaN throughout"
    return finite


def test_every_proposer_keeps_the_output_contract(proposer, kitti):
    name, propose = proposer
    parts = set(name.split("+"))
    named = parts | {x for n in parts if n in REGISTRY for x in REGISTRY[n].extras}  # e.g. the generic candidates
    for frame, geometry in kitti:
        p = propose(frame, geometry)
        h, w = frame.calib.height, frame.calib.width
        if isinstance(propose, FrameProposer):  # each model result is the part it stands for (the union's order)
            models = propose.propose_images([frame.index], [frame.left])[0]
            assert [set(m.proposer) <= {n} for m, n in zip(models, propose.model_names)] == [True] * len(models)
        assert isinstance(p, Proposals) and p.frame == frame.index
        n = len(p)
        assert n > 0, f"{name} proposed nothing on frame {frame.index}"

        # Each row is named by the proposer that made it; a union names its parts.
        assert len(p.proposer) == n and parts <= set(p.proposer) <= named, (name, set(p.proposer))
        rows = np.array(p.proposer)

        # Masks: one canonical COCO RLE of the frame's size per row.
        assert len(p.rles) == n
        for rle in p.rles:
            assert list(rle["size"]) == [h, w] and isinstance(rle["counts"], bytes)
            m = mask_utils.decode(rle)
            assert m.shape == (h, w)
            assert mask_utils.encode(np.asfortranarray(m))["counts"] == rle["counts"], "not canonical"

        # Boxes: float32 x1 y1 x2 y2 inside the frame, of positive size.
        assert p.boxes.shape == (n, 4) and p.boxes.dtype == np.float32
        assert np.isfinite(p.boxes).all() and (p.boxes[:, 2:] > p.boxes[:, :2]).all()
        assert (p.boxes >= 0).all() and (p.boxes[:, [0, 2]] <= w).all() and (p.boxes[:, [1, 3]] <= h).all()

        # Objectness: float32 in [0, 1], best first.
        assert p.objectness.shape == (n,) and p.objectness.dtype == np.float32
        assert ((p.objectness >= 0) & (p.objectness <= 1)).all()
        assert (np.diff(p.objectness) <= 0).all(), "not sorted best first"

        # Posterior: None without a classifier; else (n, 81) rows summing to 1 where one looked, NaN where none did.
        classified = np.isin(rows, sorted(CLASSIFYING))
        if not parts & CLASSIFYING:
            assert p.posterior is None
        else:
            assert p.posterior.shape == (n, N_CLASSES) and p.posterior.dtype == np.float32
            looked = _rows_finite_or_nan(p.posterior)
            assert looked[classified].all(), "a classifier's own row has no posterior"
            assert (p.posterior[looked] >= 0).all()
            np.testing.assert_allclose(p.posterior[looked].sum(axis=1), 1.0, atol=1e-5)

        # Evidence weights: in [0, 1]; 0 where no classifier looked; a classifier's own rows count in full.
        if p.class_weight is not None:
            assert p.class_weight.shape == (n,) and p.class_weight.dtype == np.float32
            assert np.isfinite(p.class_weight).all()
        weights = p.class_weights()
        assert weights.shape == (n,) and weights.dtype == np.float32
        assert ((weights >= 0) & (weights <= 1)).all()
        if p.posterior is None:
            assert (weights == 0).all()
        else:
            assert (weights[~np.isfinite(p.posterior).all(axis=1)] == 0).all()
            assert (weights[classified] == 1).all()

        # 3D: None when no proposer measures it; else (n, 3) float32 rows, finite exactly for the proposers that do.
        measured = np.isin(rows, sorted(IN_3D))
        for field in ("position", "size"):
            a = getattr(p, field)
            if not parts & IN_3D:
                assert a is None, field
                continue
            assert a.shape == (n, 3) and a.dtype == np.float32, field
            finite = _rows_finite_or_nan(a)
            assert (finite == measured).all(), f"{field}: finite rows are not the measuring proposers' rows"
        if parts & IN_3D:
            assert (p.position[measured, 2] > 0).all(), "a position behind the camera"
            assert (p.size[measured] >= 0).all(), "a negative size"
