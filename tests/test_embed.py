"""``mine embed``: an image encoder the user brings, on each tube's best views (mining/discovery/embed.py).

The encoders are tiny random-weight ONNX graphs built here in the contract's layout
(tests/_tiny_models.py ``encoder_onnx``: (B, 3, H, W) float32 in, (B, D) or (B, T, D) out); the
catalogue is the real KITTI 0005 one of tests/_catalog_data.py, its frames re-read through the
KITTI source its job.json names; the Ray test runs real Ray with logical GPUs in a process of its own.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from _jobs import files
from _run import cli
from _tiny_models import encoder_onnx
from mining.config import EmbedConfig
from mining.errors import MiningError

pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def encoders(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("encoders")
    return {"plain": encoder_onnx(d / "plain.onnx"), "tokens": encoder_onnx(d / "tokens.onnx", tokens=5),
            "other": encoder_onnx(d / "other.onnx", seed=9), "b1": encoder_onnx(d / "b1.onnx", batch=1),
            "dynamic_hw": encoder_onnx(d / "dynamic_hw.onnx", size=None)}


@pytest.fixture
def cat(catalogue, tmp_path) -> Path:
    """A copy of the KITTI 0005 catalogue (4 tubes) to embed into."""
    return Path(shutil.copytree(catalogue[0], tmp_path / "cat"))


def _rows(out: Path, sql: str = "SELECT * FROM tube_embeddings ORDER BY tube_id, model_sha256") -> list[dict]:
    from mining.catalog.views import connect

    con = connect(out)
    try:
        rel = con.sql(sql)
        return [dict(zip(rel.columns, r)) for r in rel.fetchall()]
    finally:
        con.close()


def _embed(out: Path, model: Path, **kw):
    from mining.discovery.embed_run import embed_catalogue

    return embed_catalogue(str(out), str(model), kw.pop("where", "true"), EmbedConfig(**kw), use_ray=False)


# -- the contract: a bad model is refused in one line, before anything is written ---------------------


def _bad_models(d: Path, good: Path) -> dict[str, tuple[Path, str]]:
    from onnx import TensorProto

    data = good.read_bytes()
    (d / "truncated.onnx").write_bytes(data[: len(data) // 2])
    (d / "random.onnx").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    (d / "empty.onnx").write_bytes(b"")
    return {
        "missing": (d / "missing.onnx", "embedding model not found"),
        "empty": (d / "empty.onnx", "empty file"),
        "truncated": (d / "truncated.onnx", "not a readable ONNX model"),
        "random": (d / "random.onnx", "not a readable ONNX model"),
        "int input": (encoder_onnx(d / "int.onnx", elem_type=TensorProto.INT64), "not (B, 3, H, W) float32"),
        "4-D output": (encoder_onnx(d / "rank4.onnx", out_rank=4), "not (B, D) or (B, T, D)"),
        "D = 1": (encoder_onnx(d / "d1.onnx", dim=1), "with D ≥ 2"),
    }


def test_a_bad_model_is_refused_in_one_line_naming_the_file_before_anything_is_written(cat, encoders, tmp_path):
    before = files(cat)
    for case, (path, why) in _bad_models(tmp_path, encoders["plain"]).items():
        with pytest.raises(MiningError) as e:
            _embed(cat, path)
        msg = str(e.value)
        assert "\n" not in msg and f"file {path}" in msg and why in msg, (case, msg)
        assert files(cat) == before, case  # not even the writer's lock


def test_the_command_refuses_a_bad_model_in_its_name_with_exit_status_2(cat, tmp_path, capsys):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x07garbage")
    before = files(cat)
    rc, out, err = cli(capsys, "embed", "--out", str(cat), "--model", str(bad), "--local")
    assert (rc, out) == (2, "") and err.startswith(f"mine embed: file {bad}: embedding model:"), err
    assert len(err.splitlines()) == 1 and files(cat) == before


def test_both_output_layouts_give_the_same_unit_vector_and_identical_crops_identical_vectors(encoders):
    from mining.discovery.embed import Encoder

    rng = np.random.default_rng(1)
    crops = [rng.integers(0, 256, (50, 30, 3), dtype=np.uint8), rng.integers(0, 256, (20, 70, 3), dtype=np.uint8)]
    crops.append(crops[0].copy())
    plain = Encoder(encoders["plain"], EmbedConfig(), "cpu")
    tokens = Encoder(encoders["tokens"], EmbedConfig(), "cpu")  # (B, T, D): the first token is read
    one_at_a_time = Encoder(encoders["b1"], EmbedConfig(), "cpu")  # a fixed batch of 1
    a, b, c = (e.embed_crops(crops) for e in (plain, tokens, one_at_a_time))
    assert a.shape == (3, 16) and np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-6)
    assert np.array_equal(a[0], a[2]) and not np.allclose(a[0], a[1])
    assert np.allclose(a, b, atol=1e-6) and np.allclose(a, c, atol=1e-6)
    other = Encoder(encoders["other"], EmbedConfig(), "cpu")
    assert not np.allclose(other.embed_crops(crops), a, atol=1e-3)  # another model, other vectors
    # Symbolic H and W: the crop goes in at --input-size
    assert Encoder(encoders["dynamic_hw"], EmbedConfig(input_size=48), "cpu").input.height == 48


def test_the_presets_hold_the_published_constants_and_the_command_offers_them():
    from mining.commands import embed as command
    from mining.discovery.embed import PRESETS

    assert PRESETS["clip"] == ((0.48145466, 0.4578275, 0.40821073), (0.26862954, 0.26130258, 0.27577711))
    assert PRESETS["dino"] == PRESETS["imagenet"] == ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
    assert command.PRESETS == tuple(PRESETS)
    assert command.DEVICES == ("auto", "cpu", "cuda")


def test_best_views_are_the_largest_masks_by_objectness_in_frame_order():
    from mining.discovery.embed import aspect_crop, best_views

    rows = [{"frame": f, "observed": o, "objectness": p} for f, o, p in
            [(1, True, 0.5), (2, True, None), (3, False, None), (4, True, 0.9), (5, True, 1.0)]]
    areas = [100.0, 30.0, 1000.0, 100.0, 10.0]  # frame 3 is a prediction: never a view
    assert [r["frame"] for r in best_views(rows, areas, 2)] == [1, 4]  # 50 and 90 beat 30 and 10
    assert [r["frame"] for r in best_views(rows, areas, 9)] == [1, 2, 4, 5]
    image = np.full((100, 200, 3), 7, np.uint8)
    crop = aspect_crop(image, [0, 40, 10, 60], 0.0, 1.0, np.array([1, 2, 3], np.uint8))  # at the left edge
    assert crop.shape[0] == crop.shape[1] and (crop[:, 0] == [1, 2, 3]).all() and (crop == 7).any()


# -- mine embed on a real catalogue ------------------------------------------------------------------


def test_mine_embed_writes_one_unit_vector_per_selected_tube_with_the_models_sha256(cat, encoders, capsys):
    import duckdb

    rc, out, err = cli(capsys, "embed", "--out", str(cat), "--model", str(encoders["plain"]), "--local",
                       "--where", "true")
    assert rc == 0 and "4 tubes embedded, 0 already embedded" in out, (out, err)
    rows = _rows(cat)
    tubes = [r[0] for r in duckdb.connect().execute(
        f"SELECT tube_id FROM read_parquet('{cat}/catalog/tubes/*/*/*.parquet') ORDER BY 1").fetchall()]
    assert [r["tube_id"] for r in rows] == tubes and len(tubes) == 4
    sha = hashlib.sha256(encoders["plain"].read_bytes()).hexdigest()
    for r in rows:
        assert r["model"] == "plain.onnx" and r["model_sha256"] == sha and r["preset"] == "clip"
        assert r["dim"] == len(r["vector"]) == 16 and abs(np.linalg.norm(r["vector"]) - 1.0) < 1e-5
        assert 1 <= r["n_views"] == len(r["view_frames"]) <= 3
    # The views are the tube's own observed frames
    observed = _rows(cat, "SELECT tube_id, list(frame) AS f FROM tube_frames WHERE observed GROUP BY tube_id")
    frames = {r["tube_id"]: set(r["f"]) for r in observed}
    assert all(set(r["view_frames"]) <= frames[r["tube_id"]] for r in rows)
    # Read through pyarrow datasets (how a catalogue on an object store is read): the same rows
    from mining.catalog.views import connect

    con = connect(cat, native=False)
    try:
        assert con.sql("SELECT tube_id, vector FROM tube_embeddings ORDER BY 1").fetchall() == \
            [(r["tube_id"], r["vector"]) for r in rows]
    finally:
        con.close()
    # A predicate that matches nothing writes nothing and exits 1, as mine export's and mine label's
    before = files(cat)
    assert cli(capsys, "embed", "--out", str(cat), "--model", str(encoders["plain"]), "--local",
               "--where", "n_frames < 0")[0] == 1
    assert files(cat) == before
    # Similarity is one SQL expression away
    sims = _rows(cat, "SELECT list_cosine_similarity(a.vector, b.vector) AS s FROM tube_embeddings a, tube_embeddings b "
                      "WHERE a.tube_id = b.tube_id")
    assert all(abs(r["s"] - 1.0) < 1e-5 for r in sims)


def test_tubes_with_the_same_views_get_the_same_vector(every_call, encoders, tmp_path):
    # every_call's catalogue holds copies of tubes under new ids, with the same frames, boxes and masks
    out = Path(shutil.copytree(every_call[0], tmp_path / "copies"))
    summary = _embed(out, encoders["plain"], tubes_per_task=3)  # copies land in other tasks and batches
    assert summary.embedded == 8 and not summary.failed
    rows = _rows(out)
    by_views: dict[str, list[list[float]]] = {}
    for r in rows:
        by_views.setdefault(r["views_key"], []).append(r["vector"])
    assert sorted(len(v) for v in by_views.values()) == [2, 2, 2, 2]
    assert all(v[0] == v[1] for v in by_views.values())  # identical crops, identical vectors, to the bit
    assert len({tuple(v[0]) for v in by_views.values()}) == 4  # and other tubes, other vectors


def test_mine_embed_takes_its_settings_from_the_jobs_embed_section_then_its_flags(cat, encoders, capsys):
    job = json.loads((cat / "job.json").read_text())
    job["config"]["embed"] = {"model_path": str(encoders["plain"]), "preset": "dino", "views": 1}
    (cat / "job.json").write_text(json.dumps(job))
    rc, out, err = cli(capsys, "embed", "--out", str(cat), "--local")
    assert rc == 0, err
    assert {(r["model"], r["preset"], r["n_views"]) for r in _rows(cat)} == {("plain.onnx", "dino", 1)}
    rc, out, err = cli(capsys, "embed", "--out", str(cat), "--local", "--preset", "imagenet", "--views", "2")
    assert rc == 0, err
    assert {(r["preset"], r["n_views"]) for r in _rows(cat)} <= {("imagenet", 2), ("imagenet", 1)}


def test_running_again_embeds_nothing_and_a_changed_model_embeds_everything_again(cat, encoders):
    first = _embed(cat, encoders["plain"], where="selected")
    selected = len(_rows(cat, "SELECT tube_id FROM tubes WHERE selected"))
    assert first.embedded == selected > 0 and not first.failed
    written = files(cat)
    again = _embed(cat, encoders["plain"], where="selected")
    assert (again.embedded, again.skipped) == (0, selected)
    assert {k: v for k, v in files(cat).items() if k.startswith("embeddings")} == \
        {k: v for k, v in written.items() if k.startswith("embeddings")}
    wider = _embed(cat, encoders["plain"])  # the unselected tubes too: only they are new
    assert (wider.embedded, wider.skipped) == (4 - selected, selected)
    changed = _embed(cat, encoders["other"])
    assert changed.embedded == 4
    by_model = _rows(cat, "SELECT model, count(*) AS n FROM tube_embeddings GROUP BY model ORDER BY model")
    assert by_model == [{"model": "other.onnx", "n": 4}, {"model": "plain.onnx", "n": 4}]
    # Other settings make other vectors: the tubes are embedded again, the newest row is the one read
    views = _embed(cat, encoders["plain"], views=1)
    assert views.embedded == 4
    assert {r["n_views"] for r in _rows(cat, "SELECT n_views FROM tube_embeddings WHERE model = 'plain.onnx'")} == {1}


def test_a_killed_run_resumes_after_its_last_recorded_file_and_its_leftovers_are_never_read(cat, encoders):
    from mining.catalog.layout import EMBEDDING_MARKERS

    full = _embed(cat, encoders["plain"], tubes_per_task=1)
    assert full.embedded == 4 and len(full.files) == 4
    (marker,) = (cat / EMBEDDING_MARKERS).rglob("*.json")
    record = json.loads(marker.read_text())
    kept = sorted(record["files"])[:2]
    record["files"] = {k: record["files"][k] for k in kept}  # killed after two tasks were recorded
    marker.write_text(json.dumps(record))
    assert len(_rows(cat)) == 2  # the two unrecorded files are not read
    (marker.parent / f".{marker.name}.tmp-0123456789ab").write_text("{")  # a kill mid-write of the marker
    resumed = _embed(cat, encoders["plain"], tubes_per_task=1)
    assert not list(marker.parent.glob(".*"))
    assert (resumed.embedded, resumed.skipped) == (2, 2)
    folder = cat / Path(kept[0]).parent
    assert sorted(p.name for p in folder.iterdir()) == sorted(Path(f).name for f in [*kept, *resumed.files])
    assert len(_rows(cat)) == 4


def test_a_damaged_embedding_file_fails_the_view_naming_it_and_is_embedded_again(cat, encoders):
    import duckdb

    _embed(cat, encoders["plain"])
    (part,) = (cat / "embeddings").rglob("part-*.parquet")
    data = bytearray(part.read_bytes())
    data[len(data) // 2] ^= 0xFF
    part.write_bytes(bytes(data))
    with pytest.raises(duckdb.Error, match=f"tube_embeddings is damaged: {part}"):
        _rows(cat)
    assert _rows(cat, "SELECT count(*) AS n FROM tubes") == [{"n": 4}]  # the other tables answer
    again = _embed(cat, encoders["plain"])
    assert again.embedded == 4 and not part.exists() and len(_rows(cat)) == 4


def _source_without_frame(cat: Path, root: Path, kitti_tracking_root: Path, frame: int) -> None:
    """A copy of KITTI 0005's images and calibration at ``root`` without the left image of ``frame``,
    named in the catalogue's job.json."""
    train = kitti_tracking_root / "training"
    for sub in ("image_02/0005", "image_03/0005"):
        shutil.copytree(train / sub, root / "training" / sub)
    (root / "training" / "calib").mkdir()
    shutil.copy(train / "calib" / "0005.txt", root / "training" / "calib" / "0005.txt")
    (root / "training" / "image_02" / "0005" / f"{frame:06d}.png").unlink()
    job = json.loads((cat / "job.json").read_text())
    job["config"]["source"]["root"] = str(root)
    (cat / "job.json").write_text(json.dumps(job))


