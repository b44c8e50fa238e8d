"""Discovery at scale (issue 41, mining/discovery/): tube descriptors stored and recomputed only where
stale, `mine similar`, `mine group` (HDBSCAN over the unknown set), `mine label --group` and labels
propagated with their source (`mine label --like/--within`, `--undo-like`).

The catalogue is the real KITTI 0005 one (tests/_catalog_data.py), copied with planted tubes: copies
of its real rows (masks, frames, posteriors) under new ids whose size is changed, so the descriptors
of a planted family are near each other and far from another family's.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from _catalog_data import DATASET, SEQUENCE
from mining import cli
from mining.catalog import derived
from mining.catalog.store import Store, write_sequence
from mining.catalog.views import connect
from mining.commands import group as group_command
from mining.discovery import descriptors as desc
from mining.discovery import groups
from mining.discovery.describe import describe, load_descriptors
from mining.discovery.similar import ExactIndex

OTHER = "0006"  # a second sequence, to show that only a changed sequence is described again
BIG, SMALL = (2.0, 1.6, 4.5), (0.25, 0.6, 0.25)  # two families of unknown tubes: car-sized and bollard-sized
N_FAMILY = 12


def _tube(src: dict, tube_id: str, size: tuple[float, float, float], sequence: str = SEQUENCE, **changes) -> dict:
    return dict(src, tube_id=tube_id, sequence=sequence, size=list(size), **changes)


def _write(dest: Path, tables: dict, tubes: list[dict], sequence: str = SEQUENCE) -> None:
    """Write ``tubes`` (each a copy of a real tube row, ``_src`` naming it) and copies of their
    sources' frames as one sequence of ``dest``."""
    frames = {}
    for f in tables["tube_frames"].to_pylist():
        frames.setdefault(f["tube_id"], []).append(f)
    rows, tf = [], []
    for t in tubes:
        src = t.pop("_src")
        rows.append(t)
        tf += [dict(f, tube_id=t["tube_id"], sequence=sequence) for f in frames[src]]
    store = Store(dest)
    write_sequence(store, "tubes", DATASET, sequence, pa.Table.from_pylist(rows, schema=tables["tubes"].schema))
    write_sequence(store, "tube_frames", DATASET, sequence, pa.Table.from_pylist(tf, schema=tables["tube_frames"].schema))


UNKNOWN = dict(call="unknown", known=False, category="unknown", selected=True, object_prob=0.8)


def _families(tables: dict, sequence: str = SEQUENCE) -> list[dict]:
    """The real tubes, then two planted families of unknown tubes (sizes jittered by ±3 %) and a
    near-duplicate of the first real tube (size 1 % larger)."""
    real = sorted(tables["tubes"].to_pylist(), key=lambda t: t["tube_id"])
    out = [dict(t, _src=t["tube_id"]) for t in real]
    rng = np.random.default_rng(0)
    base = real[0]
    for name, size in (("big", BIG), ("small", SMALL)):
        for k in range(N_FAMILY):
            s = tuple(float(x) for x in np.asarray(size) * rng.uniform(0.97, 1.03, 3))
            out.append(dict(_tube(base, f"{DATASET}/{sequence}/{name}.{k:03d}", s, sequence, **UNKNOWN),
                            _src=base["tube_id"]))
    twin = tuple(float(x) * 1.01 for x in base["size"])
    out.append(dict(_tube(base, f"{DATASET}/{sequence}/twin.000", twin, sequence), _src=base["tube_id"]))
    return out


@pytest.fixture(scope="module")
def planted(catalogue, tmp_path_factory) -> tuple[Path, dict]:
    """(folder, tables) of a copy of the KITTI catalogue with the planted tubes in 0005 and the
    real tubes again in a second sequence."""
    out, tables = catalogue
    dest = tmp_path_factory.mktemp("discovery") / "catalogue"
    shutil.copytree(out, dest)
    _write(dest, tables, _families(tables))
    real = sorted(tables["tubes"].to_pylist(), key=lambda t: t["tube_id"])
    _write(dest, tables, [dict(t, _src=t["tube_id"], sequence=OTHER,
                               tube_id=t["tube_id"].replace(f"/{SEQUENCE}/", f"/{OTHER}/")) for t in real], OTHER)
    return dest, tables


