"""Turn a YOLO-seg ONNX model into a float model for any input size.

The shared model (see ``../shared/models/SOURCES.md``) is dynamically quantised to int8 and
fixed at 320×320. A 1242×375 KITTI frame squashed into 320×320 loses most distant objects,
so we rebuild the graph once, at set-up time:

1. every ``DynamicQuantizeLinear → ConvInteger → Cast → Mul`` chain becomes a float ``Conv``
   with weight ``(q − zero_point) · weight_scale``. The activation scale is computed at run
   time by ``DynamicQuantizeLinear`` and multiplied in by the ``Mul``; in a float graph it
   simply disappears. The bias ``Add`` after the chain stays as it is.
2. the constants that depend on the input size — reshape shapes holding the anchor count
   ``N = Σ_s (H/s)(W/s)``, the anchor-centre grid and the stride tensor — are rebuilt for the
   new size, and the input is declared ``[1, 3, H, W]``.

Each replaced constant is checked against what it must have held for the old size, so a
graph that does not follow this layout is refused rather than silently mis-converted.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

from mining.errors import InputError
from mining.files import open_regular

CONVERTER_VERSION = 1  # bump when the conversion changes, so cached models are rebuilt


def _onnx():
    try:
        import onnx  # the optional `onnx` extra
    except ImportError:  # pragma: no cover - depends on the installation
        raise ImportError("model conversion needs the `onnx` package: pip install 'tube-miner[onnx]'") from None
    return onnx


def anchor_grid(height: int, width: int, strides: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Anchor centres (2, N) in input pixels / stride and their strides (N,).

    Centres are (x + 0.5, y + 0.5) in each stride's cell units, strides in the given order
    (smallest first), cells row-major — the order of the model's output columns.
    """
    centres, stride_of = [], []
    for s in strides:
        h, w = height // s, width // s
        yy, xx = np.meshgrid(np.arange(h, dtype=np.float32) + 0.5, np.arange(w, dtype=np.float32) + 0.5, indexing="ij")
        centres.append(np.stack([xx.ravel(), yy.ravel()]))
        stride_of.append(np.full(h * w, s, dtype=np.float32))
    return np.concatenate(centres, axis=1), np.concatenate(stride_of)


def _input_hw(model, path: Path) -> tuple[int, int]:
    dims = model.graph.input[0].type.tensor_type.shape.dim
    if len(dims) != 4 or not all(d.HasField("dim_value") for d in dims[2:]):
        raise InputError("expected a model with one fixed-size NCHW image input", path)
    return int(dims[2].dim_value), int(dims[3].dim_value)


