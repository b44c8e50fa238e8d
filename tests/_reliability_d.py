"""Helpers of the reliability-d tests (issue 11, items 7 and 8): the real ``mine`` command
line in a subprocess of its own, and small KITTI tracking layouts made of the real
shared frames (symlinked, so a test may delete or edit one file of its copy)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 420  # a job that the old code starts on Ray instead of refusing must not hang the suite
# A synthetic job small enough to plan in a second (it is refused before anything runs).
SYNTHETIC = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=8", "--option", "width=621",
             "--option", "height=188"]


def mine(*args: str, cwd: Path = REPO, timeout: float = TIMEOUT_S) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``mine ARGS`` with this checkout's code and a Ray of its own."""
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0", PYTHONPATH=str(REPO))
    env.pop("RAY_ADDRESS", None)
    p = subprocess.run([sys.executable, "-m", "mining.cli", *args], cwd=cwd, env=env, capture_output=True,
                       text=True, timeout=timeout)
    return p.returncode, p.stdout, p.stderr


def main(capsys, *args: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``mine ARGS`` run in this process (``mining.cli.main``):
    for the cases refused before anything starts, without an interpreter's start-up each."""
    from mining.cli import main as mine_main

    capsys.readouterr()
    try:
        rc = mine_main(list(args))
    except SystemExit as e:  # argparse's own errors
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def submit(out: Path, *args: str, timeout: float = TIMEOUT_S) -> tuple[int, str, str]:
    return mine("submit", *args, "--out", str(out), "--workers", "1", "--no-progress", timeout=timeout)


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


def clean_error(stderr: str) -> str:
    """The error line (``mine: error: …``, ``mine export: …``), the last of standard error;
    asserts there is no traceback."""
    assert "Traceback" not in stderr, stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert lines, "no error message"
    return lines[-1]