def _main(argv: list[str], capsys) -> tuple[int, str, str]:
    code = cli.main(argv)
    got = capsys.readouterr()
    return code, got.out, got.err


def test_descriptors_are_finite_versioned_and_follow_the_recipe_table():
    raw = np.array([[1.8, 1.5, 4.3, -1.65, 10.0, 0.0, 1.0, 0.0, 0.0, 10, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5],
                    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    v = desc.normalise(raw)
    assert v.shape == (2, desc.DIM) and v.dtype == np.float32 and np.isfinite(v).all()
    w = desc.family_weights()
    # a 1.8 m width is ln(1.8)/ln(10) decades, weighed by 1/√3 (three size components)
    assert v[0, 0] == pytest.approx(math.log(1.8) / math.log(10) / math.sqrt(3), rel=1e-5)
    assert v[0, 3] == pytest.approx(0.0) and v[0, 4] == pytest.approx(0.0)  # on the ground, at 10 m
    families = {c.family for c in desc.COMPONENTS}
    for f in families:  # every family weighs the same: Σ w² = 1
        assert sum(w[k] ** 2 for k, c in enumerate(desc.COMPONENTS) if c.family == f) == pytest.approx(1.0)
    assert desc.DESCRIPTOR_VERSION.startswith(f"d{desc.RECIPE}-")


def test_the_commands_copies_of_grouping_constants_are_their_sources():
    assert group_command.MIN_GROUP_SIZE == groups.MIN_GROUP_SIZE and group_command.MIN_SAMPLES == groups.MIN_SAMPLES
    assert group_command.MAX_GROUPS == groups.MAX_GROUPS and group_command.SELECTIONS[0] == groups.SELECTION
    assert set(group_command.SELECTIONS) == set(groups.SELECTIONS)


def test_descriptors_are_stored_queryable_and_recomputed_only_for_a_changed_sequence(planted, tmp_path):
    src, tables = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    store = Store(out)
    first = describe(store)
    assert {(d, s) for d, s, _ in first.computed} == {(DATASET, SEQUENCE), (DATASET, OTHER)} and not first.kept
    ids, vec = load_descriptors(store)
    assert len(ids) == len(tables["tubes"]) * 2 + 2 * N_FAMILY + 1 and np.isfinite(vec).all()
    con = connect(out)
    try:
        n, versions, dim = con.execute("SELECT count(*), list(DISTINCT version), max(len(vector)) FROM tube_descriptors "
                                       "JOIN tubes USING (tube_id)").fetchone()
    finally:
        con.close()
    assert (n, versions, dim) == (len(ids), [desc.DESCRIPTOR_VERSION], desc.DIM)
    again = describe(store)
    assert not again.computed and len(again.kept) == 2
    before = store.read_bytes(derived.descriptors_file(DATASET, SEQUENCE))
    # the second sequence changes (one tube fewer): it alone is described again
    real = sorted(tables["tubes"].to_pylist(), key=lambda t: t["tube_id"])[1:]
    _write(out, tables, [dict(t, _src=t["tube_id"], sequence=OTHER,
                              tube_id=t["tube_id"].replace(f"/{SEQUENCE}/", f"/{OTHER}/")) for t in real], OTHER)
    third = describe(store)
    assert [(d, s) for d, s, _ in third.computed] == [(DATASET, OTHER)] and [k[:2] for k in third.kept] == [(DATASET, SEQUENCE)]
    assert store.read_bytes(derived.descriptors_file(DATASET, SEQUENCE)) == before
    assert len(load_descriptors(store)[0]) == len(ids) - 1


def test_a_damaged_descriptor_file_is_refused_naming_it(planted, tmp_path):
    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    describe(Store(out))
    path = out / derived.descriptors_file(DATASET, OTHER)
    path.write_bytes(path.read_bytes()[:-8] + b"\0" * 8)
    con = connect(out)
    try:
        with pytest.raises(Exception, match="descriptors.parquet"):
            con.execute("SELECT count(*) FROM tube_descriptors").fetchone()
        assert con.execute("SELECT count(*) FROM tubes").fetchone()[0] > 0  # the mined tables still answer
    finally:
        con.close()


def test_exact_index_returns_the_query_first_and_agrees_with_brute_force():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(500, desc.DIM)).astype(np.float32)
    idx = ExactIndex(v)
    rows, dist = idx.search(v[7], 5)
    assert rows[0] == 7 and dist[0] == pytest.approx(0.0, abs=1e-6)
    unit = v / np.linalg.norm(v, axis=1, keepdims=True)
    brute = np.argsort(1 - unit @ unit[7], kind="stable")[:5]
    assert rows.tolist() == brute.tolist()
    inside, d = idx.within(v[7], float(dist[2]))
    assert inside.tolist() == rows[:3].tolist()
    sub, _ = idx.search(v[7], 3, np.arange(100, 200))
    assert set(sub.tolist()) <= set(range(100, 200))


def test_mine_similar_gives_the_tube_itself_then_its_near_duplicate(planted, tmp_path, capsys):
    src, tables = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    first = sorted(tables["tubes"].column("tube_id").to_pylist())[0]
    code, _, err = _main(["similar", "--out", str(out), first], capsys)
    assert code == 2 and "run `mine describe" in err and err.count("\n") == 1
    assert _main(["describe", "--out", str(out)], capsys)[0] == 0
    code, text, _ = _main(["similar", "--out", str(out), first, "-k", "3", "--where", f"sequence = '{SEQUENCE}'"], capsys)
    lines = text.splitlines()
    assert code == 0 and lines[0].split()[:2] == ["tube_id", "distance"]
    assert lines[1].split()[:2] == [first, "0"] and lines[2].split()[0] == f"{DATASET}/{SEQUENCE}/twin.000"
    assert len(lines) == 4
    code, _, err = _main(["similar", "--out", str(out), "kitti/0005/nope"], capsys)
    assert code == 2 and "no tube 'kitti/0005/nope'" in err and err.count("\n") == 1


def test_hdbscan_groups_planted_families_apart(planted, tmp_path, capsys):
    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    code, text, _ = _main(["group", "--out", str(out), "--min-size", "5"], capsys)
    assert code == 0 and "described 2 sequences first" in text
    con = connect(out)
    try:
        rows = con.execute('SELECT tube_id, "group", group_size FROM tube_groups').fetchall()
        unknown = con.execute("SELECT count(*) FROM unknown_tubes").fetchone()[0]
    finally:
        con.close()
    by_family: dict[str, set[int]] = {}
    for tube_id, g, _ in rows:
        by_family.setdefault(tube_id.split("/")[-1].split(".")[0], set()).add(g)
    assert len(rows) == unknown == 2 * N_FAMILY
    assert len(by_family["big"]) == 1 and len(by_family["small"]) == 1 and by_family["big"] != by_family["small"]
    assert -1 not in by_family["big"] | by_family["small"]
    code, text, _ = _main(["group", "--out", str(out), "--min-size", "5"], capsys)
    assert code == 0 and "unchanged since the last run" in text


def test_label_group_dry_run_counts_what_it_then_labels(planted, tmp_path, capsys):
    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    code, _, err = _main(["label", "--out", str(out), "--group", "0", "--tag", "bollard"], capsys)
    assert code == 2 and "mine group" in err
    assert _main(["group", "--out", str(out), "--min-size", "5"], capsys)[0] == 0
    code, text, _ = _main(["label", "--out", str(out), "--group", "0", "--tag", "bollard", "--dry-run"], capsys)
    assert code == 0 and "would label 12 tubes of group 0" in text
    assert _main(["label", "--out", str(out), "--group", "0", "--tag", "bollard"], capsys)[0] == 0
    con = connect(out)
    try:
        tagged = con.execute("SELECT count(*) FROM tube_labels WHERE list_contains(tags, 'bollard')").fetchone()[0]
        in_group = con.execute('SELECT count(*) FROM tube_groups WHERE "group" = 0').fetchone()[0]
    finally:
        con.close()
    assert tagged == in_group == N_FAMILY


def test_label_like_labels_exactly_the_tubes_within_d_with_their_source_and_takes_them_back(planted, tmp_path, capsys):
    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    assert _main(["describe", "--out", str(out)], capsys)[0] == 0
    source = f"{DATASET}/{SEQUENCE}/big.000"
    store = Store(out)
    ids, vec = load_descriptors(store)
    tube_ids = ids.column("tube_id").to_pylist()
    d = ExactIndex(vec).distances(vec[tube_ids.index(source)])
    within = float(np.sort(d)[6] + np.sort(d)[7]) / 2  # between the 6th and 7th nearest other tube
    expect = {t for t, x in zip(tube_ids, d) if x <= within and t != source}
    assert len(expect) == 6
    # a tube labelled by a person first is never overridden
    person = sorted(expect)[0]
    assert _main(["label", "--out", str(out), "--where", f"tube_id = '{person}'", "--tag", "mine"], capsys)[0] == 0
    code, text, _ = _main(["label", "--out", str(out), "--like", source, "--within", str(within), "--tag", "car",
                           "--dry-run"], capsys)
    assert code == 0 and "would label 5 tubes" in text
    assert _main(["label", "--out", str(out), "--like", source, "--within", str(within), "--tag", "car"], capsys)[0] == 0
    con = connect(out)
    try:
        got = con.execute("SELECT tube_id, labelled_via, source_tube, source_distance FROM tube_labels "
                          "WHERE list_contains(tags, 'car')").fetchall()
    finally:
        con.close()
    assert {r[0] for r in got} == expect - {person}
    for tube_id, via, source_tube, dist in got:
        assert via == "propagated" and source_tube == source
        assert dist == pytest.approx(float(d[tube_ids.index(tube_id)]), abs=1e-5) and dist <= within
    # a person's later decision on one propagated tube survives the undo
    kept = sorted(r[0] for r in got)[0]
    assert _main(["label", "--out", str(out), "--where", f"tube_id = '{kept}'", "--tag", "car"], capsys)[0] == 0
    code, text, _ = _main(["label", "--out", str(out), "--undo-like", source], capsys)
    assert code == 0 and "took back 4 labels" in text
    con = connect(out)
    try:
        left = [r[0] for r in con.execute("SELECT tube_id FROM tube_labels WHERE list_contains(tags, 'car')").fetchall()]
    finally:
        con.close()
    assert left == [kept]
    code, _, err = _main(["label", "--out", str(out), "--undo-like", source], capsys)
    assert code == 1 and "nothing taken back" in err


def test_the_tube_page_shows_its_similar_tubes_once_described(planted, tmp_path):
    from conftest import json_get, serving

    src, tables = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    first = sorted(tables["tubes"].column("tube_id").to_pylist())[0]
    with serving(out, tmp_path / "cache") as (base, _):
        status, d = json_get(base, "/api/tube", {"id": first})
        assert status == 200 and d["similar"] == [] and "mine describe" in d["similar_note"]
        describe(Store(out))
        status, d = json_get(base, "/api/tube", {"id": first})
    assert status == 200 and d["similar_note"] is None and len(d["similar"]) == 8
    assert first not in [s["tube_id"] for s in d["similar"]]
    assert d["similar"][0]["tube_id"] in (f"{DATASET}/{SEQUENCE}/twin.000", first.replace(f"/{SEQUENCE}/", f"/{OTHER}/"))
    dist = [s["distance"] for s in d["similar"]]
    assert dist == sorted(dist) and set(d["similar"][0]) == {"tube_id", "distance", "call", "category", "n_frames",
                                                             "selected"}


def test_a_labels_file_written_before_the_source_columns_still_reads(planted, tmp_path):
    from mining.catalog import labels

    src, tables = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    tube = sorted(tables["tubes"].column("tube_id").to_pylist())[0]
    old = labels.events([(DATASET, SEQUENCE, tube)], "tag", "cone").drop_columns(["source_tube", "distance"])
    Store(out).write_table("labels/part-20260101T000000000000Z-000000000000.parquet", old)
    con = connect(out)
    try:
        got = con.execute("SELECT tube_id, tags, labelled_via, source_tube, source_distance FROM tube_labels").fetchall()
    finally:
        con.close()
    assert got == [(tube, ["cone"], "cli", None, None)]


def test_bench_similar_runs_small_and_the_exact_searches_agree(capsys):
    code, text, _ = _main(["bench", "similar", "--sizes", "3000", "--queries", "5", "--group-size", "600"], capsys)
    lines = text.splitlines()
    assert code == 0 and lines[0].split()[0] == "method"
    rows = {line.rsplit(None, 4)[0]: line.split()[-4:] for line in lines[1:-1]}
    assert set(rows) == {"numpy exact (chosen; build: read from Parquet)", "duckdb array_cosine_distance"}
    assert all(r[0] == "3000" and r[-1] == "1.000" for r in rows.values())  # DuckDB finds the same 10 tubes
    assert lines[-1].startswith("grouping 600 unknown tubes (HDBSCAN): ")


def test_realistic_descriptors_group_into_several_groups():
    from mining.bench.similar import realistic_descriptors

    labels, prob = groups.group_vectors(realistic_descriptors(3000, 5))
    assert labels.max() + 1 >= 3 and (labels >= 0).mean() > 0.3 and ((prob > 0) == (labels >= 0)).all()


def test_the_groups_page_has_one_tile_per_group_and_the_gallery_filters_by_group(planted, tmp_path, capsys):
    from conftest import get, json_get, serving

    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    with serving(out, tmp_path / "cache") as (base, _):
        status, d = json_get(base, "/api/groups")
        assert status == 200 and d["groups"] == [] and "mine group" in d["note"]
        assert _main(["group", "--out", str(out), "--min-size", "5"], capsys)[0] == 0  # the viewer sees it at once
        status, d = json_get(base, "/api/groups")
        assert status == 200 and d["note"] is None and d["tubes"] == 2 * N_FAMILY
        tiles = {g["group"]: g for g in d["groups"]}
        assert len(tiles) == 2 and all(g["size"] == N_FAMILY and 0 <= g["spread"] < 0.01 for g in tiles.values())
        family = {g: t["exemplar"].split("/")[-1].split(".")[0] for g, t in tiles.items()}
        assert sorted(family.values()) == ["big", "small"]
        g = next(iter(tiles))
        status, page = json_get(base, "/api/tubes", {"group": str(g), "limit": "100"})
        assert status == 200 and page["total"] == N_FAMILY and page["where"].endswith(f"tube_group IN ({g})")
        assert {t["tube_id"].split("/")[-1].split(".")[0] for t in page["tubes"]} == {family[g]}
        assert json_get(base, "/api/groups", {"x": "1"})[0] == 400
        assert get(base, "/groups")[0] == 200
    code, _, _ = _main(["label", "--out", str(out), "--where", f"tube_group = {g}", "--tag", "t", "--dry-run"], capsys)
    assert code == 0


@pytest.mark.slow  # over ~2.5 s: it mines the job again twice (resume, then --new-run)
def test_a_mined_catalogue_keeps_its_descriptors_through_a_resubmission_and_a_new_run_moves_them_aside(
        base_catalogue, tmp_path):
    from _jobs import copy_of, mine

    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    first = describe(store)  # the sequences' inputs are their finished markers' sha256
    assert first.computed and not first.kept
    before = {rel: (out / rel).read_bytes() for rel in store.list("discovery", "")}
    assert not mine(out).failed  # the same job again: resumed, nothing re-mined
    assert {rel: (out / rel).read_bytes() for rel in store.list("discovery", "")} == before
    again = describe(store)
    assert not again.computed and len(again.kept) == len(first.computed)
    assert not mine(out, mode="new").failed
    assert not (out / "discovery").exists()
    assert len(list((out / "_replaced").glob("*/discovery/tube_descriptors/*/*/descriptors.parquet"))) == len(first.computed)


def test_tubes_written_before_the_motion_noise_and_call_columns_are_described(planted, tmp_path):
    src, tables = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    store = Store(out)
    rel = store.list(f"catalog/tubes/{DATASET}/{OTHER}")[0]
    old = store.read_table(rel).drop_columns(["speed_sigma_mps", "moving_speed_mps", "object_prob", "call"])
    store.write_table(rel, old)
    describe(store)
    ids, vec = load_descriptors(store)
    mine = [k for k, t in enumerate(ids.column("tube_id").to_pylist()) if f"/{OTHER}/" in t]
    assert len(mine) == len(tables["tubes"]) and np.isfinite(vec[mine]).all()
    k = desc.NAMES.index("moving")
    assert (vec[mine, k] == 0).all()  # no moving_speed_mps: not measured as moving


@pytest.mark.slow  # over ~2.5 s: a headless Chromium
def test_the_groups_page_and_the_similar_strip_in_chromium(planted, chromium, tmp_path, capsys):
    from _cdp import Browser
    from conftest import serving
    from test_view_browser import _looks_like_a_page, _shots

    shots = _shots(tmp_path)
    src, tables = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    assert _main(["group", "--out", str(out), "--min-size", "5"], capsys)[0] == 0
    with serving(out, tmp_path / "cache") as (base, _):
        with Browser(chromium, width=1400, height=900) as b:
            b.goto(f"{base}/groups")
            b.wait_for("document.body.dataset.state === 'ready'")
            assert b.evaluate("document.querySelectorAll('#groups .card').length") == 2
            assert b.evaluate("document.getElementById('totals').textContent") == f"2 groups · {2 * N_FAMILY} unknown tubes"
            b.wait_for("[...document.querySelectorAll('#groups img')].every(i => i.complete && i.naturalWidth > 0)")
            _looks_like_a_page(b.screenshot(shots / "groups.png"), 1400, 900)
            b.evaluate("document.querySelector('#groups .card').click()")  # the gallery, on that group
            b.wait_for("location.pathname === '/' && document.body.dataset.state === 'ready'")
            assert b.evaluate("document.querySelectorAll('#grid .card').length") == N_FAMILY
            assert "tube_group IN (" in b.evaluate("document.getElementById('export').textContent")
            b.goto(f"{base}/tube?id=kitti/0005/big.000")
            b.wait_for("document.body.dataset.state === 'ready'")
            b.evaluate("document.getElementById('similar').scrollIntoView()")
            _looks_like_a_page(b.screenshot(shots / "tube-similar.png"), 1400, 900)
            links = b.evaluate("[...document.querySelectorAll('#similar a')].map(a => a.title)")
    assert len(links) == 8 and all(t.startswith(f"{DATASET}/") for t in links)
    assert sum(t.startswith(f"{DATASET}/{SEQUENCE}/big.") for t in links) == 8  # its own family is nearest


def test_a_new_descriptor_recipe_describes_every_sequence_again(planted, tmp_path, monkeypatch):
    import mining.discovery.describe as describe_module

    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    store = Store(out)
    assert len(describe(store).computed) == 2
    monkeypatch.setattr(describe_module, "DESCRIPTOR_VERSION", "d999-test")
    assert len(load_descriptors(store)[0]) == 0  # stored vectors of another recipe are not served
    again = describe(store)
    assert len(again.computed) == 2 and not again.kept
    con = connect(out)
    try:
        assert con.execute("SELECT list(DISTINCT version) FROM tube_descriptors").fetchone()[0] == ["d999-test"]
    finally:
        con.close()


def test_a_damaged_groups_file_fails_the_views_that_read_it_naming_it(planted, tmp_path, capsys):
    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    assert _main(["group", "--out", str(out), "--min-size", "5"], capsys)[0] == 0
    path = out / derived.GROUPS_FILE
    path.write_bytes(path.read_bytes()[:-8] + b"\0" * 8)
    con = connect(out)
    try:
        for view in ("tube_groups", "labelled_tubes"):
            with pytest.raises(Exception, match="groups.parquet"):
                con.execute(f"SELECT count(*) FROM {view}").fetchone()
        assert con.execute("SELECT count(*) FROM unknown_tubes").fetchone()[0] == 2 * N_FAMILY
    finally:
        con.close()
    code, text, _ = _main(["group", "--out", str(out), "--min-size", "5"], capsys)
    assert code == 0 and "grouped in" in text  # recomputed, not read back
    assert _main(["label", "--out", str(out), "--group", "0", "--tag", "x", "--dry-run"], capsys)[0] == 0


def test_mine_group_label_the_group_export_and_read_back(planted, tmp_path, capsys):
    """The issue's loop end to end: mine (the planted catalogue) → group → label a whole group
    with a tag no COCO class names → export with the tag as the category → TrackEval's YouTube-VIS
    reader reads the tag back as a class of its own with every tube of the group."""
    import json
    import os

    trackeval = pytest.importorskip("trackeval")
    src, _ = planted
    out = tmp_path / "c"
    shutil.copytree(src, out)
    assert _main(["group", "--out", str(out), "--min-size", "5"], capsys)[0] == 0
    con = connect(out)
    try:
        (group,) = con.execute("SELECT DISTINCT \"group\" FROM tube_groups WHERE tube_id LIKE '%/small.%'").fetchone()
    finally:
        con.close()
    code, text, _ = _main(["label", "--out", str(out), "--group", str(group), "--tag", "bollard"], capsys)
    assert code == 0, text
    dest = tmp_path / "vis"
    assert _main(["export", "--out", str(out), "--where", "list_contains(tags, 'bollard')", "--category-from", "tag",
                  "--format", "youtube-vis", str(dest)], capsys)[0] == 0
    doc = json.loads((dest / "instances.json").read_text())
    assert [c["name"] for c in doc["categories"]] == ["bollard"]
    assert sorted(a["tube_id"].split("/")[-1] for a in doc["annotations"]) == [f"small.{k:03d}" for k in range(N_FAMILY)]
    gt, trk = tmp_path / "gt" / "youtube_vis_loop", tmp_path / "trk" / "youtube_vis_loop" / "ours" / "data"
    gt.mkdir(parents=True), trk.mkdir(parents=True)
    shutil.copy(dest / "instances.json", gt)
    shutil.copy(dest / "results" / "results.json", trk)
    dataset = trackeval.datasets.YouTubeVIS({"GT_FOLDER": f"{tmp_path / 'gt'}{os.sep}", "SPLIT_TO_EVAL": "loop",
                                             "TRACKERS_FOLDER": f"{tmp_path / 'trk'}{os.sep}", "PRINT_CONFIG": False,
                                             "TRACKERS_TO_EVAL": ["ours"], "OUTPUT_FOLDER": str(tmp_path / "eval")})
    config = {"USE_PARALLEL": False, "PRINT_RESULTS": False, "PRINT_CONFIG": False, "TIME_PROGRESS": False,
              "OUTPUT_SUMMARY": False, "OUTPUT_DETAILED": False, "PLOT_CURVES": False, "LOG_ON_ERROR": None}
    res, messages = trackeval.Evaluator(config).evaluate([dataset], [trackeval.metrics.HOTA()])
    assert messages["YouTubeVIS"]["ours"] == "Success", messages
    counts = res["YouTubeVIS"]["ours"]["COMBINED_SEQ"]["bollard"]["Count"]
    assert counts["GT_IDs"] == counts["IDs"] == N_FAMILY, counts
    hota = res["YouTubeVIS"]["ours"]["COMBINED_SEQ"]["bollard"]["HOTA"]
    assert float(np.mean(hota["DetA"])) == pytest.approx(1.0)  # every mask of the group, as labelled