def test_a_tube_whose_frame_is_missing_from_the_source_fails_alone_named(cat, encoders, kitti_tracking_root, tmp_path,
                                                                        capsys):
    first = _embed(cat, encoders["plain"], views=1)
    frames = {r["tube_id"]: r["view_frames"][0] for r in _rows(cat)}
    victim, frame = next((t, f) for t, f in frames.items() if list(frames.values()).count(f) == 1)
    shutil.rmtree(cat / "embeddings")
    _source_without_frame(cat, tmp_path / "kitti", kitti_tracking_root, frame)
    rc, out, err = cli(capsys, "embed", "--out", str(cat), "--model", str(encoders["plain"]), "--local",
                       "--where", "true", "--views", "1")
    assert rc == 2 and "3 tubes embedded" in out and "1 failed" in out, (out, err)
    (line,) = err.splitlines()
    assert line.startswith(f"  tube {victim}: ") and f"frame {frame}" in line, line
    assert sorted(r["tube_id"] for r in _rows(cat)) == sorted(t for t in frames if t != victim)
    assert first.embedded == 4


# -- on Ray's actors, with logical GPUs ----------------------------------------------------------------


def test_how_many_actors_a_cluster_gets_and_what_each_holds():
    from mining.discovery.embed_run import actor_count

    gpus, cpus = {"CPU": 16.0, "GPU": 4.0}, {"CPU": 16.0}
    assert actor_count(EmbedConfig(), gpus) == (4, 1.0)  # one per GPU
    assert actor_count(EmbedConfig(), cpus) == (16, 0.0)  # one per CPU
    assert actor_count(EmbedConfig(gpus_per_actor=0.5), gpus) == (8, 0.5)
    assert actor_count(EmbedConfig(actors=0), gpus) == (16, 0.0)  # the CPUs only
    assert actor_count(EmbedConfig(actors=2), gpus) == (2, 1.0)
    with pytest.raises(MiningError, match="the cluster has 4 GPUs"):
        actor_count(EmbedConfig(actors=5), gpus)



