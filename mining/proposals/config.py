"""Proposal-stage settings. REFERENCE values from ../shared/docs/REFERENCE.md §5 unless marked ours."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Count, Fraction, OneOf, Positive, Range, Satisfies, Signed
from mining.proposals.registry import unknown_proposers
from mining.proposals.stereo_config import StereoProposerConfig


def _input_side(v: int | str) -> str | None:
    if v == "auto" or (isinstance(v, int) and v > 0 and v % 32 == 0):
        return None
    return "must be 'auto' or a positive multiple of 32 (the YOLO family's largest stride)"


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
    device: Annotated[str, OneOf(("cpu", "cuda", "auto"))] = "cpu"  # ours: onnxruntime provider: "cpu", "cuda" (onnxruntime-gpu, refused without it) or "auto" (CUDA where installed)
    pad_value: Annotated[int, Range(0, 255)] = 114  # ours: letterbox grey the YOLO family was trained with


@dataclass
class OnnxGenericConfig:
    """Generic candidates from the ONNX model's anchors below its score cut (mining/proposals/onnx_generic.py)."""

    enabled: bool = True  # ours (issue 29): on — unknown objects proposed 53 → 73 % on seeds 0000–0003 with the unary refit on them (docs/RESULTS.md); false = the proposals before issue 29
    min_score: Fraction = 0.001  # ours: anchors with best class score in [min_score, onnx.score_threshold); 0.001 = ten times below the decoder's cut
    nms_iou: Fraction = 0.7  # ours: their own class-agnostic NMS, as onnx.nms_iou (Ultralytics' default)
    max_proposals: Count = 300  # REFERENCE: at most 300 kept, best score first, as onnx.max_proposals (on seeds 0000–0006 a cap of 1000 keeps no more)


@dataclass
class FastSamConfig:
    """FastSAM-s/x ("everything" mode, class-agnostic) as a YOLOv8-seg ONNX export (``fastsam`` proposer).

    The layout of mining/proposals/fastsam.py: output0 (1, 4 + K + 32, N) with K class rows (one
    for FastSAM), output1 (1, 32, h/4, w/4) prototypes. Sizes as ``[proposals.onnx]``: both
    ``"auto"`` (the frame's aspect, long side at most ``auto_max_side``) or both multiples of 32;
    a fixed-size export at another size is rebuilt for it once (onnx_convert), a dynamic one runs as is.
    """

    model_path: str = ""  # ours: user-given FastSAM ONNX export (weights are not bundled)
    cache_dir: str = ""  # ours: where resized models are kept; "" = ~/.cache/tube_miner/onnx
    input_height: Annotated[int | str, Satisfies(_input_side)] = "auto"  # ours: "auto" = the frame's aspect (KITTI → 320×1024 at auto_max_side 1024)
    input_width: Annotated[int | str, Satisfies(_input_side)] = "auto"  # ours: see input_height
    auto_max_side: Annotated[int, Range(32)] = 1024  # FastSAM README: imgsz=1024 (the size it was trained and is run at)
    score_threshold: Fraction = 0.05  # ours: low for recall (FastSAM README's everything mode: conf=0.4; Ultralytics' default 0.25)
    nms_iou: Fraction = 0.9  # FastSAM README: iou=0.9 (masks of parts and wholes overlap on purpose; Ultralytics' default 0.7)
    max_proposals: Count = 300  # REFERENCE: sorted by score, at most 300 kept (as onnx)
    mask_threshold: Fraction = 0.5  # Ultralytics: sigmoid mask probability cut (as onnx)
    intra_op_num_threads: int = 1  # ours: one thread per proposer; Ray parallelises over actors (as onnx)
    pad_value: Annotated[int, Range(0, 255)] = 114  # Ultralytics: letterbox grey of the YOLOv8 family FastSAM is trained in


@dataclass
class SamConfig:
    """SAM-family automatic masks (SAM ViT-B/L/H, MobileSAM) through onnxruntime: the GPU worker's proposer.

    Two user files (mining/proposals/sam.py): the image encoder (input (1, 3, S, S), normalised and
    padded; output the image embeddings), run once a frame, and the mask decoder in the official SAM
    ONNX export layout, run for a grid of ``points_per_side``² points, ``points_per_batch`` at a
    time where the export takes a batch (one point per run where it does not). The cost grows with
    the grid: on a CPU 25–50 s a frame with SAM ViT-B/H at 32×32, so run it where a GPU is
    (``device``) or on a coarser grid. Filters and their defaults are SAM's automatic mask generator's.
    """

    encoder_path: str = ""  # ours: user-given image encoder ONNX file (weights are not bundled)
    decoder_path: str = ""  # ours: user-given mask decoder ONNX file (SAM's scripts/export_onnx_model.py layout)
    input_size: Annotated[int, Range(16)] = 1024  # SAM / MobileSAM: long side resized to 1024 (ResizeLongestSide), padded square
    points_per_side: Annotated[int, Range(1, 256)] = 32  # SAM automatic mask generator default: a 32×32 grid (1024 prompts a frame)
    points_per_batch: Count = 64  # SAM automatic mask generator default: prompts per decoder run (when the export takes a batch)
    pred_iou_thresh: Fraction = 0.88  # SAM automatic mask generator default: the decoder's predicted IoU cut
    stability_score_thresh: Fraction = 0.95  # SAM automatic mask generator default: IoU of the mask at logit cuts ±offset
    stability_score_offset: Positive = 1.0  # SAM automatic mask generator default: logit offset of the stability score
    box_nms_thresh: Fraction = 0.7  # SAM automatic mask generator default: box NMS over all masks by predicted IoU
    min_region_area: int = 0  # SAM automatic mask generator default (min_mask_region_area 0 = off): holes and islands below this many pixels removed
    max_proposals: Count = 300  # REFERENCE: sorted by score, at most 300 kept (as onnx)
    device: Annotated[str, OneOf(("auto", "cpu", "cuda"))] = "auto"  # ours: "auto" = onnxruntime's CUDA provider when installed (onnxruntime-gpu), else the CPU
    intra_op_num_threads: int = 1  # ours: CPU threads per proposer, as onnx; 0 = onnxruntime's default (all cores)


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
    precision: Annotated[str, OneOf(("fp32", "fp16"))] = "fp32"  # ours: "fp16" = autocast to half on a CUDA device (refused on the CPU); fp32 is torchvision's


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
    proposer: Annotated[str, Satisfies(unknown_proposers)] = "stereo"  # ours: "stereo" (weight-free default), "onnx", "torch", "json", "fastsam", "sam", or a union: "onnx+stereo"
    onnx: OnnxConfig = field(default_factory=OnnxConfig)
    onnx_generic: OnnxGenericConfig = field(default_factory=OnnxGenericConfig)
    fastsam: FastSamConfig = field(default_factory=FastSamConfig)
    sam: SamConfig = field(default_factory=SamConfig)
    torch: TorchConfig = field(default_factory=TorchConfig)
    json: JsonProposalsConfig = field(default_factory=JsonProposalsConfig)
    kitti_detections: KittiDetectionsConfig = field(default_factory=KittiDetectionsConfig)
    union: UnionConfig = field(default_factory=UnionConfig)
    stereo: StereoProposerConfig = field(default_factory=StereoProposerConfig)

