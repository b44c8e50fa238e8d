"""The proposal stage (issue 30): the proposer's model parts batched, on actors of their own.

The model is the real maskrcnn_resnet50_fpn with random weights (conftest's ``torch_checkpoint``)
at a reduced input size: random weights say nothing about accuracy, they exercise batching and
placement. Ray's GPUs here are logical (``ray.init(num_gpus=2)``): the actors get GPU ids and
``CUDA_VISIBLE_DEVICES`` as on a GPU node, and the model runs on the CPU.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from conftest import MODEL, REPO, TORCH_SMALL

from mining.config import load_config
from mining.errors import ConfigError
from mining.pipeline.executors import cluster_with_gpus, proposal_actor_count
from mining.pipeline.frames import plan_frames, plan_geometry
from mining.pipeline.proposal_stage import LocalModels, ahead
from mining.proposals.make import FrameProposer
from mining.sources.synthetic import SyntheticSource

pytest.importorskip("torch")
pytest.importorskip("torchvision")


def _cfg(checkpoint, *sets: str):
    torch_sets = [f"proposals.torch.{k}={v!r}" if isinstance(v, str) else f"proposals.torch.{k}={v}"
                  for k, v in TORCH_SMALL.items()]
    return load_config(REPO / "jobs" / "synthetic.toml",
                       ["proposals.proposer='torch+stereo'", f"proposals.torch.model_path='{checkpoint}'",
                        *torch_sets, *sets])


def _same(a, b) -> None:
    assert a.frame == b.frame and len(a) == len(b) and list(a.proposer) == list(b.proposer)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.objectness, b.objectness)
    np.testing.assert_array_equal(a.posterior, b.posterior)
    assert a.rles == b.rles


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_model_parts_in_batches_give_each_frame_its_own_proposals(torch_checkpoint):
    # Three frames in batches of two (the torch proposer's own batch of two inside): the model
    # parts run elsewhere and joined by finish equal the whole proposer on each frame alone.
    cfg = _cfg(torch_checkpoint, "proposals.torch.batch_size=2")
    src = SyntheticSource(n_frames=3)
    plan = src.plan("0000")
    size = (plan.calib.height, plan.calib.width)
    whole = FrameProposer(cfg.proposals, size)
    here = FrameProposer(cfg.proposals, size, models=False)
    assert here.model_names == ["torch"] and whole.names == ["torch", "stereo"]
    got = list(ahead(plan_frames(src, plan, 0, 3), LocalModels(cfg.proposals), batch=2, queue=2))
    assert [g[0] for g in got] == [0, 1, 2]
    n = 0
    for (_, frame, geom, _), (_, frame2, _, models) in zip(plan_geometry(src, plan, 0, 3, cfg.geometry), got):
        assert frame2.index == frame.index
        alone = whole(frame, geom)
        _same(here.finish(frame, geom, models), alone)
        n += len(alone)
    assert n > 0


class _Counting(LocalModels):
    """The in-process stage, counting the batches submitted and not yet collected."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.out, self.most, self.sizes = 0, 0, []

    def submit(self, frame_size, frames, images):
        self.out += 1
        self.most = max(self.most, self.out)
        self.sizes.append(len(frames))
        return super().submit(frame_size, frames, images)

    def result(self, handle):
        self.out -= 1
        return super().result(handle)


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_ahead_sends_at_most_queue_batches_ahead_and_keeps_the_order(torch_checkpoint):
    cfg = _cfg(torch_checkpoint)
    src = SyntheticSource(n_frames=7)
    plan = src.plan("0000")
    stage = _Counting(cfg.proposals)
    got = list(ahead(plan_frames(src, plan, 0, 7), stage, batch=3, queue=2))
    assert [g[0] for g in got] == list(range(7))
    assert stage.sizes == [3, 3, 1] and stage.most == 2 and stage.out == 0
    assert all(models[0].frame == frame.index for _, frame, _, models in got)


def test_how_many_proposal_actors_a_cluster_gets(torch_checkpoint):
    auto = _cfg(torch_checkpoint)
    assert auto.run.proposal_actors == -1  # one per GPU where there are GPUs, none elsewhere
    assert proposal_actor_count(auto, {"CPU": 16.0}) == 0
    assert proposal_actor_count(auto, {"CPU": 16.0, "GPU": 4.0}) == 4
    half = dataclasses.replace(auto, run=dataclasses.replace(auto.run, gpus_per_proposal_actor=0.5))
    assert proposal_actor_count(half, {"CPU": 16.0, "GPU": 4.0}) == 8
    stereo = load_config(REPO / "jobs" / "synthetic.toml", ["run.proposal_actors=2"])
    with pytest.raises(ConfigError, match="runs no network"):
        proposal_actor_count(stereo, {"CPU": 16.0, "GPU": 4.0})
    too_many = _cfg(torch_checkpoint, "run.proposal_actors=3")
    with pytest.raises(ConfigError, match="the cluster has 2 GPUs"):
        proposal_actor_count(too_many, {"CPU": 16.0, "GPU": 2.0})