@pytest.fixture(scope="module")
def ray_with_logical_gpus():
    import ray

    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.slow  # starts a Ray of its own (logical GPUs)
@pytest.mark.own_process
def test_on_ray_one_actor_holds_each_logical_gpu_and_the_vectors_are_the_local_ones(ray_with_logical_gpus, catalogue,
                                                                                   encoders, tmp_path):
    from mining.discovery.embed_run import embed_catalogue

    local, remote = (Path(shutil.copytree(catalogue[0], tmp_path / n)) for n in ("local", "ray"))
    _embed(local, encoders["plain"])
    summary = embed_catalogue(str(remote), str(encoders["plain"]), "true", EmbedConfig(tubes_per_task=1), use_ray=True)
    assert summary.embedded == 4 and not summary.failed
    actors = summary.placement
    assert len(actors) == 2 and sorted(g for a in actors for g in a["gpu_ids"]) == ["0", "1"]
    assert sum(a["tubes"] for a in actors) == 4 and all(a["tubes"] > 0 for a in actors)
    # This onnxruntime has no CUDA provider: the GPU actors run the CPU's (with onnxruntime-gpu, CUDA's)
    assert all(a["providers"][-1] == "CPUExecutionProvider" for a in actors)
    a = {r["tube_id"]: r["vector"] for r in _rows(local)}
    b = {r["tube_id"]: r["vector"] for r in _rows(remote)}
    assert a.keys() == b.keys() and all(np.allclose(a[t], b[t], atol=1e-6) for t in a)


