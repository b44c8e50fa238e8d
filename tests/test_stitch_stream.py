"""The streaming stitch (``stitch_windows``: parts read window by window, tubes settled group by group,
co-selection at the end) writes what the batch stitch wrote (``tests/_stitch_reference.py``, the stitch
as it was): the same rows, values, order, schema and metadata, on a synthetic sequence of 240 frames
mined into six windows, with a failed window in the middle, with fragments linked across windows;
and a part of another schema still fails naming the file and the columns."""

from __future__ import annotations

import pyarrow as pa
import _stitch_reference
import pytest
from _stitch_reference import reference_stitch

from mining.catalog.layout import part_path
from mining.catalog.rows import RunInfo, to_table
from mining.catalog.store import Store
from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.stitch import check_parts, concat_parts, stitch_sequence, stitch_windows
from mining.pipeline.submit import mine_job
from mining.sources.synthetic import SyntheticSource
from mining.tubes.link import link_fragments
from mining.types import plan_windows

from conftest import REPO

N_FRAMES, CORE, CONTEXT = 240, 40, 12  # ours: six windows, enough tubes to cross several borders, ~1 min of mining


def _same(a: dict[str, pa.Table], b: dict[str, pa.Table]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].schema.equals(b[k].schema, check_metadata=True), k
        assert a[k].equals(b[k]), k
        assert a[k].to_pylist() == b[k].to_pylist(), k


@pytest.fixture(scope="module")
def mined(tmp_path_factory):
    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        f"source.options.n_frames={N_FRAMES}", "source.options.width=414", "source.options.height=125",
        f"window.core={CORE}", f"window.context_before={CONTEXT}", f"window.context_after={CONTEXT}"])
    out = tmp_path_factory.mktemp("stream") / "catalog"
    assert mine_job(cfg, str(out), ["0000"], executor=LocalExecutor).ok
    windows = plan_windows(SyntheticSource(**cfg.source.options).plan("0000"), CORE, CONTEXT, CONTEXT)
    store = Store(str(out))
    parts = {w.name: {t: store.read_table(part_path(t, "synthetic", "0000", w.name))
                      for t in ("tubes", "tube_frames", "frames")} for w in windows}
    return cfg, windows, parts


def _both(cfg, windows, parts):
    tables = {t: pa.concat_tables([parts[w.name][t] for w in windows]) for t in ("tubes", "tube_frames", "frames")}
    run = RunInfo("synthetic", "0000", "run", cfg.params_hash, 0.5)
    ref = reference_stitch(windows, tables["tubes"], tables["tube_frames"], tables["frames"], cfg, run)
    streamed = stitch_windows(windows, lambda w: parts[w.name]["tube_frames"], tables["frames"], cfg, run)
    whole = stitch_sequence(windows, tables["tubes"], tables["tube_frames"], tables["frames"], cfg, run)
    return ref, streamed, whole


@pytest.mark.slow  # mines 240 frames in this process
def test_the_streaming_stitch_writes_what_the_batch_stitch_wrote(mined):
    cfg, windows, parts = mined
    assert len(windows) == N_FRAMES // CORE
    ref, streamed, whole = _both(cfg, windows, parts)
    assert ref["tubes"].num_rows > 50 and sum(ref["tubes"].column("selected").to_pylist()) > 5
    assert max(ref["tubes"].column("n_windows").to_pylist()) >= 3, "no tube crosses two borders: nothing stitched"
    _same(ref, streamed)
    _same(ref, whole)


@pytest.mark.slow
def test_a_failed_window_in_the_middle_is_not_stitched_across(mined):
    cfg, windows, parts = mined
    kept = windows[:2] + windows[3:]
    ref, streamed, whole = _both(cfg, kept, parts)
    frames = set(ref["tube_frames"].column("frame").to_pylist())
    assert not frames & set(range(*windows[2].core))
    _same(ref, streamed)
    _same(ref, whole)


@pytest.mark.slow
def test_fragments_linked_across_windows_come_out_the_same(mined, monkeypatch):
    cfg, windows, parts = mined
    cfg.tubes.link_min_common = 1  # ours: looser links, so that chains of fragments cross borders
    cfg.tubes.link_agree_share = 0.5
    joined = []

    def recording(tubes, tcfg, first_id):
        out = link_fragments(tubes, tcfg, first_id)
        joined.extend(t for t, _ in out)
        return out

    monkeypatch.setattr(_stitch_reference, "link_fragments", recording)
    ref, streamed, _ = _both(cfg, windows, parts)
    cores = [w.core for w in windows]
    spans = [{i for f in t.frames for i, (a, b) in enumerate(cores) if a <= f.frame < b} for t in joined]
    assert max(map(len, spans), default=0) >= 3, "no joined tube spans three windows' cores"
    _same(ref, streamed)


def test_parts_of_another_schema_fail_naming_the_file_and_the_columns():
    good = to_table([], "tube_frames", part=True)
    bad = good.drop_columns(["core"])
    with pytest.raises(InputError) as e:
        check_parts("tube_frames", [("a.part", good.schema), ("b.part", bad.schema), ("c.part", good.schema)])
    assert "b.part" in str(e.value) and "column core is missing here" in str(e.value) and "a.part" in str(e.value)
    with pytest.raises(InputError) as e2:
        concat_parts("tube_frames", [("a.part", good), ("b.part", bad)])
    assert str(e2.value) == str(e.value)
    assert concat_parts("tube_frames", [("a.part", good), ("c.part", good)]).num_rows == 0

