"""Issue 30: render N synthetic frames at RobotCar geometry (1280x960, fx 983, baseline 0.24 m, 16 Hz)
and write them as an Oxford traversal (GBRG Bayer + radial LUT) and an npz of frames + exact depth.
Usage: PYTHONPATH=. taskset -c 1 python scripts/robotcar_fixture.py OUT_DIR N [SEQ]"""
import sys, time, numpy as np, cv2
from pathlib import Path
cv2.setNumThreads(1)
from mining.sources.synthetic import SyntheticSource
from mining.testing.fixtures import write_robotcar_fixture
out = Path(sys.argv[1]); n = int(sys.argv[2]); seq = sys.argv[3] if len(sys.argv) > 3 else "0000"
out.mkdir(parents=True, exist_ok=True)  # a folder not there yet is made
src = SyntheticSource(n_frames=max(n, 20), width=1280, height=960, fx=983.044, baseline_m=0.24, hz=16.0, sequences=[seq])
plan = src.plan(seq)
L, R, D = [], [], []
t_render = []
for i in range(n):
    t0 = time.process_time(); f = src.read_frame(plan, i); t_render.append(time.process_time() - t0)
    L.append(f.left); R.append(f.right); D.append(f.truth.depth.astype(np.float32))
print("render cpu-s per frame (after first):", np.mean(t_render[1:]))
np.savez(out / f"frames_{seq}.npz", left=np.array(L), right=np.array(R), depth=np.array(D))
write_robotcar_fixture(out / f"robotcar_{seq}", L, R, src.calib, traversal=f"t{seq}", frames_per_chunk=1000)
print(src.calib)