# -- beside the catalogue: a resubmission keeps the embeddings, a new run moves them aside ----------


@pytest.mark.slow  # a small synthetic job mined (once a session), then resumed and mined anew
def test_a_resubmission_keeps_the_embeddings_and_a_new_run_moves_them_aside(base_catalogue, encoders, tmp_path):
    from _jobs import copy_of, mine

    out = copy_of(base_catalogue, tmp_path / "c")
    first = _embed(out, encoders["plain"])  # frames re-rendered through the synthetic source of job.json
    assert first.embedded == len(_rows(out, "SELECT tube_id FROM tubes")) > 0 and not first.failed
    before = _rows(out)
    assert not mine(out).failed  # the same job again: resumed, nothing re-mined
    assert _rows(out) == before
    assert _embed(out, encoders["plain"]).embedded == 0
    assert not mine(out, mode="new").failed
    assert _rows(out) == []
    assert len(list((out / "_replaced").glob("*/embeddings/_markers/*/*/*.json"))) == 1


# -- mine submit's embedding stage (embed.model_path) ---------------------------------------------


def test_a_bad_embedding_model_refuses_the_job_before_anything_is_written(encoders, tmp_path):
    from _jobs import mine, small_cfg

    bad = tmp_path / "bad.onnx"
    bad.write_bytes(encoders["plain"].read_bytes()[:100])
    out = tmp_path / "never"
    with pytest.raises(MiningError, match=f"file {bad}: embedding model: not a readable ONNX model"):
        mine(out, cfg=small_cfg(f'embed.model_path="{bad}"'))
    assert not out.exists()


