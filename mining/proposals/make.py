"""Build the configured proposer: one name or a union such as ``"onnx+stereo"``.

Every proposer is called as ``proposer(frame, geometry) -> Proposals``. Proposers that
hold a model load it once, in the constructor. ``FrameProposer`` splits a union into the
parts that run a network on the image (batched; on a GPU stage when the job has one) and
the parts that need the frame's geometry. Which proposers there are, their kinds and the
functions that build them: ``registry.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mining.errors import ConfigError
from mining.proposals.config import ProposalConfig
from mining.proposals.registry import (CLASSIFYING, MODEL, MODELS, ModelBatch, Proposer, entry, extra_parts,
                                       proposer_names)
from mining.proposals.union import union
from mining.types import FrameGeometry, Proposals, StereoFrame


def classifiers_line(proposer: str) -> str:
    """Which of the configured proposers classify, in words (for summaries and ``mine status``)."""
    names = proposer_names(proposer)
    cls = [n for n in names if n in CLASSIFYING]
    if not cls:
        return f"classes: no classifier ran (proposer {proposer}): every tube is unclassified (known is null)"
    only_if = entry(cls[0]).classifies_if if len(cls) == 1 else ""
    what = " and ".join(cls) + (f" ({only_if})" if only_if else "")
    return (f"classes: {what} classified (proposer {proposer}); the other proposers' proposals it did not cover "
            f"count toward unknown, by how likely it would have found a COCO object that size"
            if len(cls) < len(names) else f"classes: {what} classified (proposer {proposer})")


def classify_hint(proposer: str) -> str | None:
    """Where no proposer classifies: how to mine a catalogue whose tubes are called known or unknown
    (a summary's closing line); None where one does."""
    if any(n in CLASSIFYING for n in proposer_names(proposer)):
        return None
    # MODEL.onnx is a placeholder the user must replace: a plausible-looking path was copied as is
    return ("to call each tube known (one of COCO's 80 classes, e.g. car) or unknown (the discovery set), mine "
            "again into a new --out with a COCO instance-segmentation model you provide in place of MODEL.onnx "
            "(a YOLOv8-seg ONNX file, e.g. made by Ultralytics' `yolo export model=yolov8n-seg.pt format=onnx`; "
            "its weights are AGPL-3.0, not bundled; docs/USAGE.md, Proposers): "
            f"--set proposals.proposer=onnx+{proposer} --set proposals.onnx.model_path=MODEL.onnx")


def make_one(name: str, cfg: ProposalConfig, frame_size: tuple[int, int]) -> Proposer:
    """One named proposer of a union (an entry of ``registry.PROPOSERS``) as ``proposer(frame, geometry)``;
    a model proposer gives its own proposals alone (its ``extras`` are parts of their own)."""
    e = entry(name)
    if e.kind != MODEL:
        return e.load()(cfg, frame_size)
    own = replace(cfg, **{x: replace(getattr(cfg, x), enabled=False) for x in e.extras})
    batch = e.load()(own, frame_size)
    return lambda frame, geometry: batch([frame.index], [frame.left])[0][0]


class FrameProposer:
    """The configured proposer, split by what each part needs.

    *Model parts* (the registry's ``MODEL`` proposers, and the ``extras`` their network run
    gives, such as the ONNX model's generic candidates) look at the left image alone:
    ``propose_images`` runs them on a batch of frames, in this process or on a proposal stage
    of their own (a GPU actor, ``mining/pipeline/proposal_stage.py``). *Frame parts* (the
    ``FRAME`` proposers: ``stereo``, ``json``) need the frame's geometry or its index and run
    where the geometry is. ``finish`` joins a frame's model parts with its frame parts through the
    union, in the configured order, so a frame's proposals are the same wherever its model
    parts ran. ``proposer(frame, geometry)`` does both for one frame.
    """

    def __init__(self, cfg: ProposalConfig, frame_size: tuple[int, int], models: bool = True,
                 frame_parts: bool = True):
        names = proposer_names(cfg.proposer)
        if not names:
            raise ConfigError("proposals.proposer is empty")
        self.cfg, self.frame_size = cfg, frame_size
        model_parts = [n for n in names if entry(n).kind == MODEL]
        extras = extra_parts(cfg)
        # The extra parts come last, so the union keeps them only where no other part proposed.
        self.names = names + extras
        # In the order the models give their results: each model's own, then its extras that are on.
        self.model_names = [p for n in model_parts for p in [n, *(x for x in entry(n).extras if x in extras)]]
        self._frame_parts = {n: make_one(n, cfg, frame_size) for n in self.names
                             if frame_parts and n not in self.model_names}
        self._models = [model_batch(n, cfg, frame_size) for n in model_parts] if models else []

    def propose_images(self, frames: Sequence[int], images: Sequence[np.ndarray]) -> list[list[Proposals]]:
        """The model parts of each frame (in ``model_names`` order), batched where a model takes batches."""
        per_model = [m(list(frames), list(images)) for m in self._models]
        return [[p for outs in per_model for p in outs[i]] for i in range(len(frames))]

    def finish(self, frame: StereoFrame, geometry: FrameGeometry, models: Sequence[Proposals]) -> Proposals:
        """The frame's proposals from its model parts (``propose_images``) and its frame parts."""
        if len(models) != len(self.model_names):
            raise ValueError(f"{len(models)} model results for the model parts {self.model_names}")
        given = dict(zip(self.model_names, models))
        parts = [given[n] if n in given else self._frame_parts[n](frame, geometry) for n in self.names]
        if len(parts) == 1:
            return parts[0]
        return union(parts, self.cfg.union.mask_iou, self.cfg.union, geometry.disparity, geometry.depth)

    def __call__(self, frame: StereoFrame, geometry: FrameGeometry) -> Proposals:
        models = self.propose_images([frame.index], [frame.left])[0] if self.model_names else []
        return self.finish(frame, geometry, models)


def model_batch(name: str, cfg: ProposalConfig, frame_size: tuple[int, int]) -> ModelBatch:
    """A model proposer as a batch function (its registry factory): frames → per frame, its own
    proposals, then those of its ``extras`` that are on (one network run serves them all)."""
    e = entry(name)
    if e.kind != MODEL:
        raise ConfigError(f"proposals.proposer: {name!r} is not a model proposer; models: {MODELS}")
    return e.load()(cfg, frame_size)


def make_proposer(cfg: ProposalConfig, frame_size: tuple[int, int]) -> FrameProposer:
    """``frame_size`` is (height, width)."""
    return FrameProposer(cfg, frame_size)