@pytest.fixture(scope="module")
def ray_with_logical_gpus():
    import ray

    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.slow  # starts a local Ray and waits 1.5 s on purpose
@pytest.mark.own_process
def test_a_job_asking_for_more_gpus_than_there_are_waits_for_the_autoscaler_then_names_the_shortfall(
        ray_with_logical_gpus, torch_checkpoint):
    import ray

    fits = _cfg(torch_checkpoint, "run.proposal_actors=2", "run.gpu_wait_s=30")
    t0 = time.monotonic()
    assert cluster_with_gpus(fits, ray)["GPU"] == 2.0 and time.monotonic() - t0 < 1.0  # there: no wait
    short = _cfg(torch_checkpoint, "run.proposal_actors=3", "run.gpu_wait_s=1.5")
    t0 = time.monotonic()
    resources = cluster_with_gpus(short, ray, poll_s=0.5)  # asks the (absent) autoscaler, then waits
    assert 1.5 <= time.monotonic() - t0 < 10.0 and resources["GPU"] == 2.0
    with pytest.raises(ConfigError, match=r"the cluster has 2 GPUs \(after waiting up to run.gpu_wait_s=1.5 s"):
        proposal_actor_count(short, resources)
    auto = _cfg(torch_checkpoint, "run.gpu_wait_s=30")  # -1 takes the GPUs there are, at once
    t0 = time.monotonic()
    assert proposal_actor_count(auto, cluster_with_gpus(auto, ray)) == 2 and time.monotonic() - t0 < 1.0


@pytest.mark.slow  # two jobs of 16 frames on a local Ray
@pytest.mark.own_process
def test_logical_gpus_hold_the_proposal_stage_and_the_tubes_do_not_change(ray_with_logical_gpus, torch_checkpoint,
                                                                          tmp_path):
    from mining.catalog.views import connect
    from mining.pipeline.executors import RayExecutor
    from mining.pipeline.submit import mine_job

    frames = (0, 16)
    staged = mine_job(_cfg(torch_checkpoint, "window.core=8", "run.proposal_batch=4"), str(tmp_path / "staged"),
                      ["0000"], frames, executor=RayExecutor)
    plain = mine_job(_cfg(torch_checkpoint, "window.core=8", "run.proposal_actors=0"), str(tmp_path / "plain"),
                     ["0000"], frames, executor=RayExecutor)
    assert staged.ok == plain.ok == 2 and not staged.failed and not plain.failed

    actors, workers = staged.placement["proposal_actors"], staged.placement["workers"]
    assert len(actors) == 2 and sorted(g for a in actors for g in a["gpu_ids"]) == ["0", "1"]
    assert all(len(a["gpu_ids"]) == 1 for a in actors)
    assert len(workers) == 2 and all(w["gpu_ids"] == [] for w in workers)  # nothing else on a GPU
    assert not {a["pid"] for a in actors} & {w["pid"] for w in workers}
    # Every frame observed, warm-up frames included (2 before the second window), was proposed there.
    assert sum(a["frames"] for a in actors) == frames[1] + 2
    assert plain.placement["proposal_actors"] == []
    assert "proposal stage: 2 actor(s) on GPUs" in "\n".join(staged.lines())
    # Their busy time: inside the job's mining time, each actor worked, and the share is said.
    busy = staged.stage_busy()
    assert all(a["busy_s"] > 0 and a["first_t"] >= staged.started_at for a in actors)
    assert 0 < busy["share"] <= 1 and 0 <= busy["all_busy_after_s"] <= staged.mining_seconds
    assert "proposal stage busy" in "\n".join(staged.lines()) and plain.stage_busy() is None

    cols = "tube_id, selected, known, category, score, n_frames, frame_start, frame_end, mean_position, params_hash"
    a = connect(str(tmp_path / "staged")).execute(f"SELECT {cols} FROM tubes ORDER BY tube_id").fetchall()
    b = connect(str(tmp_path / "plain")).execute(f"SELECT {cols} FROM tubes ORDER BY tube_id").fetchall()
    assert a == b and len(a) > 0
    ma = connect(str(tmp_path / "staged")).execute("SELECT tube_id, frame, bbox, rle_counts, position_world FROM tube_frames ORDER BY 1, 2").fetchall()
    mb = connect(str(tmp_path / "plain")).execute("SELECT tube_id, frame, bbox, rle_counts, position_world FROM tube_frames ORDER BY 1, 2").fetchall()
    assert ma == mb


