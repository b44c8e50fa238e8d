"""Build the configured proposer: one name or a union such as ``"onnx+stereo"``.

Every proposer is called as ``proposer(frame, geometry) -> Proposals``. Proposers that
hold a model load it once, in the constructor. ``FrameProposer`` splits a union into the
parts that run a network on the image (batched; on a GPU stage when the job has one) and
the parts that need the frame's geometry.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from mining.errors import ConfigError
from mining.proposals.config import ProposalConfig
from mining.proposals.union import union
from mining.types import FrameGeometry, Proposals, StereoFrame

Proposer = Callable[[StereoFrame, FrameGeometry], Proposals]
NAMES = ("stereo", "onnx", "torch", "json", "fastsam", "sam")
# Proposers that give each proposal an 81-way class posterior (a classifier looked); "json"
# does when its files carry ``second_posterior`` or COCO category ids, "torch" unless its
# checkpoint is class-agnostic. "fastsam" and "sam" are class-agnostic: objectness from their
# own scores, no posterior (in a union the classifier's rows give the class, union.py).
CLASSIFYING = ("onnx", "torch", "json")


def unknown_proposers(proposer: str) -> str | None:
    """What is wrong with a ``proposals.proposer`` setting, or None (the config's rule)."""
    names = proposer_names(proposer)
    if not names:
        return f"names no proposer; known: {', '.join(NAMES)} or a union like 'onnx+stereo'"
    bad = [n for n in names if n not in NAMES]
    if bad:
        return f"unknown proposer {', '.join(map(repr, bad))}; known: {', '.join(NAMES)} or a union like 'onnx+stereo'"
    return None


def proposer_names(proposer: str) -> list[str]:
    """The proposers of a ``proposals.proposer`` setting ("onnx+stereo" → ["onnx", "stereo"])."""
    return [n.strip() for n in proposer.split("+") if n.strip()]


def classifiers_line(proposer: str) -> str:
    """Which of the configured proposers classify, in words (for summaries and ``mine status``)."""
    names = proposer_names(proposer)
    cls = [n for n in names if n in CLASSIFYING]
    if not cls:
        return f"classes: no classifier ran (proposer {proposer}): every tube is unclassified (known is null)"
    what = " and ".join(cls) + (" (if its files carry classes)" if cls == ["json"] else "")
    return (f"classes: {what} classified (proposer {proposer}); the other proposers' proposals it did not cover "
            f"count toward unknown, by how likely it would have found a COCO object that size"
            if len(cls) < len(names) else f"classes: {what} classified (proposer {proposer})")


def classify_hint(proposer: str) -> str | None:
    """Where no proposer classifies: how to mine a catalogue whose tubes are called known or unknown
    (a summary's closing line); None where one does."""
    if any(n in CLASSIFYING for n in proposer_names(proposer)):
        return None
    return ("to call each tube known (one of COCO's 80 classes, e.g. car) or unknown (the discovery set), mine "
            "again into a new --out with a COCO instance-segmentation model you provide (a YOLOv8-seg ONNX file; "
            f"its weights are AGPL-3.0, not bundled): --set proposals.proposer=onnx+{proposer} "
            "--set proposals.onnx.model_path=/path/to/yolov8n-seg.onnx")


def make_one(name: str, cfg: ProposalConfig, frame_size: tuple[int, int]) -> Proposer:
    """One named proposer of a union (``stereo``, ``onnx``, ``torch``, ``json``, ``fastsam``, ``sam``)."""
    if name == "stereo":
        from mining.proposals.stereo import StereoProposer

        p = StereoProposer(cfg.stereo)
        return p
    if name == "onnx":
        from mining.proposals.onnx_yolo import OnnxProposer

        model = OnnxProposer(cfg.onnx, frame_size=frame_size)
        return lambda frame, geometry: model(frame.index, frame.left)
    if name == "torch":
        from mining.proposals.mprcnn_torch import TorchProposer  # a ConfigError naming the extra without torch

        mprcnn = TorchProposer(cfg.torch)
        return lambda frame, geometry: mprcnn(frame.index, frame.left)
    if name == "fastsam":
        from mining.proposals.fastsam import FastSamProposer

        fastsam = FastSamProposer(cfg.fastsam, frame_size=frame_size)
        return lambda frame, geometry: fastsam(frame.index, frame.left)
    if name == "sam":
        from mining.proposals.sam import SamProposer

        sam = SamProposer(cfg.sam)
        return lambda frame, geometry: sam(frame.index, frame.left)
    if name == "json":
        from mining.proposals.precomputed import JsonProposals

        reader = JsonProposals(cfg.json.folder, cfg.json, image_size=(frame_size[1], frame_size[0]))
        return lambda frame, geometry: reader(frame.index, frame.left)
    raise ConfigError(f"proposals.proposer: unknown proposer {name!r}; known: {NAMES} or a union like 'onnx+stereo'")


MODELS = ("onnx", "torch", "fastsam", "sam")  # proposers that run a network on the left image alone
GENERIC = "onnx_generic"  # the ONNX model's generic candidates: a part of its own, from the same network run


class FrameProposer:
    """The configured proposer, split by what each part needs.

    *Model parts* (``MODELS``, and the ONNX model's generic candidates) look at the left
    image alone: ``propose_images`` runs them on a batch of frames, in this process or on a
    proposal stage of their own (a GPU actor, ``mining/pipeline/proposal_stage.py``).
    *Frame parts* (``stereo``, ``json``) need the frame's geometry or its index and run where
    the geometry is. ``finish`` joins a frame's model parts with its frame parts through the
    union, in the configured order, so a frame's proposals are the same wherever its model
    parts ran. ``proposer(frame, geometry)`` does both for one frame.
    """

    def __init__(self, cfg: ProposalConfig, frame_size: tuple[int, int], models: bool = True,
                 frame_parts: bool = True):
        names = proposer_names(cfg.proposer)
        if not names:
            raise ConfigError("proposals.proposer is empty")
        self.cfg, self.frame_size = cfg, frame_size
        generic = "onnx" in names and cfg.onnx_generic.enabled
        # The generic candidates come last, so the union keeps them only where no other part proposed.
        self.names = names + ([GENERIC] if generic else [])
        self.model_names = [n for n in self.names if n in MODELS or n == GENERIC]
        self._frame_parts = {n: make_one(n, cfg, frame_size) for n in self.names
                             if frame_parts and n not in self.model_names}
        self._models = [_model(n, cfg, frame_size, generic) for n in self.model_names
                        if models and n != GENERIC]

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


ModelBatch = Callable[[list[int], list[np.ndarray]], list[list[Proposals]]]


def _model(name: str, cfg: ProposalConfig, frame_size: tuple[int, int], generic: bool) -> ModelBatch:
    """A model part as a batch function: frames → per frame, its proposals (the ONNX model's
    generic candidates beside its own when ``generic``: one network run serves both)."""
    if name == "onnx":
        from mining.proposals.onnx_generic import generic_candidates
        from mining.proposals.onnx_yolo import OnnxProposer
        from mining.proposals.yolo_seg import decode_predictions

        model = OnnxProposer(cfg.onnx, frame_size=frame_size)

        def onnx(frames: list[int], images: list[np.ndarray]) -> list[list[Proposals]]:
            out = []
            for frame, image, (pred, protos, lb) in zip(frames, images, model.raw_outputs_batch(frames, images)):
                hw = image.shape[:2]
                own = decode_predictions(frame, pred, protos, lb, hw, cfg.onnx)
                out.append([own, generic_candidates(frame, pred, protos, lb, hw, cfg.onnx, cfg.onnx_generic)]
                           if generic else [own])
            return out
        return onnx
    if name == "torch":
        from mining.proposals.mprcnn_torch import TorchProposer  # a ConfigError naming the extra without torch

        mprcnn = TorchProposer(cfg.torch)
        return lambda frames, images: [[p] for p in mprcnn.propose_batch(frames, images)]
    if name == "fastsam":
        from mining.proposals.fastsam import FastSamProposer

        fastsam = FastSamProposer(cfg.fastsam, frame_size=frame_size)
        return lambda frames, images: [[fastsam(f, im)] for f, im in zip(frames, images)]
    if name == "sam":
        from mining.proposals.sam import SamProposer

        sam = SamProposer(cfg.sam)
        return lambda frames, images: [[sam(f, im)] for f, im in zip(frames, images)]
    raise ConfigError(f"proposals.proposer: {name!r} is not a model proposer; models: {MODELS}")


def make_proposer(cfg: ProposalConfig, frame_size: tuple[int, int]) -> FrameProposer:
    """``frame_size`` is (height, width)."""
    return FrameProposer(cfg, frame_size)
