"""Write rendered frames for a look: ``python -m mining.sources.synthetic --seq 0000 --frames 0:5 --out DIR``
(``--scenario border`` stages a scenario), or time the renderer: ``--bench 50`` renders plan positions
1–50 (left, right and truth; one OpenCV thread) and prints ms per frame — for the one-core figure run it
as ``OMP_NUM_THREADS=1 taskset -c 0 python -m mining.sources.synthetic --bench 50``."""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from mining.sources.synthetic import SyntheticSource


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mining.sources.synthetic")
    ap.add_argument("--seq", default="0000")
    ap.add_argument("--frames", default="0:5", help="start:stop plan positions")
    ap.add_argument("--out", help="folder for the PNGs (required unless --bench)")
    ap.add_argument("--bench", type=int, default=0, help="time this many frames instead of writing any")
    ap.add_argument("--n-frames", type=int, default=500)
    ap.add_argument("--scenario", default=None, help="a staged scenario (scenarios.py), e.g. border")
    a = ap.parse_args(argv)
    if a.bench:
        cv2.setNumThreads(1)
        src = SyntheticSource(n_frames=max(a.n_frames, a.bench + 1), scenario=a.scenario)
        plan = src.plan(a.seq)
        src.read_frame(plan, 0)  # the atlas and the world
        ms, cpu = [], []
        for i in range(1, a.bench + 1):
            t0, c0 = time.perf_counter(), time.process_time()
            src.read_frame(plan, i)
            ms.append(1e3 * (time.perf_counter() - t0))
            cpu.append(1e3 * (time.process_time() - c0))
        print(f"{a.seq}: {a.bench} frames {src.calib.width}x{src.calib.height}: wall min {min(ms):.0f} median "
              f"{statistics.median(ms):.0f} ms ({1e3 / statistics.median(ms):.1f} frames/s), CPU median "
              f"{statistics.median(cpu):.0f} ms ({1e3 / statistics.median(cpu):.1f} frames/s)")
        return
    if not a.out:
        ap.error("--out is required (or --bench N)")
    start, stop = (int(x) for x in a.frames.split(":"))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    src = SyntheticSource(n_frames=a.n_frames, scenario=a.scenario)
    plan = src.plan(a.seq)
    for fr in src.read(plan, start, stop):
        stem = out / f"{a.seq}_{fr.index:06d}"
        cv2.imwrite(f"{stem}_left.png", fr.left[:, :, ::-1])
        cv2.imwrite(f"{stem}_right.png", fr.right[:, :, ::-1])
        d = fr.truth.depth
        vis = np.where(np.isfinite(d), np.clip(255 * 4 / np.maximum(d, 1e-3), 0, 255), 0).astype(np.uint8)
        cv2.imwrite(f"{stem}_depth.png", cv2.applyColorMap(vis, cv2.COLORMAP_MAGMA))
        inst = np.zeros(d.shape + (3,), np.uint8)
        for o in fr.truth.objects:
            colour = np.random.default_rng(o.track_id).integers(60, 255, 3)
            inst[o.mask] = colour if o.known else colour // 3 + 170
        cv2.imwrite(f"{stem}_inst.png", inst[:, :, ::-1])
        print(stem, [(o.track_id, o.category) for o in fr.truth.objects])


if __name__ == "__main__":
    main()
