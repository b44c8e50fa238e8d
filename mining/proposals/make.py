"""Build the configured proposer: one name or a union such as ``"onnx+stereo"``.

Every proposer is called as ``proposer(frame, geometry) -> Proposals``. Proposers that
hold a model load it once, in the constructor.
"""

from __future__ import annotations

from collections.abc import Callable

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


def _with_generic(names: list[str], cfg: ProposalConfig, frame_size: tuple[int, int]) -> list[Proposer]:
    """The parts of ``names`` with the ONNX model's generic candidates (``proposals.onnx_generic``) as
    one more class-agnostic part, last, so they only add what the others did not find; one network run
    per frame serves both ONNX parts."""
    from mining.proposals.onnx_generic import SharedOnnxRun
    from mining.proposals.onnx_yolo import OnnxProposer, decode_predictions

    run = SharedOnnxRun(OnnxProposer(cfg.onnx, frame_size=frame_size))

    def onnx(frame: StereoFrame, geometry: FrameGeometry) -> Proposals:
        pred, protos, lb = run.outputs(frame.index, frame.left)
        return decode_predictions(frame.index, pred, protos, lb, frame.left.shape[:2], cfg.onnx)

    parts = [onnx if n == "onnx" else make_one(n, cfg, frame_size) for n in names]
    return parts + [lambda frame, geometry: run.generic(frame.index, frame.left, cfg.onnx_generic)]


def make_proposer(cfg: ProposalConfig, frame_size: tuple[int, int]) -> Proposer:
    """``frame_size`` is (height, width)."""
    names = proposer_names(cfg.proposer)
    if not names:
        raise ConfigError("proposals.proposer is empty")
    if "onnx" in names and cfg.onnx_generic.enabled:
        parts = _with_generic(names, cfg, frame_size)
    else:
        parts = [make_one(n, cfg, frame_size) for n in names]
    if len(parts) == 1:
        return parts[0]
    return lambda frame, geometry: union([p(frame, geometry) for p in parts], cfg.union.mask_iou, cfg.union,
                                         geometry.disparity, geometry.depth)
