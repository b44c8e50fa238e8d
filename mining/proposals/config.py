"""Proposal-stage settings. REFERENCE values from ../shared/docs/REFERENCE.md §5 unless marked ours."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Count, Fraction, OneOf, Positive, Range, Satisfies, Signed
from mining.proposals.stereo_config import StereoProposerConfig


def _input_side(v: int | str) -> str | None:
    if v == "auto" or (isinstance(v, int) and v > 0 and v % 32 == 0):
        return None
    return "must be 'auto' or a positive multiple of 32 (the YOLO family's largest stride)"


def _proposer_names(v: str) -> str | None:
    from mining.proposals.make import unknown_proposers  # the names live beside the code that makes them

    return unknown_proposers(v)


@dataclass
class OnnxConfig:
    """A YOLO-seg-family ONNX instance segmentation model run through onnxruntime.

    The project ships no weights: ``model_path`` is always the user's. Input sizes are either
    both ``"auto"`` (the frame's own size, scaled down to ``auto_max_side`` if larger, rounded
    up to multiples of 32) or both pixel counts that are multiples of 32.
    """

    model_path: str = ""  # ours: user-given model file (weights are not bundled: AGPL-3.0)
    cache_dir: str = ""  # ours: where converted float models are kept; "" = ~/.cache/tube_miner/onnx
    input_height: Annotated[int | str, Satisfies(_input_side)] = "auto"  # ours: "auto" = the frame's aspect; 320 squashes KITTI to 320×97
    input_width: Annotated[int | str, Satisfies(_input_side)] = "auto"  # ours: see input_height
    auto_max_side: Annotated[int, Range(32)] = 1280  # ours: "auto" never runs larger than this on the long side (KITTI 1242 → 1248)
    score_threshold: Fraction = 0.01  # ours: low on purpose, proposals live on recall (REFERENCE's 0.8 cut is a ⚠)
    nms_iou: Fraction = 0.7  # ours: class-agnostic NMS box IoU (Ultralytics' default); tubes prune the rest
    max_proposals: Count = 300  # REFERENCE: sorted by score, at most 300 kept
    mask_threshold: Fraction = 0.5  # ours: sigmoid mask probability cut (Ultralytics' choice)
    intra_op_num_threads: int = 1  # ours: one thread per proposer; Ray parallelises over actors
    pad_value: Annotated[int, Range(0, 255)] = 114  # ours: letterbox grey the YOLO family was trained with


@dataclass
class OnnxGenericConfig:
    """Generic candidates from the ONNX model's anchors below its score cut (mining/proposals/onnx_generic.py)."""

    enabled: bool = False  # ours: off = today's proposals; on = the "onnx" proposer also gives its low-score anchors as class-agnostic "onnx_generic" rows
    min_score: Fraction = 0.001  # ours: anchors with best class score in [min_score, onnx.score_threshold); 0.001 = ten times below the decoder's cut
    nms_iou: Fraction = 0.7  # ours: their own class-agnostic NMS, as onnx.nms_iou (Ultralytics' default)
    max_proposals: Count = 300  # REFERENCE: at most 300 kept, best score first, as onnx.max_proposals (on seeds 0000–0006 a cap of 1000 keeps no more)


@dataclass
class TorchConfig:
    """MP R-CNN (the paper's proposer) on torchvision's Mask R-CNN ResNet-50 FPN (extra ``torch``).

    The project ships no weights: ``model_path`` is always the user's, a state dict in
    torchvision's maskrcnn_resnet50_fpn COCO layout or MP R-CNN's two-head layout
    (mining/proposals/mprcnn_torch.py). Frames are resized as torchvision's transform does:
    the short side to ``min_size`` unless the long side would pass ``max_size``.
    """

    model_path: str = ""  # ours: user-given state dict (weights are neither bundled nor downloaded)
    device: str = "auto"  # ours: "auto" = CUDA when present, else the CPU; or "cpu", "cuda", "cuda:N"
    batch_size: int = 4  # ours: frames per forward pass in propose_batch
    min_size: int = 800  # torchvision MaskRCNN default: short side resized to 800...
    max_size: int = 1333  # torchvision MaskRCNN default: ...long side at most 1333 (KITTI 1242×375 → 1333×402)
    rpn_pre_nms_top_n: int = 1000  # torchvision default rpn_pre_nms_top_n_test: anchors per FPN level before RPN NMS
    rpn_post_nms_top_n: int = 1000  # torchvision default rpn_post_nms_top_n_test: RoIs per frame the box head scores
    score_threshold: float = 0.05  # torchvision box_score_thresh (Mask R-CNN's test cut): low, proposals live on recall
    nms_iou: float = 0.5  # torchvision box_nms_thresh (Mask R-CNN's test NMS), here class-agnostic
    max_proposals: int = 300  # REFERENCE: sorted by score, at most 300 kept
    mask_threshold: float = 0.5  # torchvision / Mask R-CNN: mask probability ≥ 0.5 is the object
    # "background": the class head's p(background) is the unknown mass (the original's second_posterior[0]);
    # "none": the 80 class probabilities renormalised, unknown 0.
    unknown_mass: str = "background"  # original implementation (see above); "none" is ours
    batch_norm_eps: float = 0.0  # torchvision: runs its COCO Mask R-CNN weights with frozen batch norm eps 0
    num_threads: int = 1  # ours: CPU threads per proposer, as onnx (Ray parallelises over actors); 0 = torch's default


