"""Labels (mining/catalog/labels.py, `mine label`, POST /api/labels): decisions kept as appended
events beside the catalogue, replayed by the `tube_labels` view, kept through a resubmission and a
compaction, never lost between two writers, and exported with the tubes."""

from __future__ import annotations

import json
import threading
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from _jobs import copy_of, mine
from conftest import serving
from mining import cli
from mining.catalog import labels
from mining.catalog.lock import LockedError, OutputLock
from mining.catalog.store import Store
from mining.catalog.views import connect
from mining.commands import export as export_command
from mining.commands import label as label_command
from mining.errors import InputError
from mining.export import kitti


def _ids(out: Path, where: str = "true", n: int | None = None) -> list[tuple[str, str, str]]:
    con = connect(out)
    try:
        rows = con.execute(f"SELECT dataset, sequence, tube_id FROM tubes WHERE {where} ORDER BY tube_id").fetchall()
    finally:
        con.close()
    return [tuple(r) for r in rows][:n]


def _tube_labels(out: Path) -> dict[str, tuple]:
    con = connect(out)
    try:
        return {r[0]: r[1:] for r in con.execute("SELECT tube_id, verdict, tags, tag FROM tube_labels").fetchall()}
    finally:
        con.close()


def test_the_commands_copies_of_label_and_export_constants_are_their_sources():
    assert label_command.VERDICTS == labels.VERDICTS
    assert label_command.MAX_TAG_CHARS == labels.MAX_TAG_CHARS
    assert export_command.MOTS_MAX_CLASS == kitti.MOTS_MAX_CLASS


def test_tube_labels_replays_the_events_in_time_order(base_catalogue, tmp_path):
    from datetime import datetime, timedelta, timezone

    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    a, b = _ids(out, n=2)
    t0 = datetime(2026, 1, 1, tzinfo=timezone.utc)
    for k, (tubes, kind, value, op) in enumerate([
            ([a, b], "verdict", "object", "set"), ([a], "verdict", "duplicate", "set"),
            ([b], "verdict", None, "unset"), ([a], "tag", "barrier", "set"), ([a], "tag", "post", "set"),
            ([a], "tag", "barrier", "unset"), ([b], "tag", "cone", "set")]):
        labels.append(store, labels.events(tubes, kind, value, op, "tester", at=t0 + timedelta(seconds=k)))
    got = _tube_labels(out)
    assert got[a[2]] == ("duplicate", ["post"], "post")  # the last verdict; barrier taken back
    assert got[b[2]] == (None, ["cone"], "cone")  # its verdict taken back, its tag kept
    # A tube whose every decision was taken back is not labelled at all.
    labels.append(store, labels.events([b], "tag", "cone", "unset", "tester", at=t0 + timedelta(seconds=9)))
    assert b[2] not in _tube_labels(out)


def test_bad_labels_are_refused_with_the_reason():
    tube = [("d", "s", "d/s/1.2")]
    with pytest.raises(InputError, match="verdict 'maybe'"):
        labels.events(tube, "verdict", "maybe")
    with pytest.raises(InputError, match="control character"):
        labels.events(tube, "tag", "a\x1b[2Jb")
    with pytest.raises(InputError, match="at most 64"):
        labels.events(tube, "tag", "x" * 65)
    with pytest.raises(InputError, match="tag is empty"):
        labels.events(tube, "tag", "   ")


def test_two_writers_at_once_lose_no_event_and_compaction_keeps_every_one(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    tubes = _ids(out)
    errors: list[BaseException] = []

    def writer(name: str) -> None:
        try:
            for k in range(20):
                labels.append(store, labels.events([tubes[k % len(tubes)]], "tag", f"{name}-{k}", author=name))
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=writer, args=(n,)) for n in ("ann", "bob")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    before = labels.read_labels(store)
    assert before.num_rows == 40 and len(labels.label_files(store)) == 40
    merged, kept = labels.compact(store)
    assert (merged, kept) == (40, 40) and len(labels.label_files(store)) == 1
    after = labels.read_labels(store)
    assert sorted(after["label_id"].to_pylist()) == sorted(before["label_id"].to_pylist())
    # A merged file beside a part it already holds (a compaction killed before removing it): read once.
    part = labels.append(store, labels.events([tubes[0]], "tag", "late"))
    (Path(out) / part.replace("part-", "copy-")).write_bytes((Path(out) / part).read_bytes())
    assert labels.read_labels(store).num_rows == 41