def _dequantise_convs(model, path: Path) -> int:
    """Replace each quantised conv chain by a float Conv; returns how many were replaced."""
    _onnx()
    from onnx import helper, numpy_helper

    g = model.graph
    inits = {t.name: t for t in g.initializer}
    producer = {o: n for n in g.node for o in n.output}
    consumers = defaultdict(list)
    for n in g.node:
        for i in n.input:
            consumers[i].append(n)

    def only_consumer(name: str, op: str):
        users = consumers[name]
        if len(users) != 1 or users[0].op_type != op:
            raise InputError(f"quantised conv: {name!r} should feed exactly one {op}", path)
        return users[0]

    def const(name: str) -> np.ndarray:
        if name not in inits:
            raise InputError(f"quantised conv: {name!r} is not a constant", path)
        return numpy_helper.to_array(inits[name])

    # Nodes are keyed by their first output name (unique in a graph).
    new_nodes: dict[str, object] = {}  # ConvInteger output → float Conv replacing the chain
    dropped: set[str] = set()  # Cast and Mul outputs of replaced chains
    new_inits = []
    for n in g.node:
        if n.op_type != "ConvInteger":
            continue
        x_q, w_q, x_zp, w_zp = (list(n.input) + ["", "", "", ""])[:4]
        dql = producer.get(x_q)
        if dql is None or dql.op_type != "DynamicQuantizeLinear" or dql.output[0] != x_q or dql.output[2] != x_zp:
            raise InputError(f"ConvInteger {n.name!r}: its input is not a DynamicQuantizeLinear output", path)
        cast = only_consumer(n.output[0], "Cast")
        mul = only_consumer(cast.output[0], "Mul")
        # The Mul must scale by input_scale · weight_scale, the scale product of this chain.
        scale_name = mul.input[1] if mul.input[0] == cast.output[0] else mul.input[0]
        scales = producer.get(scale_name)
        if scales is None or scales.op_type != "Mul" or dql.output[1] not in scales.input:
            raise InputError(f"ConvInteger {n.name!r}: scale Mul does not use the activation scale", path)
        w_scale_name = scales.input[1] if scales.input[0] == dql.output[1] else scales.input[0]
        w_scale = const(w_scale_name).astype(np.float32)
        q = const(w_q).astype(np.float32)
        zp = const(w_zp).astype(np.float32) if w_zp else np.float32(0.0)
        # Per-tensor scales are scalars; per-channel ones run along the output channels.
        shape = (-1,) + (1,) * (q.ndim - 1)
        weight = (q - np.reshape(zp, shape if np.ndim(zp) else ())) * np.reshape(w_scale, shape if w_scale.ndim else ())
        w_name = w_q.replace("_quantized", "") + "_float"
        new_inits.append(numpy_helper.from_array(weight.astype(np.float32), w_name))
        attrs = {a.name: helper.get_attribute_value(a) for a in n.attribute}
        conv = helper.make_node("Conv", [dql.input[0], w_name], [mul.output[0]], name=n.name + "_float", **attrs)
        new_nodes[n.output[0]] = conv
        dropped.update({cast.output[0], mul.output[0]})  # the scale products die with them below

    nodes = []
    for n in g.node:
        if n.output[0] in new_nodes:
            nodes.append(new_nodes[n.output[0]])
        elif n.output[0] not in dropped:
            nodes.append(n)
    del g.node[:]
    g.node.extend(nodes)
    g.initializer.extend(new_inits)
    _remove_dead(model)
    left = [n.op_type for n in g.node if n.op_type in ("DynamicQuantizeLinear", "ConvInteger", "MatMulInteger")]
    if left:
        raise InputError(f"quantised nodes left after conversion: {sorted(set(left))}", path)
    return len(new_nodes)


def _remove_dead(model) -> None:
    """Drop nodes whose outputs nobody uses, then unused constants."""
    g = model.graph
    outputs = {o.name for o in g.output}
    while True:
        used = {i for n in g.node for i in n.input} | outputs
        keep = [n for n in g.node if any(o in used for o in n.output if o)]
        if len(keep) == len(g.node):
            break
        del g.node[:]
        g.node.extend(keep)
    used = {i for n in g.node for i in n.input}
    keep_inits = [t for t in g.initializer if t.name in used]
    del g.initializer[:]
    g.initializer.extend(keep_inits)