@dataclass
class JsonProposalsConfig:
    """Per-frame proposal files in the original 4D-GVT JSON format (``precomputed`` proposer)."""

    folder: str = ""  # ours: user-given folder of NNNNNN.json files, one per frame
    filename_digits: Count = 6  # ours: zero-padded frame index in the file name (4D-GVT files: 000042.json)
    category_ids: Annotated[str, OneOf(("agnostic", "coco"))] = "agnostic"  # ours: category_id without second_posterior: "agnostic" (no classes) or "coco" ids
    # Bounds on what one frame's file may cost a worker: the file is refused above max_file_bytes
    # (read as text once, its proposals parsed one at a time), and of more than max_proposals
    # only the best by score are kept, before any mask is decoded.
    max_file_bytes: Count = 64 * 2**20  # ours: 64 MiB, ~390× the largest shared file (171 KB, 500 proposals); a worker holds it about twice
    max_proposals: Count = 1000  # ours: twice the 500 the authors advise at most (REFERENCE); localise.filters keeps its own max_proposals of these later


@dataclass
class KittiDetectionsConfig:
    """KITTI tracking detection files (PointRCNN comma files or 18-column results) as box-mask proposals.

    objectness = 1 / (1 + exp(−(score − score_offset) / score_scale)): the detectors' scores are
    unbounded. Defaults: maximum-likelihood logistic fit of "detection matches a label_02 box of
    its class (Car~Van, Pedestrian~Person, Cyclist) at box IoU ≥ 0.5, greedy by score" on all
    PointRCNN detections of the 12 train sequences (45,711, unmatched ones in DontCare left
    out); per class the offsets are Car 2.76, Pedestrian 2.42, Cyclist 3.55. Optimistic:
    PointRCNN was trained on the same drives (SOURCES.md §6). Other detectors (Regionlets,
    scores −9…18) need their own values.
    """

    path: str = ""  # ours: a file, or a folder of <seq>.txt (results) or <Class>/<seq>.txt (PointRCNN)
    score_offset: Signed = 2.67  # ours: raw score at objectness 0.5; logistic fit, PointRCNN vs label_02
    score_scale: Positive = 1.02  # ours: raw-score units per logit of objectness; same fit (per class 0.92–1.11)


@dataclass
class UnionConfig:
    """Several proposers' outputs merged into one set per frame."""

    mask_iou: Fraction = 0.5  # ours: same object above it (KITTI 0005 box vs YOLO masks separate there)
    # A class-agnostic proposal no classifier covers counts toward "unknown" with weight
    # 1 / (1 + exp(−(ln h − ln detect_h50_px) / detect_log_scale)), h its box height (union.py).
    detect_h50_px: Positive = 7.3  # ours: maximum-likelihood fit, `mine bench classify` (docs/RESULTS.md)
    detect_log_scale: Positive = 0.59  # ours: spread of that curve in ln(height); same fit
    better_mask: bool = False  # ours: off — the learned mask is better on average than the depth rule's (`mine bench classify`, docs/RESULTS.md)
    better_mask_margin: Fraction = 0.2  # ours: the later mask must agree better by this much (IoU with the depth region); `mine bench classify`
    depth_band_m: float = 2.5  # ours: depth extent of an object around its median (half a car's length + margin)
    band_noise_px: float = 1.0  # ours: disparity noise allowed on top of that band (2 × SGBM's ~0.5 px)


@dataclass
class ProposalConfig:
    proposer: Annotated[str, Satisfies(_proposer_names)] = "stereo"  # ours: "stereo" (weight-free default), "onnx", "torch", "json", or a union: "onnx+stereo"
    onnx: OnnxConfig = field(default_factory=OnnxConfig)
    onnx_generic: OnnxGenericConfig = field(default_factory=OnnxGenericConfig)
    torch: TorchConfig = field(default_factory=TorchConfig)
    json: JsonProposalsConfig = field(default_factory=JsonProposalsConfig)
    kitti_detections: KittiDetectionsConfig = field(default_factory=KittiDetectionsConfig)
    union: UnionConfig = field(default_factory=UnionConfig)
    stereo: StereoProposerConfig = field(default_factory=StereoProposerConfig)

