"""`mine view`'s server on the real KITTI 0005 catalogue: the JSON API (filters, paging, bad
parameters, unknown tubes), the pictures drawn on the real frames, the caches, the placeholders."""

from __future__ import annotations

import json
import shutil
import tomllib

import cv2
import numpy as np
import pytest
from pycocotools import mask as mask_utils

from _catalog_data import DATASET, SEQUENCE
from _run import env
from conftest import REPO, count_tubes, get, json_get, serving
from mining.catalog.views import connect
from mining.cli import main
from mining.errors import InputError
from mining.export.selection import selected_rows, tube_call
from mining.types import CALLS
from mining.view.images import JPEG_QUALITY, THUMB_SIZE
from mining.view.server import make_server


@pytest.fixture(scope="module")
def server(catalogue, tmp_path_factory):
    out, _ = catalogue
    with serving(out, tmp_path_factory.mktemp("view-cache")) as (base, srv):
        yield base, srv, out


def test_gallery_pages_are_the_catalogues_tubes_in_score_order(server):
    base, _, out = server
    status, page = json_get(base, "/api/tubes")
    assert status == 200
    assert page["total"] == count_tubes(out, "selected") == len(page["tubes"]) > 0
    con = connect(out)
    ids = [r[0] for r in con.execute("SELECT tube_id FROM tubes ORDER BY score DESC, tube_id").fetchall()]
    con.close()
    status, every = json_get(base, "/api/tubes", {"set": "all"})
    assert every["total"] == len(ids) > page["total"], "the fixture has tubes co-selection left out"
    assert [t["tube_id"] for t in every["tubes"]] == ids
    # Pages of two tile the whole list, in order.
    paged = []
    for offset in range(0, len(ids), 2):
        status, p = json_get(base, "/api/tubes", {"set": "all", "limit": 2, "offset": offset})
        assert status == 200 and p["total"] == len(ids) and len(p["tubes"]) <= 2
        paged += [t["tube_id"] for t in p["tubes"]]
    assert paged == ids
    status, asc = json_get(base, "/api/tubes", {"set": "all", "order": "asc"})
    scores = [t["score"] for t in asc["tubes"]]
    assert scores == sorted(scores) and {t["tube_id"] for t in asc["tubes"]} == set(ids)
    status, by_length = json_get(base, "/api/tubes", {"set": "all", "sort": "n_frames"})
    lengths = [t["n_frames"] for t in by_length["tubes"]]
    assert lengths == sorted(lengths, reverse=True)


@pytest.mark.parametrize("params, where, values", [
    ({"min_score": "50"}, "selected AND score >= ?", [50.0]),
    ({"set": "all", "max_n_frames": "15"}, "n_frames <= ?", [15]),
    ({"call": "known"}, "selected AND call = 'known'", []),
    ({"call": ["unknown", "clutter", "unclassified"]}, "selected AND call IN ('unknown', 'clutter', 'unclassified')", []),
    ({"set": "all", "min_object_prob": "0.5"}, "object_prob >= 0.5", []),
    ({"category": "car", "min_score_mask": "85"}, "selected AND category = 'car' AND score_mask >= 85", []),
    ({"seq": f"{DATASET}/{SEQUENCE}", "min_score_motion": "57", "max_score_objectness": "34"},
     "selected AND score_motion >= 57 AND score_objectness <= 34", []),
    ({"seq": "kitti/9999"}, "false", []),
    ({"category": "person"}, "false", []),  # a class name no tube of the fixture has
])
def test_filters_count_what_duckdb_counts(server, params, where, values):
    base, _, out = server
    status, page = json_get(base, "/api/tubes", params)
    assert status == 200, page
    assert page["total"] == count_tubes(out, where, values) == len(page["tubes"])
    # The shown --where expression selects exactly the same tubes.
    assert count_tubes(out, page["where"]) == page["total"]
    assert page["export_command"].startswith(f"mine export --out {out} --where ")


