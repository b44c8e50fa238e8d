"""Small KITTI tracking layouts made of the real shared frames (symlinked, so a test may delete
or edit one file of its copy), and their calibration edited."""

from __future__ import annotations

from pathlib import Path


def kitti_copy(dest: Path, kitti_tracking_root: Path, sequences: tuple[str, ...] = ("0005",), n_frames: int = 16) -> Path:
    """A KITTI tracking root at ``dest`` whose sequences are all real 0005 (frames symlinked,
    calibration copied); returns ``dest``."""
    real = kitti_tracking_root / "training"
    split = dest / "training"
    (split / "calib").mkdir(parents=True, exist_ok=True)
    for seq in sequences:
        (split / "calib" / f"{seq}.txt").write_text((real / "calib" / "0005.txt").read_text())
        for cam in ("image_02", "image_03"):
            (split / cam / seq).mkdir(parents=True, exist_ok=True)
            for i in range(n_frames):
                (split / cam / seq / f"{i:06d}.png").symlink_to(real / cam / "0005" / f"{i:06d}.png")
    return dest


def set_calib_value(calib: Path, key: str, index: int, value: str) -> None:
    """Replace value ``index`` of calibration line ``key:`` (e.g. P2's fx is index 0)."""
    lines = []
    for line in calib.read_text().splitlines():
        parts = line.split()
        if parts and parts[0] == f"{key}:":
            parts[1 + index] = value
            line = " ".join(parts)
        lines.append(line)
    calib.write_text("\n".join(lines) + "\n")
