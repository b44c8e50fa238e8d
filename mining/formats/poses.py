"""KITTI odometry poses files: one row-major 3×4 camera-to-world matrix per line."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mining.errors import InputError
from mining.files import read_text


def poses_text(poses: np.ndarray) -> str:
    """KITTI odometry poses: one row-major 3×4 camera-to-world matrix per line (NaN rows allowed)."""
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    return "".join(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n" for T in poses)


def write_poses(path: str | Path, poses: np.ndarray) -> None:
    """``poses_text`` to ``path`` (in a folder the caller owns: this opens ``path`` as given)."""
    Path(path).write_text(poses_text(poses))


def read_poses(path: str | Path) -> np.ndarray:
    """KITTI odometry poses file → (N, 4, 4)."""
    p = Path(path)
    rows = []
    for n, line in enumerate(read_text(p, "poses file").splitlines()):
        if not line.strip():
            continue
        vals = line.split()
        if len(vals) != 12:
            raise InputError(f"line {n + 1}: expected 12 values, got {len(vals)}", p, frame=n)
        T = np.eye(4)
        T[:3] = np.array(vals, np.float64).reshape(3, 4)
        rows.append(T)
    return np.array(rows).reshape(-1, 4, 4)