def _resize_constants(model, path: Path, old_hw: tuple[int, int], new_hw: tuple[int, int]) -> None:
    """Rebuild the anchor count, anchor grid and stride constants for the new input size."""
    from onnx import numpy_helper

    g = model.graph
    inits = {t.name: t for t in g.initializer}
    arrays = {k: numpy_helper.to_array(t) for k, t in inits.items()}
    # The stride tensor is the float constant shaped (1, N_old) whose values are the strides.
    stride_names = [k for k, a in arrays.items() if a.dtype == np.float32 and a.ndim == 2 and a.shape[0] == 1
                    and a.shape[1] > 1 and set(np.unique(a)) <= {8.0, 16.0, 32.0, 64.0}]
    if len(stride_names) != 1:
        raise InputError(f"expected one stride constant, found {len(stride_names)}", path)
    old_strides = arrays[stride_names[0]][0]
    strides = [int(s) for s in dict.fromkeys(old_strides.tolist())]  # in order of appearance
    old_grid, old_stride_of = anchor_grid(*old_hw, strides)
    n_old = old_grid.shape[1]
    if not np.array_equal(old_strides, old_stride_of):
        raise InputError(f"stride constant does not match input size {old_hw} and strides {strides}", path)
    for s in strides:
        if new_hw[0] % s or new_hw[1] % s:
            raise InputError(f"input size {new_hw} is not a multiple of the model's stride {s}", path)
    grid, stride_of = anchor_grid(*new_hw, strides)
    n_new = grid.shape[1]

    reshape_shapes = {n.input[1] for n in g.node if n.op_type == "Reshape"}
    replaced = {"grid": 0, "stride": 0, "shape": 0}
    for name, a in arrays.items():
        new = None
        if name in stride_names:
            new, kind = stride_of[None], "stride"
        elif a.dtype == np.float32 and a.shape == (1, 2, n_old):
            if not np.array_equal(a[0], old_grid):
                raise InputError(f"constant {name!r} looks like the anchor grid but does not match it", path)
            new, kind = grid[None], "grid"
        elif name in reshape_shapes and a.dtype == np.int64 and n_old in a.tolist():
            new, kind = np.where(a == n_old, n_new, a).astype(np.int64), "shape"
        if new is not None:
            inits[name].CopyFrom(numpy_helper.from_array(np.ascontiguousarray(new), name))
            replaced[kind] += 1
    if replaced["grid"] == 0:
        raise InputError("no anchor-grid constant found; cannot change the input size", path)
    leftover = [k for k, a in arrays.items() if n_old in a.shape and k not in stride_names
                and not (a.dtype == np.float32 and a.shape == (1, 2, n_old))]
    if leftover:
        raise InputError(f"constants sized by the old anchor count remain: {leftover}", path)


def convert_to_float(src_path: str | Path, dst_path: str | Path, height: int, width: int) -> Path:
    """Write a float copy of the YOLO-seg model at ``src_path`` with input ``[1, 3, height, width]``."""
    onnx = _onnx()
    src = Path(src_path)
    if not src.is_file():
        raise InputError("ONNX model not found", src)
    try:
        model = onnx.load(str(src))
    except Exception as e:  # onnx raises DecodeError and friends
        raise InputError(f"not a readable ONNX model: {e}", src) from None
    old_hw = _input_hw(model, src)
    _dequantise_convs(model, src)
    _resize_constants(model, src, old_hw, (height, width))

    g = model.graph
    dims = g.input[0].type.tensor_type.shape.dim
    dims[2].dim_value, dims[3].dim_value = height, width
    del g.value_info[:]  # intermediate shapes were for the old size; shape inference redoes them
    for out in g.output:
        for d in out.type.tensor_type.shape.dim:
            d.Clear()
    for p in model.metadata_props:
        if p.key == "imgsz":
            p.value = f"[{height}, {width}]"
    model = onnx.shape_inference.infer_shapes(model, strict_mode=True)
    onnx.checker.check_model(model)

    dst = Path(dst_path)
    dst.parent.mkdir(parents=True, exist_ok=True)
    # Write under a temporary name and rename, so concurrent set-ups never read half a file.
    fd, tmp = tempfile.mkstemp(dir=dst.parent, suffix=".onnx.tmp")
    os.close(fd)
    try:
        onnx.save(model, tmp)
        os.replace(tmp, dst)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return dst


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open_regular(path) as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def converted_model(src_path: str | Path, cache_dir: str | Path, height: int, width: int) -> Path:
    """The float model for this source and size, converted once and kept in ``cache_dir``.

    The cache key is the source's sha256, the size and the converter version, so a changed
    model file or converter never reuses a stale conversion.
    """
    src = Path(src_path)
    if not src.is_file():
        raise InputError("ONNX model not found", src)
    key = f"{src.stem}-{file_sha256(src)[:16]}-{height}x{width}-v{CONVERTER_VERSION}.onnx"
    dst = Path(cache_dir) / key
    if not dst.is_file():
        convert_to_float(src, dst, height, width)
    return dst
