"""Issue 30: per-stage CPU ms per frame of the image pipeline on a RobotCar-layout fixture (scripts/robotcar_fixture.py),
one core. Usage: PYTHONPATH=. taskset -c 1 python scripts/stage_times.py FIXTURE_DIR SEQ [--config ... --set k=v ...]"""
import sys, time, json, numpy as np, cv2
from pathlib import Path
cv2.setNumThreads(1)
from mining.config import JobConfig
from mining.pipeline.arguments import job_config
import argparse
from mining.sources.oxford import OxfordSource, demosaic_gbrg
from mining.geometry.stage import GeometryStage
from mining.geometry import flow as F, egomotion as E, ground as G, disparity as D
from mining.pipeline.frames import FrameLoop
from mining.pipeline.mine import mine_tubes
import mining.pipeline.frames as FR

base = Path(sys.argv[1]); seq = sys.argv[2]
p = argparse.ArgumentParser(); from mining.pipeline.arguments import add_job_options; add_job_options(p)
args = p.parse_args(["--dataset", "oxford", "--root", str(base / f"robotcar_{seq}")] + sys.argv[3:])
cfg = job_config(args)
T = {}
def timed(name, fn):
    def w(*a, **k):
        t0 = time.process_time(); r = fn(*a, **k); T.setdefault(name, []).append(time.process_time() - t0); return r
    return w
import mining.sources.oxford as OX
import cv2 as _cv2
class CV:  # proxy cv2 that times imdecode/cvtColor/remap inside the oxford module
    def __getattr__(self, k):
        v = getattr(_cv2, k)
        if k in ("imdecode", "remap", "cvtColor"):
            return timed("read." + k, v)
        return v
OX.cv2 = CV()
D.StereoMatcher.compute = timed("geom.sgbm(total)", D.StereoMatcher.compute)
D._upsample = timed("geom.sgbm.upsample", D._upsample)
import mining.geometry.stage as ST
ST.stereo_features = timed("geom.stereo_features", F.stereo_features)
F.detect_corners = timed("geom.detect_corners", F.detect_corners)
ST.match_quad = timed("geom.match_quad", F.match_quad)
ST.estimate_egomotion = timed("geom.egomotion", E.estimate_egomotion)
ST.scene_flow = timed("geom.scene_flow", F.scene_flow)
ST.estimate_ground = timed("geom.ground", G.estimate_ground)
GeometryStage.run = timed("geom(total)", GeometryStage.run)
FR.localise = timed("localise", FR.localise)
FR.geometric_filter = timed("geometric_filter", FR.geometric_filter)

src = OxfordSource(base / f"robotcar_{seq}")
plan = src.plan(f"t{seq}")
loop = FrameLoop(cfg)
loop.proposer = None
recs = []
t_read = []
for i in range(len(plan)):
    t0 = time.process_time(); fr = src.read_frame(plan, i); t_read.append(time.process_time() - t0)
    if loop.proposer is None:
        from mining.proposals.make import make_proposer
        loop.proposer = timed("proposals", make_proposer(cfg.proposals, (fr.calib.height, fr.calib.width)))
    t0 = time.process_time(); recs.append(loop.step(fr, position=i)); T.setdefault("step(total)", []).append(time.process_time() - t0)
T["read(total)"] = t_read
t0 = time.process_time(); tubes = mine_tubes([r.tracking for r in recs], cfg, link=False); T["tubes(all frames)"] = [time.process_time() - t0]
skip = 2
print(f"{'stage':<24} {'ms/frame':>9}   (frames {skip}..{len(plan)-1}; tubes: total/frames)")
for k in sorted(T):
    v = T[k]
    if k.startswith("tubes"):
        print(f"{k:<24} {1e3*v[0]/len(plan):9.1f}")
    else:
        vv = v[skip:] if len(v) > skip else v
        print(f"{k:<24} {1e3*np.sum(vv)/max(1,len(plan)-skip):9.1f}   n={len(v)}")
print("proposals/frame", np.mean([len(r.proposals) for r in recs]), "obs/frame", np.mean([len(r.tracking.observations) for r in recs]), "tubes", len(tubes))
print("ego ok", sum(1 for r in recs if r.geometry.egomotion is not None and r.geometry.egomotion.ok), "ground ok", sum(r.geometry.ground.ok for r in recs))