@pytest.mark.slow  # the small synthetic job mined again, with the stage
def test_the_submit_stage_embeds_the_selected_tubes_and_changes_no_tube(base_catalogue, encoders, tmp_path):
    from _jobs import mine, small_cfg, tables

    with_stage = small_cfg(f'embed.model_path="{encoders["plain"]}"', "embed.views=2")
    assert with_stage.params_hash == small_cfg().params_hash  # embeddings are no part of the result's identity
    out = tmp_path / "staged"
    s = mine(out, cfg=with_stage)
    assert not s.failed and any("tubes embedded" in line for line in s.lines()), s.lines()
    assert tables(out) == base_catalogue[1]  # the same tubes as the job without the stage
    selected = sorted(r["tube_id"] for r in _rows(out, "SELECT tube_id FROM tubes WHERE selected"))
    rows = _rows(out)
    assert sorted(r["tube_id"] for r in rows) == selected and {r["n_views"] for r in rows} <= {1, 2}
    again = mine(out, cfg=with_stage)  # resubmitted: nothing to mine, nothing to embed
    assert any(f"0 tubes embedded, {len(selected)} already embedded" in line for line in again.lines()), again.lines()
    assert not mine(out).failed  # and without the stage: the same job
    assert len(_rows(out)) == len(selected)


