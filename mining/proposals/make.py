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
NAMES = ("stereo", "onnx", "torch", "json")


def _one(name: str, cfg: ProposalConfig, frame_size: tuple[int, int]) -> Proposer:
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
    if name == "json":
        from mining.proposals.precomputed import JsonProposals

        reader = JsonProposals(cfg.json.folder, cfg.json, image_size=(frame_size[1], frame_size[0]))
        return lambda frame, geometry: reader(frame.index, frame.left)
    raise ConfigError(f"proposals.proposer: unknown proposer {name!r}; known: {NAMES} or a union like 'onnx+stereo'")


def make_proposer(cfg: ProposalConfig, frame_size: tuple[int, int]) -> Proposer:
    """``frame_size`` is (height, width)."""
    names = [n.strip() for n in cfg.proposer.split("+") if n.strip()]
    if not names:
        raise ConfigError("proposals.proposer is empty")
    parts = [_one(n, cfg, frame_size) for n in names]
    if len(parts) == 1:
        return parts[0]
    return lambda frame, geometry: union([p(frame, geometry) for p in parts], cfg.union.mask_iou)