def test_compaction_waits_for_the_writer_lock(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    tubes = _ids(out, n=2)
    labels.append(store, labels.events(tubes, "verdict", "object"))
    labels.append(store, labels.events(tubes, "tag", "car"))
    with OutputLock(store):  # a running submit holds it
        with pytest.raises(LockedError, match="one writer per catalogue"):
            labels.compact(store)
        labels.append(store, labels.events(tubes[:1], "tag", "while-locked"))  # appends never wait
    assert labels.compact(store) == (3, 5)


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_a_resubmission_keeps_every_label_and_a_new_run_moves_them_aside(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "c")
    tubes = _ids(out, "selected")
    assert len(tubes) >= 2
    store = Store(out)
    labels.append(store, labels.events(tubes, "verdict", "object"))
    labels.append(store, labels.events(tubes[:1], "tag", "first"))
    before = _tube_labels(out)
    s = mine(out)  # the same job again: resumed, nothing re-mined
    assert not s.failed
    assert _tube_labels(out) == before
    # Every labelled tube is still a tube of the catalogue.
    assert set(before) <= {t[2] for t in _ids(out)}
    s = mine(out, mode="new")
    assert not s.failed
    assert _tube_labels(out) == {}
    moved = list((Path(out) / "_replaced").glob("*/labels/*.parquet"))
    assert len(moved) == 2


def test_mine_label_labels_what_the_predicate_selects(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "c")
    n_selected = len(_ids(out, "selected"))
    assert cli.main(["label", "--out", str(out), "--where", "selected", "--tag", "seen"]) == 0
    assert f"{n_selected} tubes: tag 'seen' added" in capsys.readouterr().out
    assert cli.main(["label", "--out", str(out), "--where", "list_contains(tags, 'seen') AND n_frames >= 0",
                     "--verdict", "not_object", "--author", "ann"]) == 0
    got = _tube_labels(out)
    assert len(got) == n_selected and {v for v, _, _ in got.values()} == {"not_object"}
    assert cli.main(["label", "--out", str(out), "--where", "false", "--tag", "x"]) == 1
    assert cli.main(["label", "--out", str(out), "--where", "selected", "--tag", "x", "--verdict", "object"]) == 2
    assert "exactly one of" in capsys.readouterr().err
    assert cli.main(["label", "--out", str(out), "--where", "no_such_column", "--tag", "x"]) == 2
    assert "no_such_column" in capsys.readouterr().err
    assert cli.main(["label", "--out", str(out), "--where", "selected", "--tag", "x", "--dry-run"]) == 0
    assert len(labels.label_files(Store(out))) == 2


def test_exports_carry_the_labels_and_can_take_the_tag_as_category(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "c")
    tubes = _ids(out, "selected")
    labels.append(Store(out), labels.events(tubes[:1], "tag", "traffic cone"))
    dest = tmp_path / "kitti"
    assert cli.main(["export", "--out", str(out), "--where", "list_contains(tags, 'traffic cone')", "--format", "kitti",
                     "--category-from", "tag", str(dest)]) == 0
    sidecar = json.loads((dest / "tube_labels.json").read_text())
    assert [(t["tube_id"], t["tags"]) for t in sidecar["tubes"]] == [(tubes[0][2], ["traffic cone"])]
    (ids_file,) = dest.glob("*.ids.json")
    assert [v["category"] for v in json.loads(ids_file.read_text()).values()] == ["traffic cone"]


def _post(base: str, body: bytes, headers: dict[str, str]) -> tuple[int, dict]:
    req = urllib.request.Request(f"{base}/api/labels", data=body, method="POST", headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


JSON = {"Content-Type": "application/json"}


def test_the_viewer_labels_only_from_its_own_pages_and_names_what_is_wrong(catalogue, tmp_path):
    out, tables = catalogue
    tube = tables["tubes"].to_pylist()[0]["tube_id"]
    with serving(out, tmp_path / "cache", author="ann") as (base, _):
        host = base.removeprefix("http://")
        ok = json.dumps({"tubes": [tube], "verdict": "object"}).encode()
        # A form from another site (no preflight needed) and a JSON body from another origin: refused.
        assert _post(base, b"tubes=x", {"Content-Type": "application/x-www-form-urlencoded"})[0] == 403
        assert _post(base, ok, {**JSON, "Origin": "http://evil.example"})[0] == 403
        assert _post(base, ok, {**JSON, "Sec-Fetch-Site": "cross-site"})[0] == 403
        status, answer = _post(base, json.dumps({"tubes": ["kitti/0005/9999999.999"], "tag": "x"}).encode(), JSON)
        assert status == 404 and "9999999.999" in answer["error"]
        assert _post(base, json.dumps({"tubes": [tube], "tag": "x", "verdict": "object"}).encode(), JSON)[0] == 400
        assert _post(base, json.dumps({"tubes": [tube], "verdict": "maybe"}).encode(), JSON)[0] == 400
        assert _post(base, json.dumps({"tubes": [tube] * 1001, "tag": "x"}).encode(), JSON)[0] == 413
        assert _post(base, b"{\"tubes\": [NaN]}", JSON)[0] == 400
        status, answer = _post(base, ok, {**JSON, "Origin": f"http://{host}"})
        assert status == 200 and answer["labelled"][0]["verdict"] == "object" and answer["author"] == "ann"
    assert _tube_labels(out)[tube][0] == "object"


def test_two_viewers_on_one_catalogue_see_and_keep_each_others_labels(catalogue, tmp_path):
    out, tables = catalogue
    ids = [t["tube_id"] for t in tables["tubes"].to_pylist()][:6]
    assert len(ids) >= 2
    last = len(ids) - 1
    with serving(out, tmp_path / "c1", author="ann") as (a, _), serving(out, tmp_path / "c2", author="bob") as (b, _):
        errors = []

        def tag(base: str, name: str) -> None:
            for k, tube in enumerate(ids):
                status, answer = _post(base, json.dumps({"tubes": [tube], "tag": f"{name}{k}"}).encode(), JSON)
                if status != 200:
                    errors.append(answer)

        threads = [threading.Thread(target=tag, args=(base, name)) for base, name in ((a, "a"), (b, "b"))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors
        for base in (a, b):  # each server reads the other's labels
            with urllib.request.urlopen(f"{base}/api/tubes?set=all&tag=a0&tag=b{last}", timeout=30) as r:
                page = json.loads(r.read())
            assert sorted(t["tube_id"] for t in page["tubes"]) == sorted({ids[0], ids[last]})
    got = _tube_labels(out)
    for k, tube in enumerate(ids):
        assert {f"a{k}", f"b{k}"} <= set(got[tube][1])


def test_a_damaged_label_file_fails_the_label_views_naming_it_and_nothing_else(base_catalogue, tmp_path):
    import duckdb

    out = copy_of(base_catalogue, tmp_path / "c")
    labels.append(Store(out), labels.events(_ids(out, n=1), "tag", "kept"))
    bad = Path(out) / "labels" / "part-20260101T000000000000Z-000000000000.parquet"
    bad.write_bytes(b"PAR1 not really")
    con = connect(out)
    try:
        assert con.execute("SELECT count(*) FROM tubes").fetchone()[0] > 0  # the mined tables answer
        with pytest.raises(duckdb.Error, match=bad.name):
            con.execute("SELECT * FROM tube_labels").fetchall()
    finally:
        con.close()
    assert cli.main(["label", "--out", str(out), "--where", "selected", "--tag", "x"]) == 2  # refused, not written over
    assert bad.read_bytes() == b"PAR1 not really"


def _flip_a_label_value(path: Path) -> None:
    """Flip one bit of ``path`` where it still reads as a labels file but a value changes (the
    silent kind: a tag's dataset ``synthetic`` → ``synthethc`` detaches it from its tube)."""
    import pyarrow.parquet as pq

    data = path.read_bytes()
    before = pq.read_table(path)
    for i in range(4, len(data) - 8):  # past the header's magic, before the footer's
        for bit in (0x01, 0x10):
            flipped = bytearray(data)
            flipped[i] ^= bit
            path.write_bytes(bytes(flipped))
            try:
                after = pq.read_table(path)
            except Exception:  # noqa: BLE001 - a flip a decoder sees: not the case under test
                continue
            if after.schema == before.schema and not after.equals(before):
                return
    raise AssertionError(f"no single flipped bit of {path} changes a value and still reads")


def _sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_flipped_bit_in_a_label_file_is_named_as_damage_and_set_aside_never_read(base_catalogue, tmp_path,
                                                                                     capsys):
    """A flipped bit in a labels file changed a tag (detaching it from its tube) and every read
    answered, exit 0: label files carry their sha256 in their name, every read checks it, a damaged
    file fails the label tables alone (named, "damaged"), `mine status` lists it and
    `mine submit --verify` moves it, byte-identical, to labels/_damaged/, naming it."""
    from _jobs import mine
    from _run import cli as run_cli

    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    first, second = _ids(out, n=2)
    kept = labels.append(store, labels.events([first], "tag", "kept"))
    lost = labels.append(store, labels.events([second], "tag", "lost"))
    bad = Path(out) / lost
    _flip_a_label_value(bad)
    damaged_bytes = bad.read_bytes()

    with pytest.raises(InputError, match="sha256 mismatch: damaged"):
        labels.read_labels(store)
    rc, o, e = run_cli(capsys, "query", "SELECT * FROM tube_labels", "--out", str(out))
    assert rc == 2 and bad.name in e and "damaged" in e and len(e.strip().splitlines()) == 1, o + e
    rc, o, e = run_cli(capsys, "query", "SELECT count(*) AS n FROM tubes", "--out", str(out), "--format", "csv")
    assert rc == 0 and int(o.split()[1]) > 0, o + e  # the mined tables answer
    rc, o, e = run_cli(capsys, "status", "--out", str(out))
    assert rc == 1 and f"damaged  {lost}: sha256 mismatch: damaged" in o, o + e

    s = mine(out, verify=True)
    assert not s.failed, s.lines()
    aside = Path(out) / "labels" / "_damaged" / bad.name
    assert not bad.exists() and aside.read_bytes() == damaged_bytes  # set aside, byte-identical
    assert any(line.startswith("DAMAGED LABELS") and bad.name in line for line in s.lines()), s.lines()
    assert labels.label_files(store) == [kept]
    assert _tube_labels(out) == {first[2]: (None, ["kept"], "kept")}
    assert run_cli(capsys, "status", "--out", str(out))[0] == 0


def test_label_files_named_before_digests_still_read_and_a_compaction_records_them(base_catalogue, tmp_path):
    """A label file written before names carried a digest reads unchecked; a compaction writes
    its events into a file whose name carries the sha256 of its bytes."""
    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    tubes = _ids(out, n=2)
    old = "labels/part-20260101T000000000000Z-0123456789ab.parquet"
    store.write_table(old, labels.events(tubes[:1], "verdict", "object"))
    new = labels.append(store, labels.events(tubes[1:], "tag", "car"))
    assert _sha256(Path(out) / new) in new  # a new file's name carries its digest
    before = labels.read_labels(store)
    assert before.num_rows == 2
    assert labels.compact(store) == (2, 2)
    (merged,) = labels.label_files(store)
    assert merged.startswith("labels/compact-") and _sha256(Path(out) / merged) in merged
    assert labels.read_labels(store).equals(before)


def test_sixteen_writers_and_compactions_at_once_lose_nothing_and_every_file_checks_out(base_catalogue, tmp_path):
    """Sixteen writers, two compactors and a reader on one catalogue at once: every event is kept,
    no read fails (a file a compaction removed between a listing and its read is listed again) and
    every label file's name carries the sha256 of its bytes."""
    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    tubes = _ids(out)
    written: list[str] = []
    errors: list[BaseException] = []
    done = threading.Event()

    def writer(k: int) -> None:
        try:
            for j in range(6):
                t = labels.events([tubes[(k + j) % len(tubes)]], "tag", f"w{k}-{j}", author=f"w{k}")
                labels.append(store, t)
                written.extend(t["label_id"].to_pylist())
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    merges: list[int] = []

    def compactor() -> None:
        try:
            while not done.is_set():
                merges.append(labels.compact(store, lock_wait_s=30)[0])
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    def reader() -> None:
        try:
            while not done.is_set():
                labels.read_labels(store)
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    background = [threading.Thread(target=f) for f in (compactor, compactor, reader)]
    writers = [threading.Thread(target=writer, args=(k,)) for k in range(16)]
    for t in background + writers:
        t.start()
    for t in writers:
        t.join()
    done.set()
    for t in background:
        t.join()
    assert not errors, errors
    assert sum(merges) > 0  # the compactions merged files while the writers wrote
    labels.compact(store)
    assert sorted(labels.read_labels(store)["label_id"].to_pylist()) == sorted(written)
    assert len(written) == 16 * 6
    for rel in labels.label_files(store):
        assert _sha256(Path(out) / rel) in rel, rel