@pytest.mark.slow  # a small synthetic job on a local Ray, with the stage
@pytest.mark.own_process
def test_the_submit_stage_runs_on_the_jobs_ray_one_actor_per_logical_gpu(ray_with_logical_gpus, encoders, tmp_path):
    from _jobs import SEQ, small_cfg
    from mining.pipeline.executors import RayExecutor
    from mining.pipeline.submit import mine_job

    cfg = small_cfg(f'embed.model_path="{encoders["plain"]}"', "embed.tubes_per_task=1")
    s = mine_job(cfg, str(tmp_path / "ray"), [SEQ], (0, 16), executor=RayExecutor)
    assert not s.failed
    n = len(_rows(tmp_path / "ray", "SELECT tube_id FROM tubes WHERE selected"))
    line = next(line for line in s.lines() if "tubes embedded" in line)
    assert n >= 2 and f"{n} tubes embedded" in line and "2 actor(s) on GPUs [0, 1]" in line, line
    assert len(_rows(tmp_path / "ray")) == n


def test_mine_similar_compares_either_vector(cat, encoders, capsys):
    """`mine similar --vector embedding` ranks by the embeddings (the tube itself first, the order
    the stored vectors give); one model is taken without naming it, two need --model."""
    assert cli(capsys, "similar", "--out", str(cat), "kitti/0005/x", "--vector", "embedding")[0] == 2  # none stored yet
    _embed(cat, encoders["plain"])
    rows = _rows(cat)
    query = rows[0]["tube_id"]
    rc, out, err = cli(capsys, "similar", "--out", str(cat), query, "--vector", "embedding", "--format", "json")
    assert rc == 0, err
    got = json.loads(out)
    v = {r["tube_id"]: np.asarray(r["vector"]) for r in rows}
    want = sorted(v, key=lambda t: (1.0 - float(v[t] @ v[query]), t))
    assert [r["tube_id"] for r in got] == want and got[0]["distance"] == pytest.approx(0.0, abs=1e-6)
    _embed(cat, encoders["tokens"])
    rc, _, err = cli(capsys, "similar", "--out", str(cat), query, "--vector", "embedding")
    assert rc == 2 and "2 models" in err and "--model" in err, err
    rc, out, err = cli(capsys, "similar", "--out", str(cat), query, "--vector", "embedding", "--model", "tokens.onnx",
                       "--format", "json")
    assert rc == 0 and json.loads(out)[0]["tube_id"] == query, err
    rc, _, err = cli(capsys, "similar", "--out", str(cat), query, "--model", "tokens.onnx")
    assert rc == 2 and "--vector embedding" in err


def test_the_tube_page_shows_the_tubes_similar_in_looks_once_embedded(cat, encoders, tmp_path):
    """The tube page's second strip: the nearest tubes by image embedding, with the model's name;
    no strip before anything is embedded, a note where two models are (name one: mine similar)."""
    from conftest import json_get, serving

    with serving(cat, tmp_path / "cache") as (base, _):
        first = _rows(cat, "SELECT tube_id FROM tubes ORDER BY 1")[0]["tube_id"]
        status, d = json_get(base, "/api/tube", {"id": first})
        assert status == 200 and d["similar_looks"] == [] and d["similar_looks_note"] is None
        _embed(cat, encoders["plain"])
        status, d = json_get(base, "/api/tube", {"id": first})
        rows = _rows(cat)
        v = {r["tube_id"]: np.asarray(r["vector"]) for r in rows}
        want = sorted((t for t in v if t != first), key=lambda t: (1.0 - float(v[t] @ v[first]), t))
        assert status == 200 and d["similar_looks_model"] == "plain.onnx"
        assert [s["tube_id"] for s in d["similar_looks"]] == want
        _embed(cat, encoders["tokens"])
        status, d = json_get(base, "/api/tube", {"id": first})
        assert status == 200 and d["similar_looks"] == [] and "--model" in d["similar_looks_note"]
