"""Tiny random-weight ONNX models in the real graph layouts of the class-agnostic proposers.

No weights can be downloaded and none are bundled: these graphs have the input and output
names, shapes and layouts of the real exports (FastSAM's YOLOv8-seg head; SAM's image encoder
and its official mask-decoder export) with a few random convolutions inside, so the proposers'
contracts can be tested in seconds. They say nothing about accuracy.

* ``fastsam_onnx``: input ``images`` (1, 3, h, w); output0 (1, 4 + K + 32, N) = cx, cy, w, h
  (input pixels, decoded from the anchor-grid and stride constants as a fixed-size Ultralytics
  export holds them), K sigmoid scores, 32 coefficients; output1 (1, 32, h/4, w/4) prototypes.
* ``sam_encoder_onnx``: input ``x`` (1, 3, S, S) → ``image_embeddings`` (1, C, S/16, S/16).
* ``sam_decoder_onnx``: inputs image_embeddings, point_coords (B, P, 2), point_labels (B, P),
  mask_input (1, 1, 4e, 4e), has_mask_input (1,), orig_im_size (2,); outputs masks (B, M, H, W)
  (SAM's postprocessing: bilinear to S×S, crop to the resized frame, bilinear to orig_im_size),
  iou_predictions (B, M), low_res_masks (B, M, 4e, 4e). Each mask is a blob around the first
  point (radius per mask token) plus an image term, so masks differ from point to point.
  ``batch=None`` declares B symbolic (a batched export); ``batch=1`` is the official export.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

IR_VERSION = 8  # what the installed onnxruntime reads
OPSET = 17  # SAM's export script default


def _save(graph, path: Path) -> Path:
    import onnx
    from onnx import helper

    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=IR_VERSION)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def fastsam_onnx(path: Path, height: int = 64, width: int = 64, n_classes: int = 1, n_coeffs: int = 32,
                 seed: int = 0, proto_channels: int | None = None, batch: int | None = 1) -> Path:
    """A YOLOv8-seg-layout model (FastSAM: ``n_classes`` = 1; the COCO YOLO layout: 80) with random
    weights; ``proto_channels`` other than ``n_coeffs`` makes an off-layout model; ``batch=None``
    declares the batch axis symbolic (an export with a batch axis; 1 is the usual fixed export)."""
    proto_channels = n_coeffs if proto_channels is None else proto_channels
    from onnx import TensorProto as T
    from onnx import helper, numpy_helper

    rng = np.random.default_rng(seed)
    strides = (8, 16, 32)
    rows = 4 + n_classes + n_coeffs
    inits, nodes, levels = [], [], []
    for s in strides:
        w = rng.normal(0, 0.05, (rows, 3, s, s)).astype(np.float32)
        b = rng.normal(0, 1.0, rows).astype(np.float32)
        inits += [numpy_helper.from_array(w, f"head{s}.w"), numpy_helper.from_array(b, f"head{s}.b")]
        nodes.append(helper.make_node("Conv", ["images", f"head{s}.w", f"head{s}.b"], [f"feat{s}"],
                                      kernel_shape=[s, s], strides=[s, s]))
        nodes.append(helper.make_node("Reshape", [f"feat{s}", "flat_shape"], [f"flat{s}"]))
        levels.append(f"flat{s}")
    inits.append(numpy_helper.from_array(np.array([0 if batch is None else batch, rows, -1], np.int64), "flat_shape"))
    nodes.append(helper.make_node("Concat", levels, ["raw"], axis=2))
    inits.append(numpy_helper.from_array(np.array([4, n_classes, n_coeffs], np.int64), "split"))
    nodes.append(helper.make_node("Split", ["raw", "split"], ["dist", "cls", "coef"], axis=1))
    # Box from distances to the anchor centre (cell units) × stride, as YOLOv8's head decodes it.
    from mining.proposals.onnx_convert import anchor_grid

    grid, stride_of = anchor_grid(height, width, list(strides))
    inits += [numpy_helper.from_array(grid[None].astype(np.float32), "anchors"),
              numpy_helper.from_array(stride_of[None].astype(np.float32), "strides"),
              numpy_helper.from_array(np.array([3.0], np.float32), "reach"),
              numpy_helper.from_array(np.array([0.5], np.float32), "half")]
    nodes += [
        helper.make_node("Sigmoid", ["dist"], ["dist_s"]),
        helper.make_node("Mul", ["dist_s", "reach"], ["ltrb"]),
        helper.make_node("Split", ["ltrb", "two_two"], ["lt", "rb"], axis=1),
        helper.make_node("Sub", ["anchors", "lt"], ["x1y1"]),
        helper.make_node("Add", ["anchors", "rb"], ["x2y2"]),
        helper.make_node("Add", ["x1y1", "x2y2"], ["sum"]),
        helper.make_node("Mul", ["sum", "half"], ["cxcy"]),
        helper.make_node("Sub", ["x2y2", "x1y1"], ["wh"]),
        helper.make_node("Concat", ["cxcy", "wh"], ["box_cells"], axis=1),
        helper.make_node("Mul", ["box_cells", "strides"], ["box"]),
        helper.make_node("Sigmoid", ["cls"], ["score"]),
        helper.make_node("Concat", ["box", "score", "coef"], ["output0"], axis=1),
    ]
    inits.append(numpy_helper.from_array(np.array([2, 2], np.int64), "two_two"))
    wp = rng.normal(0, 0.3, (proto_channels, 3, 4, 4)).astype(np.float32)
    inits.append(numpy_helper.from_array(wp, "proto.w"))
    nodes.append(helper.make_node("Conv", ["images", "proto.w"], ["output1"], kernel_shape=[4, 4], strides=[4, 4]))
    b = "batch" if batch is None else batch
    graph = helper.make_graph(
        nodes, "fastsam_tiny",
        [helper.make_tensor_value_info("images", T.FLOAT, [b, 3, height, width])],
        [helper.make_tensor_value_info("output0", T.FLOAT, [b, rows, grid.shape[1]]),
         helper.make_tensor_value_info("output1", T.FLOAT, [b, proto_channels, height // 4, width // 4])],
        inits)
    return _save(graph, path)


def sam_encoder_onnx(path: Path, size: int = 128, channels: int = 8, seed: int = 1) -> Path:
    """SAM's image encoder stand-in: (1, 3, S, S) normalised image → (1, C, S/16, S/16) embeddings."""
    from onnx import TensorProto as T
    from onnx import helper, numpy_helper

    rng = np.random.default_rng(seed)
    w = rng.normal(0, 0.02, (channels, 3, 16, 16)).astype(np.float32)
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w"], ["image_embeddings"], kernel_shape=[16, 16], strides=[16, 16])],
        "sam_encoder_tiny",
        [helper.make_tensor_value_info("x", T.FLOAT, [1, 3, size, size])],
        [helper.make_tensor_value_info("image_embeddings", T.FLOAT, [1, channels, size // 16, size // 16])],
        [numpy_helper.from_array(w, "w")])
    return _save(graph, path)


DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size")
DECODER_OUTPUTS = ("masks", "iou_predictions", "low_res_masks")


def sam_decoder_onnx(path: Path, size: int = 128, channels: int = 8, n_masks: int = 4, batch: int | None = None,
                     drop_input: str | None = None) -> Path:
    """SAM's mask decoder stand-in in the official export's I/O layout (module docstring)."""
    from onnx import TensorProto as T
    from onnx import helper, numpy_helper

    e = size // 16
    low = 4 * e
    cell = size / low
    yy, xx = np.meshgrid((np.arange(low) + 0.5) * cell, (np.arange(low) + 0.5) * cell, indexing="ij")
    radii = np.array([0.10, 0.06, 0.12, 0.2][:n_masks] + [0.15] * max(0, n_masks - 4), np.float32) * size
    iou_bias = np.array([2.3, 1.6, 2.4, 3.2][:n_masks] + [2.5] * max(0, n_masks - 4), np.float32)
    c = lambda name, a: numpy_helper.from_array(np.asarray(a), name)  # noqa: E731
    inits = [
        c("gx", xx[None, None].astype(np.float32)), c("gy", yy[None, None].astype(np.float32)),
        c("inv_r2", (1.0 / radii ** 2).reshape(1, -1, 1, 1).astype(np.float32)),
        c("gain", np.array([60.0], np.float32)), c("one", np.array([1.0], np.float32)),
        c("img_gain", np.array([20.0], np.float32)),
        c("iou_bias", iou_bias[None]), c("iou_slope", np.array([3.0], np.float32)),
        c("inv_size", np.array([1.0 / size], np.float32)), c("centre", np.array([0.5], np.float32)),
        c("idx0", np.array(0, np.int64)), c("idx1", np.array(1, np.int64)),
        c("bshape", np.array([-1, 1, 1, 1], np.int64)), c("wshape", np.array([-1, 1], np.int64)),
        c("low_hw", np.array([low, low], np.int64)), c("sq_hw", np.array([size, size], np.int64)),
        c("s_f", np.array([float(size)], np.float32)), c("half", np.array([0.5], np.float32)),
        c("zeros2", np.array([0, 0], np.int64)), c("axes23", np.array([2, 3], np.int64)),
    ]
    nodes = [
        # first point of each prompt: (B, 2) → px, py as (B, 1, 1, 1)
        helper.make_node("Gather", ["point_coords", "idx0"], ["p0"], axis=1),
        helper.make_node("Gather", ["p0", "idx0"], ["px_"], axis=1),
        helper.make_node("Gather", ["p0", "idx1"], ["py_"], axis=1),
        helper.make_node("Reshape", ["px_", "bshape"], ["px"]),
        helper.make_node("Reshape", ["py_", "bshape"], ["py"]),
        helper.make_node("Sub", ["gx", "px"], ["dx"]), helper.make_node("Sub", ["gy", "py"], ["dy"]),
        helper.make_node("Mul", ["dx", "dx"], ["dx2"]), helper.make_node("Mul", ["dy", "dy"], ["dy2"]),
        helper.make_node("Add", ["dx2", "dy2"], ["d2"]),
        helper.make_node("Mul", ["d2", "inv_r2"], ["d2r"]),  # (B, M, L, L)
        helper.make_node("Sub", ["one", "d2r"], ["blob"]),
        helper.make_node("Mul", ["blob", "gain"], ["blob_g"]),
        # image term: the mean embedding, upsampled to the low-res grid
        helper.make_node("ReduceMean", ["image_embeddings"], ["emb_mean"], axes=[1], keepdims=1),
        helper.make_node("Shape", ["emb_mean"], ["emb_shape"], start=0, end=2),
        helper.make_node("Concat", ["emb_shape", "low_hw"], ["emb_sizes"], axis=0),
        helper.make_node("Resize", ["emb_mean", "", "", "emb_sizes"], ["emb_up"], mode="linear"),
        helper.make_node("Mul", ["emb_up", "img_gain"], ["emb_g"]),
        helper.make_node("Add", ["blob_g", "emb_g"], ["low_res_masks"]),
        # predicted IoU: a per-token bias and a slope across the frame
        helper.make_node("Mul", ["px_", "inv_size"], ["pxn"]),
        helper.make_node("Sub", ["pxn", "centre"], ["pxc"]),
        helper.make_node("Reshape", ["pxc", "wshape"], ["pxc2"]),
        helper.make_node("Mul", ["pxc2", "iou_slope"], ["slope"]),
        helper.make_node("Add", ["slope", "iou_bias"], ["iou_logit"]),
        helper.make_node("Sigmoid", ["iou_logit"], ["iou_predictions"]),
        # SAM's mask postprocessing: to S×S, crop to the resized frame, to orig_im_size
        helper.make_node("Shape", ["low_res_masks"], ["lr_shape"], start=0, end=2),
        helper.make_node("Concat", ["lr_shape", "sq_hw"], ["sq_sizes"], axis=0),
        helper.make_node("Resize", ["low_res_masks", "", "", "sq_sizes"], ["sq"], mode="linear"),
        helper.make_node("ReduceMax", ["orig_im_size"], ["long_side"], keepdims=1),
        helper.make_node("Div", ["s_f", "long_side"], ["scale"]),
        helper.make_node("Mul", ["orig_im_size", "scale"], ["pre_f"]),
        helper.make_node("Add", ["pre_f", "half"], ["pre_h"]),
        helper.make_node("Floor", ["pre_h"], ["pre_fl"]),
        helper.make_node("Cast", ["pre_fl"], ["pre"], to=T.INT64),
        helper.make_node("Slice", ["sq", "zeros2", "pre", "axes23"], ["cropped"]),
        helper.make_node("Cast", ["orig_im_size"], ["orig_i"], to=T.INT64),
        helper.make_node("Concat", ["lr_shape", "orig_i"], ["orig_sizes"], axis=0),
        helper.make_node("Resize", ["cropped", "", "", "orig_sizes"], ["masks"], mode="linear"),
    ]
    b = "batch" if batch is None else batch
    inputs = {
        "image_embeddings": helper.make_tensor_value_info("image_embeddings", T.FLOAT, [1, channels, e, e]),
        "point_coords": helper.make_tensor_value_info("point_coords", T.FLOAT, [b, "num_points", 2]),
        "point_labels": helper.make_tensor_value_info("point_labels", T.FLOAT, [b, "num_points"]),
        "mask_input": helper.make_tensor_value_info("mask_input", T.FLOAT, [1, 1, low, low]),
        "has_mask_input": helper.make_tensor_value_info("has_mask_input", T.FLOAT, [1]),
        "orig_im_size": helper.make_tensor_value_info("orig_im_size", T.FLOAT, [2]),
    }
    if drop_input:  # a broken export: feed a constant where the input was
        del inputs[drop_input]
        if drop_input == "orig_im_size":
            inits.append(c(drop_input, np.array([96.0, 320.0], np.float32)))
    outputs = [helper.make_tensor_value_info("masks", T.FLOAT, [b, n_masks, "height", "width"]),
               helper.make_tensor_value_info("iou_predictions", T.FLOAT, [b, n_masks]),
               helper.make_tensor_value_info("low_res_masks", T.FLOAT, [b, n_masks, low, low])]
    graph = helper.make_graph(nodes, "sam_decoder_tiny", list(inputs.values()), outputs, inits)
    return _save(graph, path)


def encoder_onnx(path: Path, dim: int = 16, size: int | None = 32, tokens: int | None = None,
                 batch: int | str | None = "batch", seed: int = 3, elem_type: int | None = None,
                 out_rank: int | None = None) -> Path:
    """An image encoder in the layout ``mine embed`` reads (mining/discovery/embed.py): input ``pixel_values``
    (B, 3, H, W) float32 → a conv, ReLU, a global average pool and a linear map to ``dim``: output
    ``embeds`` (B, D), or with ``tokens`` (B, T, D) whose first token is that vector and the others
    scaled copies (a ViT's CLS token first). ``size`` None declares H and W symbolic; ``batch`` None
    or a name declares B symbolic, an int fixes it. ``elem_type`` / ``out_rank`` make off-contract
    models (another input type; an output of another rank)."""
    from onnx import TensorProto as T
    from onnx import helper, numpy_helper

    rng = np.random.default_rng(seed)
    ch = 8
    inits = [numpy_helper.from_array(rng.normal(0, 0.5, (ch, 3, 3, 3)).astype(np.float32), "conv.w"),
             numpy_helper.from_array(rng.normal(0, 0.1, ch).astype(np.float32), "conv.b"),
             numpy_helper.from_array(rng.normal(0, 1.0, (ch, dim)).astype(np.float32), "fc.w"),
             numpy_helper.from_array(rng.normal(0, 0.1, dim).astype(np.float32), "fc.b"),
             numpy_helper.from_array(np.array([0, -1], np.int64), "flat")]
    nodes = [helper.make_node("Conv", ["pixel_values", "conv.w", "conv.b"], ["c"], kernel_shape=[3, 3], strides=[2, 2]),
             helper.make_node("Relu", ["c"], ["r"]),
             helper.make_node("GlobalAveragePool", ["r"], ["g"]),
             helper.make_node("Reshape", ["g", "flat"], ["f"]),
             helper.make_node("MatMul", ["f", "fc.w"], ["m"]),
             helper.make_node("Add", ["m", "fc.b"], ["vec"])]
    b = batch
    out_shape: list = [b, dim]
    out = "vec"
    if tokens:
        scales = np.linspace(1.0, 0.2, tokens).astype(np.float32).reshape(1, tokens, 1)
        inits += [numpy_helper.from_array(np.array([1], np.int64), "axis1"),
                  numpy_helper.from_array(scales, "scales")]
        nodes += [helper.make_node("Unsqueeze", ["vec", "axis1"], ["v3"]),
                  helper.make_node("Mul", ["v3", "scales"], ["tok"])]
        out, out_shape = "tok", [b, tokens, dim]
    if out_rank == 4:
        inits.append(numpy_helper.from_array(np.array([2, 3], np.int64), "axes23"))
        nodes.append(helper.make_node("Unsqueeze", [out, "axes23"], ["v4"]))
        out, out_shape = "v4", [*out_shape, 1, 1]
    nodes.append(helper.make_node("Identity", [out], ["embeds"]))
    side = size if size is not None else "height"
    graph = helper.make_graph(
        nodes, "encoder_tiny",
        [helper.make_tensor_value_info("pixel_values", elem_type or T.FLOAT,
                                       [b, 3, side, size if size is not None else "width"])],
        [helper.make_tensor_value_info("embeds", T.FLOAT, out_shape)], inits)
    return _save(graph, path)