def test_a_narrowing_filter_narrows(server):
    base, _, _ = server
    _, everything = json_get(base, "/api/tubes")
    scores = sorted({t["score"] for t in everything["tubes"]})
    assert len(scores) >= 2, "the fixture catalogue needs tubes of different scores"
    # the median's score, on whatever scale the unary has (REFERENCE ~20–100, calibrated log-odds ~0–10)
    _, narrowed = json_get(base, "/api/tubes", {"min_score": str(scores[len(scores) // 2])})
    assert 0 < narrowed["total"] < everything["total"]


@pytest.mark.parametrize("params, message", [
    ({"min_score": "abc"}, "'min_score' must be a number"),
    ({"min_n_frames": "2.5"}, "'min_n_frames' must be an integer"),
    ({"min_score": "nan"}, "must be finite"),
    ({"min_score": "9", "max_score": "1"}, "is above max_score"),
    ({"sort": "score; DROP TABLE tubes"}, "cannot sort by"),
    ({"order": "sideways"}, "'order' is 'asc' or 'desc'"),
    ({"limit": "0"}, "'limit' must be in 1..500"),
    ({"limit": "100000"}, "'limit' must be in 1..500"),
    ({"offset": "-1"}, "'offset' must be ≥ 0"),
    ({"call": "maybe"}, "parameter 'call' is one of known, unknown, clutter, unclassified, got 'maybe'"),
    ({"call": ["known", "true"]}, "parameter 'call' is one of known, unknown, clutter, unclassified, got 'true'"),
    # the old parameter is refused, naming the new one (its three values cannot say clutter)
    ({"known": "true"}, "filter by parameter 'call'"),
    ({"min_object_prob": "x"}, "'min_object_prob' must be a number"),
    ({"seq": "0005"}, "'seq' is DATASET/SEQUENCE"),
    ({"set": "some"}, "'set' is 'selected' or 'all'"),
    ({"min_score": ["1", "2"]}, "given 2 times"),
    ({"score_min": "1"}, "unknown parameter 'score_min'"),
    # Unknown values are errors, never ignored (issue 19); this one, bound as a value, used to match nothing.
    ({"category": "car' OR true OR category = '"}, "'category' is a COCO class name"),
    ({"category": "carr"}, "'category' is a COCO class name"),
    ({"seq": "kitti/../0005"}, "'seq' is DATASET/SEQUENCE of names"),
    ({"offset": str(10**23)}, "'offset' must be at most"),
])
def test_bad_parameters_are_400_with_the_reason(server, params, message):
    base, _, _ = server
    status, body = json_get(base, "/api/tubes", params)
    assert status == 400
    assert message in body["error"]


def test_unknown_tubes_and_frames_are_404_bad_ones_400(server):
    base, _, _ = server
    tid = f"{DATASET}/{SEQUENCE}/0000000.000"
    for path in ("/api/tube", "/img/thumb"):
        status, body = json_get(base, path, {"id": "kitti/0005/9999999.999"})
        assert status == 404 and "no tube 'kitti/0005/9999999.999'" in body["error"]
        status, body = json_get(base, path, {"id": "../../etc/passwd"})
        assert status == 404
        status, body = json_get(base, path)
        assert status == 400 and "give one tube id" in body["error"]
    assert json_get(base, "/img/frame", {"id": tid, "frame": 99})[0] == 404
    status, body = json_get(base, "/img/frame", {"id": tid, "frame": "x"})
    assert status == 400 and "frame must be an integer" in body["error"]
    status, body = json_get(base, "/img/frame", {"id": tid, "frame": 0, "size": "huge"})
    assert status == 400 and "size is one of" in body["error"]
    assert json_get(base, "/api/facets", {"set": "none"})[0] == 400
    assert json_get(base, "/no/such/page")[0] == 404
    assert json_get(base, "/static/../server.py")[0] == 404


def test_facets_count_the_catalogue(server):
    base, _, out = server
    status, f = json_get(base, "/api/facets")
    assert status == 200
    assert f["tubes"] == count_tubes(out, "true") and f["selected"] == count_tubes(out, "selected")
    assert f["calls"] == {c: count_tubes(out, "selected AND call = ?", [c]) for c in CALLS}
    assert sum(f["calls"].values()) == f["selected"]
    assert f["sequences"] == [{"dataset": DATASET, "sequence": SEQUENCE, "n": f["selected"]}]
    assert {c["category"]: c["n"] for c in f["categories"]} == {"car": count_tubes(out, "selected AND category = 'car'")}
    lo, hi = f["ranges"]["score"]
    assert count_tubes(out, "selected AND score BETWEEN ? AND ?", [lo, hi]) == f["selected"]
    assert f["frames_unavailable"] is None


@pytest.fixture(scope="module")
def every_call_server(every_call, tmp_path_factory):
    out, calls = every_call
    with serving(out, tmp_path_factory.mktemp("every-call-cache")) as (base, _):
        yield base, out, calls


def _ids(page: dict) -> set[str]:
    return {t["tube_id"] for t in page["tubes"]}


def test_the_call_filter_gives_exactly_the_tubes_of_each_call(every_call_server):
    base, out, calls = every_call_server
    con = connect(out)
    try:
        rows = {r["tube_id"]: r for r in con.execute("SELECT * FROM tubes").to_arrow_table().to_pylist()}
    finally:
        con.close()
    assert {t: tube_call(r) for t, r in rows.items()} == calls, "the fixture's calls are the exports' reading"
    legacy = {t for t, r in rows.items() if r["call"] is None}
    assert {calls[t] for t in legacy} == {"known", "unknown", "unclassified"}, "rows from before the call column"
    selected = {t for t, r in rows.items() if r["selected"]}
    assert selected != set(rows)
    for call in CALLS:
        want = {t for t, c in calls.items() if c == call}
        assert want, f"the fixture has no {call} tube"
        for which, expected in (("all", want), ("selected", want & selected)):
            status, page = json_get(base, "/api/tubes", {"set": which, "call": call})
            assert status == 200, page
            assert _ids(page) == expected and page["total"] == len(expected), (call, which)
            assert {t["call"] for t in page["tubes"]} <= {call}, "each card says its call, old rows' read from known"
            # The export line's --where selects the same tubes through `mine export`'s own predicate check.
            con = connect(out)
            try:
                tubes, _ = selected_rows(con, page["where"])
            finally:
                con.close()
            assert set(tubes.column("tube_id").to_pylist()) == expected, page["where"]
            assert page["export_command"].startswith(f"mine export --out {out} --where \"")
    status, page = json_get(base, "/api/tubes", {"set": "all", "call": ["clutter", "unclassified"]})
    assert _ids(page) == {t for t, c in calls.items() if c in ("clutter", "unclassified")}
    status, page = json_get(base, "/api/tubes", {"set": "all"})
    assert {t["tube_id"]: t["call"] for t in page["tubes"]} == calls
    # P(object) is a range and a sort: only the tubes the object gate judged have one.
    status, page = json_get(base, "/api/tubes", {"set": "all", "min_object_prob": "0.5"})
    assert _ids(page) == {t for t, r in rows.items() if r["object_prob"] is not None and r["object_prob"] >= 0.5}
    assert page["total"] == 1
    status, page = json_get(base, "/api/tubes", {"set": "all", "sort": "object_prob", "order": "asc"})
    judged = sorted((r["object_prob"], t) for t, r in rows.items() if r["object_prob"] is not None)
    assert [t["tube_id"] for t in page["tubes"]][:len(judged)] == [t for _, t in judged]


def test_facets_count_the_calls_old_rows_by_known(every_call_server):
    base, out, calls = every_call_server
    _, f = json_get(base, "/api/facets", {"set": "all"})
    assert f["calls"] == {c: list(calls.values()).count(c) for c in CALLS}
    _, f = json_get(base, "/api/facets")
    _, page = json_get(base, "/api/tubes")
    assert f["calls"] == {c: sum(t["call"] == c for t in page["tubes"]) for c in CALLS}
    assert sum(f["calls"].values()) == f["selected"] == page["total"]
    assert "known" not in f, "the facets count calls, not known"


def _rule(base: str, tube_id: str) -> tuple[dict, dict]:
    status, d = json_get(base, "/api/tube", {"id": tube_id})
    assert status == 200, d
    return d["tube"], d["class_rule"]


def test_the_tube_page_explains_each_call_with_its_numbers(every_call_server):
    base, out, calls = every_call_server
    # clutter: unknown wins, and P(object) is below the gate's threshold
    tube, r = _rule(base, "kitti/0005/0000000.002")
    assert tube["call"] == r["call"] == "clutter" and tube["call_from_known"] is False
    assert r["object_prob"] == pytest.approx(0.31) and r["min_object"] == 0.5
    assert r["min_object_key"] == "score.unknown_min_object" and r["gate"] == "call"
    assert r["log_ratio"] == pytest.approx(np.log(0.06) - np.log(0.9), abs=1e-5) and r["best_known"] == "car"
    assert "ln 0.060 − ln 0.900 = -2.71 ≤ 0.00: unknown wins." in r["text"]
    assert "P(object) 0.31 < 0.50 (score.unknown_min_object): clutter" in r["text"]
    assert "kept out of the unknown set" in r["text"] and "score.unknown_gate = call" in r["text"]
    # unknown: the same inequality, and P(object) at or above the threshold
    tube, r = _rule(base, "kitti/0005/0000000.001")
    assert r["call"] == "unknown" and "P(object) 0.72 ≥ 0.50 (score.unknown_min_object): an object, unknown." in r["text"]
    # unclassified: no classifier looked
    tube, r = _rule(base, "kitti/0005/0000005.003")
    assert tube["call"] == r["call"] == "unclassified" and r["classified_frames"] == 0
    assert r["text"] == "Unclassified: no classifier looked at this tube (classified frames 0)."
    assert r["log_ratio"] is None and r["object_prob"] is None
    # known, whose posterior has P(unknown) 0: ln 0 is −∞, known at any margin
    tube, r = _rule(base, "kitti/0005/0000000.000")
    assert r["call"] == "known" and "= +∞ > 0.00: known, car." in r["text"]
    # rows written before the call column: read from known, and they say so
    for tube_id, call in (("kitti/0005/0000000.100", "known"), ("kitti/0005/0000000.101", "unknown"),
                          ("kitti/0005/0000000.102", "unclassified")):
        tube, r = _rule(base, tube_id)
        assert tube["call"] == r["call"] == call and tube["call_from_known"] is True and r["call_from_known"] is True
        assert "written before the call column" in r["text"], r["text"]
    assert "older rule, though 3 frame(s) were classified" in _rule(base, "kitti/0005/0000000.102")[1]["text"]


def test_without_a_job_record_the_rule_says_what_it_cannot_know(every_call, tmp_path):
    out, _ = every_call
    copy = tmp_path / "no-job"
    shutil.copytree(out, copy)
    (copy / "job.json").unlink()
    with serving(copy, tmp_path / "cache") as (base, _):
        _, r = _rule(base, "kitti/0005/0000000.002")
    assert r["margin"] is None and r["min_object"] is None
    assert "the job's margin (not known: the catalogue has no job.json)" in r["text"]
    assert "P(object) 0.31 < the job's threshold (score.unknown_min_object; no job.json): clutter" in r["text"]


def test_a_clutter_thumbnail_is_outlined_in_its_own_colour(every_call_server):
    base, _, _ = every_call_server

    def violet(tube_id: str) -> int:
        status, _, body = get(base, "/img/thumb", {"id": tube_id})
        assert status == 200
        rgb = _decode(body).astype(int)
        return int(((abs(rgb[..., 0] - 190) < 40) & (abs(rgb[..., 1] - 130) < 40) & (rgb[..., 2] > 215)).sum())

    # the same tube's frames: clutter (violet) and, as a row from before the call column, unclassified (blue)
    assert violet("kitti/0005/0000000.002") > 50 > violet("kitti/0005/0000000.102")


def test_tube_page_data(server, catalogue):
    base, _, out = server
    _, tables = catalogue
    tube = max(tables["tubes"].to_pylist(), key=lambda t: t["score"])
    status, d = json_get(base, "/api/tube", {"id": tube["tube_id"]})
    assert status == 200
    assert d["tube"]["tube_id"] == tube["tube_id"] and d["tube"]["score"] == pytest.approx(tube["score"])
    frames = sorted((f for f in tables["tube_frames"].to_pylist() if f["tube_id"] == tube["tube_id"]),
                    key=lambda f: f["frame"])
    assert [f["frame"] for f in d["frames"]] == [f["frame"] for f in frames] and len(frames) == tube["n_frames"]
    np.testing.assert_allclose([f["position_world"] for f in d["frames"]], [f["position_world"] for f in frames])
    # The camera path: the frames table's pose translations over the tube's frames.
    con = connect(out)
    poses = con.execute("SELECT frame, pose FROM frames WHERE frame BETWEEN ? AND ? ORDER BY frame",
                        [tube["frame_start"], tube["frame_end"]]).fetchall()
    con.close()
    assert [e["frame"] for e in d["ego"]] == [p[0] for p in poses]
    np.testing.assert_allclose([[e["x"], e["y"], e["z"]] for e in d["ego"]],
                               [np.asarray(p[1]).reshape(4, 4)[:3, 3] for p in poses])
    # Top classes: the posterior's largest entries, named, in order.
    post = np.asarray(tube["class_posterior"])
    assert d["top_classes"][0]["name"] == tube["category"]
    np.testing.assert_allclose([c["p"] for c in d["top_classes"]], np.sort(post)[::-1][:5], rtol=1e-6)
    assert count_tubes(out, d["where"]) == 1
    # The call, explained with this tube's numbers (the fixture's tubes are all known cars).
    assert d["tube"]["call"] == tube["call"] == "known" and d["tube"]["call_from_known"] is False
    assert d["class_rule"]["call"] == "known" and d["class_rule"]["margin_key"].startswith("score.known_margin.")
    assert d["class_rule"]["text"].endswith(": known, car.")
    assert d["export_command"] == (f"mine export --out {out} --where \"tube_id = '{tube['tube_id']}'\" "
                                   f"--format crops crops/{tube['tube_id'].replace('/', '_')}")


def _decode(body: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "not an image"
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def test_pictures_outline_the_mask_on_the_real_frame(server, catalogue, kitti_tracking_root):
    from mining.sources.kitti import read_rgb

    base, _, _ = server
    _, tables = catalogue
    tube = max(tables["tubes"].to_pylist(), key=lambda t: t["score"])
    f = next(f for f in tables["tube_frames"].to_pylist() if f["tube_id"] == tube["tube_id"] and f["frame"] == 3)
    status, headers, body = get(base, "/img/frame", {"id": tube["tube_id"], "frame": 3})
    assert status == 200 and headers["Content-Type"] == "image/jpeg" and "X-Placeholder" not in headers
    drawn = _decode(body).astype(np.int16)
    real = read_rgb(kitti_tracking_root / "training" / "image_02" / SEQUENCE / "000003.png", 3).astype(np.int16)
    assert drawn.shape == real.shape
    mask = mask_utils.decode({"size": [f["rle_h"], f["rle_w"]], "counts": f["rle_counts"].encode()}).astype(bool)
    diff = np.abs(drawn - real).max(axis=2)
    assert np.median(diff[mask]) > 25, "the mask is not drawn"
    # Away from the mask (past the JPEG blocks it touches) the picture is the real frame, as JPEG.
    _, buf = cv2.imencode(".jpg", cv2.cvtColor(real.astype(np.uint8), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    as_jpeg = _decode(buf.tobytes()).astype(np.int16)
    near = cv2.dilate(mask.astype(np.uint8), np.ones((41, 41), np.uint8)).astype(bool)
    assert np.abs(drawn - as_jpeg).max(axis=2)[~near].max() <= 2, "the picture is not the real frame"
    # The thumbnail: the fixed size, with the outline's colour (known: green) on it.
    status, headers, body = get(base, "/img/thumb", {"id": tube["tube_id"]})
    thumb = _decode(body)
    assert status == 200 and thumb.shape == (THUMB_SIZE[1], THUMB_SIZE[0], 3)
    green = (thumb[..., 1] > 180) & (thumb[..., 0] < 120) & (thumb[..., 2] < 140)
    assert green.sum() > 50
    status, _, body = get(base, "/img/frame", {"id": tube["tube_id"], "frame": 3, "size": "strip"})
    assert _decode(body).shape[1] == 200


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_pictures_are_cached_on_disk_by_content_and_only_jpegs_are_served(catalogue, tmp_path):
    out, tables = catalogue
    tid = tables["tubes"].column("tube_id")[0].as_py()
    cache = tmp_path / "cache"
    with serving(out, cache) as (base, _):
        _, _, first = get(base, "/img/thumb", {"id": tid})
    files = list(cache.rglob("*.jpg"))
    assert len(files) == 1 and len(files[0].stem) == 64 and files[0].read_bytes() == first
    assert tid.replace("/", "_") not in str(files[0])
    with serving(out, cache) as (base, _):  # a new server: the memory cache is empty, the disk one answers
        _, _, again = get(base, "/img/thumb", {"id": tid})
    assert again == first
    files[0].write_bytes(b"<script>not a picture</script>")
    with serving(out, cache) as (base, _):
        _, headers, redrawn = get(base, "/img/thumb", {"id": tid})
    assert redrawn.startswith(b"\xff\xd8") and headers["Content-Type"] == "image/jpeg"
    with pytest.raises(InputError, match="may not live inside the catalogue"):
        make_server(out, "127.0.0.1", 0, out / "cache")


def test_frames_not_on_this_machine_give_placeholders_that_say_why(catalogue, tmp_path):
    out, tables = catalogue
    moved = tmp_path / "moved"
    shutil.copytree(out, moved)
    job = json.loads((moved / "job.json").read_text())
    job["config"]["source"]["root"] = str(tmp_path / "elsewhere")
    (moved / "job.json").write_text(json.dumps(job))
    tid = tables["tubes"].column("tube_id")[0].as_py()
    with serving(moved, tmp_path / "cache") as (base, _):
        _, f = json_get(base, "/api/facets")
        assert "not on this machine" in f["frames_unavailable"] and "elsewhere" in f["frames_unavailable"]
        status, headers, body = get(base, "/img/thumb", {"id": tid})
        assert status == 200 and "not on this machine" in headers["X-Placeholder"]
        assert _decode(body).shape == (THUMB_SIZE[1], THUMB_SIZE[0], 3)
        status, headers, body = get(base, "/img/frame", {"id": tid, "frame": int(tables["tube_frames"]
                                                                                  .column("frame")[0].as_py())})
        assert status == 200 and "X-Placeholder" in headers and _decode(body).shape[:2] == (375, 1242)
        _, d = json_get(base, "/api/tube", {"id": tid})
        assert "not on this machine" in d["frames_unavailable"]
        status, page = json_get(base, "/api/tubes")
        assert status == 200 and page["total"] > 0, "the gallery still works"


def test_an_empty_catalogue_browses(tmp_path):
    (tmp_path / "empty").mkdir()
    with serving(tmp_path / "empty", tmp_path / "cache") as (base, _):
        _, f = json_get(base, "/api/facets")
        assert f["tubes"] == 0 and "job.json" in f["frames_unavailable"]
        status, page = json_get(base, "/api/tubes")
        assert status == 200 and page["total"] == 0 and page["tubes"] == []
        status, _, body = get(base, "/")
        assert status == 200 and b"gallery.js" in body


def test_pages_and_their_files_are_served_and_shipped():
    static = REPO / "mining" / "view" / "static"
    globs = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["mining.view"]
    shipped = {p for g in globs for p in static.parent.glob(g)}
    assert set(static.iterdir()) <= shipped, "a static file pyproject's package-data leaves out"
    html = (static / "index.html").read_text() + (static / "tube.html").read_text() + (static / "groups.html").read_text()
    for name in ("app.css", "common.js", "gallery.js", "tube.js", "groups.js"):
        assert f"/static/{name}" in html


def test_the_server_is_quiet_unless_asked(server, capsys):
    base, srv, _ = server
    get(base, "/api/tubes")
    assert capsys.readouterr().err == ""
    srv.app.log_requests = True
    try:
        get(base, "/api/tubes", {"min_score": "1"})
        get(base, "/api/tubes", {"min_score": "x"})
    finally:
        srv.app.log_requests = False
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and " 200 " in lines[0] and " 400 " in lines[1], lines


def test_cli_view_refuses_a_missing_catalogue(tmp_path, capsys):
    assert main(["view", "--out", str(tmp_path / "nothing"), "--port", "0"]) == 2
    assert "catalogue folder not found" in capsys.readouterr().err


def test_cli_view_names_a_busy_port(catalogue, capsys, tmp_path):
    out, _ = catalogue
    with serving(out, tmp_path / "cache") as (_, srv):
        port = srv.server_address[1]
        assert main(["view", "--out", str(out), "--port", str(port), "--cache", str(tmp_path / "cache")]) == 2
    assert f"cannot listen on 127.0.0.1:{port}" in capsys.readouterr().err


def test_a_damaged_table_is_503_naming_the_file(catalogue, tmp_path):
    out, _ = catalogue
    copy = tmp_path / "damaged"
    shutil.copytree(out, copy)
    part = next((copy / "catalog" / "tubes").rglob("*.parquet"))
    part.write_bytes(part.read_bytes()[:100])
    with serving(copy, tmp_path / "cache") as (base, _):
        status, body = json_get(base, "/api/tubes")
        assert status == 503 and part.name in body["error"]
        status, _, _ = get(base, "/")
        assert status == 200, "the pages load and say what is wrong"


def test_mine_view_serves_until_ctrl_c(catalogue, tmp_path):
    import re
    import signal
    import subprocess
    import sys

    out, _ = catalogue
    proc = subprocess.Popen([sys.executable, "-m", "mining.cli", "view", "--out", str(out), "--port", "0",
                             "--cache", str(tmp_path / "cache")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env())
    try:
        line = proc.stdout.readline()
        m = re.search(r"serving (http://127\.0\.0\.1:\d+)/", line)
        assert m, line + proc.stderr.read()
        assert f"{count_tubes(out, 'selected')} selected of {count_tubes(out, 'true')} tubes" in line
        status, page = json_get(m.group(1), "/api/tubes")
        assert status == 200 and page["total"] == count_tubes(out, "selected")
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()  # never leave a server behind
            raise
    assert proc.returncode == 0 and err == "", err


def test_an_unusable_cache_folder_costs_speed_not_pictures(catalogue, tmp_path):
    out, tables = catalogue
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    with serving(out, blocked / "cache") as (base, srv):
        assert "memory only" in srv.app.images.cache.problem
        status, headers, body = get(base, "/img/thumb", {"id": tables["tubes"].column("tube_id")[0].as_py()})
        assert status == 200 and "X-Placeholder" not in headers and body.startswith(b"\xff\xd8")