def test_an_onnx_model_with_a_batch_axis_runs_a_batch_at_once_with_the_same_outputs(tmp_path):
    if not MODEL.is_file():
        pytest.skip(f"no ONNX model at {MODEL} (../shared absent)")
    from _tiny_models import fastsam_onnx
    from mining.proposals.config import OnnxConfig
    from mining.proposals.onnx_yolo import OnnxProposer
    from mining.proposals.yolo_seg import decode_predictions

    path = fastsam_onnx(tmp_path / "yolo_batch.onnx", height=64, width=96, n_classes=80, batch=None)
    cfg = OnnxConfig(model_path=str(path), cache_dir=str(tmp_path / "cache"), input_height=64, input_width=96,
                     score_threshold=0.3)
    model = OnnxProposer(cfg)
    assert model.batch_axis((64, 96))
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (128, 192, 3), dtype=np.uint8) for _ in range(3)]
    together = model.raw_outputs_batch([0, 1, 2], images)
    n = 0
    for i, image in enumerate(images):
        pred, protos, lb = model.raw_outputs(image)
        np.testing.assert_array_equal(together[i][0], pred)
        np.testing.assert_array_equal(together[i][1], protos)
        a = decode_predictions(i, together[i][0], together[i][1], together[i][2], image.shape[:2], cfg)
        b = model(i, image)
        assert a.rles == b.rles and np.array_equal(a.boxes, b.boxes)
        n += len(b)
    assert n > 0
    # The usual export fixes its batch at 1 (inside its reshapes too): it runs image by image.
    shared = OnnxProposer(OnnxConfig(model_path=str(MODEL), cache_dir=str(tmp_path / "cache"),
                                     input_height=320, input_width=320))
    assert not shared.batch_axis((320, 320))


LONG_FRAMES = 2000  # the long sequence: twenty 100-frame windows
LONG_SIZE = (64, 212)  # ours: a sixth of KITTI's sides, so 2,000 frames fit the slow tier; memory is what is measured
STORE_SLACK = 16 * 2**20  # ours: Ray's own objects (actor handles, step results), at the sampler's MiB resolution


@pytest.mark.slow  # 2,000 frames on a local Ray
@pytest.mark.own_process
def test_on_2000_frames_the_object_store_stays_bounded_and_worker_memory_flat(tmp_path, fastsam_model):
    from mining.bench.pipeline import GROWTH_TOLERANCE, growth, measure_run_here

    h, w = LONG_SIZE
    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "proposals.proposer='fastsam+stereo'", f"proposals.fastsam.model_path='{fastsam_model}'",
        "proposals.fastsam.input_height=64", "proposals.fastsam.input_width=64", "proposals.fastsam.max_proposals=3",
        f"source.options.n_frames={LONG_FRAMES}", f"source.options.width={w}", f"source.options.height={h}",
        "source.sequences=['0000']"])
    r = measure_run_here(cfg, tmp_path / "out", workers=2, gpus=2)
    assert r["windows"] == LONG_FRAMES // 100 and r["frames"] == LONG_FRAMES
    actors = r["placement"]["proposal_actors"]
    assert len(actors) == 2 and sum(a["frames"] for a in actors) >= LONG_FRAMES
    # What may wait in the store: each worker's batches sent ahead (left images out, proposals back).
    batch_bytes = cfg.run.proposal_batch * h * w * 3
    bound = 2 * cfg.run.proposal_queue * batch_bytes * 2 + STORE_SLACK
    print(f"object store peak {r['object_store_peak_bytes'] / 2**20:.0f} MiB of a bound of {bound / 2**20:.0f} MiB "
          f"({r['object_store_samples']} samples); worker peaks {[round(x / 2**20) for x in r['worker_hwm_bytes']]} MiB")
    assert r["object_store_samples"] > 10
    assert r["object_store_peak_bytes"] <= bound
    g = growth(r["window_peak_rss_bytes"])
    print(f"per-window peak RSS, first half {g['first_half_max'] / 2**20:.0f} MiB, second half "
          f"{g['second_half_max'] / 2**20:.0f} MiB")
    assert g["ratio"] <= GROWTH_TOLERANCE
