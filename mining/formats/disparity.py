"""Disparity maps on disk: KITTI's 16-bit disparity PNG and Middlebury's portable float map (PFM)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mining.errors import InputError
from mining.files import check_regular, open_regular


def disparity_png(disparity: np.ndarray) -> bytes:
    """The bytes of a KITTI 16-bit disparity PNG: value = round(disparity × 256), 0 = invalid."""
    d = np.asarray(disparity, np.float64)
    valid = np.isfinite(d) & (d > 0)
    out = np.zeros(d.shape, np.uint16)
    # 1/256 px is the format's resolution; clip keeps large disparities from wrapping.
    out[valid] = np.clip(np.round(d[valid] * 256.0), 1, 65535).astype(np.uint16)
    ok, png = cv2.imencode(".png", out)
    if not ok:
        raise InputError(f"could not encode a disparity PNG of shape {d.shape}")
    return png.tobytes()


def write_disparity_png(path: str | Path, disparity: np.ndarray) -> None:
    """``disparity_png`` to ``path`` (in a folder the caller owns: this opens ``path`` as given)."""
    Path(path).write_bytes(disparity_png(disparity))


def read_disparity_png(path: str | Path) -> np.ndarray:
    """KITTI 16-bit disparity PNG → float32 pixels, NaN = invalid."""
    raw = cv2.imread(str(check_regular(path)), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError("unreadable or missing disparity PNG", path)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise InputError(f"expected a 16-bit greyscale PNG, got {raw.dtype} with shape {raw.shape}", path)
    d = raw.astype(np.float32) / 256.0
    d[raw == 0] = np.nan
    return d


def read_pfm(path: str | Path) -> np.ndarray:
    """Portable float map (Middlebury): rows are stored bottom-to-top; ``inf`` = unknown → NaN."""
    p = Path(path)
    with open_regular(p) as f:
        kind = f.readline().strip()
        if kind not in (b"Pf", b"PF"):
            raise InputError(f"not a PFM file (header {kind!r})", p)
        try:
            w, h = (int(x) for x in f.readline().split())
            scale = float(f.readline().strip())
        except ValueError as e:
            raise InputError(f"bad PFM header: {e}", p) from None
        channels = 1 if kind == b"Pf" else 3
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    if data.size != w * h * channels:
        raise InputError(f"PFM holds {data.size} values, header says {w}×{h}×{channels}", p)
    img = np.flipud(data.reshape(h, w, channels) if channels == 3 else data.reshape(h, w)).astype(np.float32)
    img[~np.isfinite(img)] = np.nan
    return img
