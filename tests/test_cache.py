"""The observation cache (issue 11, item 1): nothing in it can run code, and a damaged one is said.

* A damaged, foreign or outdated observation cache is a clear InputError naming the file:
  the observe step recomputes its window, a track step that meets one fails its window with
  that reason, and nothing in the file can run code.
* Nothing executes from the output folder: a pickle payload planted at every
  observation-cache path, old (``.pkl``) and new, never runs on a resubmit. The observe
  steps run, then someone who can write to ``--out`` replaces every cache with a payload
  whose ``__reduce__`` writes a marker file, and the job is resubmitted.

Real frames: small synthetic recordings observed by the pipeline's own observe step, mined in
this process (LocalExecutor, real files)."""

from __future__ import annotations

import builtins
import io
import pickle
from pathlib import Path

import numpy as np
import pytest
import zstandard

from mining.catalog.layout import cache_path, manifest_path
from mining.catalog.store import Store
from mining.catalog.views import connect
from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.steps import Observe, StepResult, Track
from mining.pipeline.submit import mine_job, open_job
from _jobs import tiny_cfg
from conftest import REPO

# Every name an observation cache has had: pickle before issue 11, zstd-framed NPZ since.
CACHE_NAMES = ("{w}.pkl", "{w}.npz.zst")


def _cfg():
    return load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=12", "source.options.width=621", "source.options.height=188",
        "source.options.fx=360.77", "window.core=6", "window.context_before=2", "window.context_after=2"])


def _observed(out: str):
    """(job, windows) of a job whose observe steps ran and whose tracks did not."""
    job, schedule, _ = open_job(_cfg(), out)
    for w in schedule.windows:
        assert Observe(job).run(w).ok
    return job, schedule.windows


def _tubes(out: str) -> list[tuple]:
    con = connect(out)
    try:
        return con.execute("SELECT tube_id, t_start, t_end, n_frames, round(score, 9), selected FROM tubes "
                           "ORDER BY tube_id").fetchall()
    finally:
        con.close()


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_resubmit_recomputes_a_truncated_cache(tmp_path):
    clean = str(tmp_path / "clean")
    assert mine_job(_cfg(), clean, executor=LocalExecutor).ok == 2
    out = str(tmp_path / "out")
    _, windows = _observed(out)
    path = Path(out) / cache_path(windows[0])
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    summary = mine_job(_cfg(), out, executor=LocalExecutor)
    assert summary.ok == 2 and not summary.failed
    assert _tubes(out) == _tubes(clean)
    assert list(summary.recomputed) == [windows[0].name] and str(path) in summary.recomputed[windows[0].name]
    assert any(line.startswith(f"RECOMPUTED {windows[0].name}: ") for line in summary.lines())


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_a_track_that_meets_a_damaged_cache_fails_its_window_with_the_reason(tmp_path):
    out = str(tmp_path / "out")
    job, (first, second) = _observed(out)
    path = Path(out) / cache_path(second)  # the first window's context reaches into the second's core
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    observed = [StepResult(w.name, True, cached=True) for w in (first, second)]
    result = Track(job).run(first, [first, second], observed)
    assert not result.ok
    assert str(path) in result.error and "damaged observation cache" in result.error
    row = Store(out).read_table(manifest_path(first.dataset, first.sequence, first.name)).to_pylist()[0]
    assert row["status"] == "failed" and str(path) in row["error"]


class _Payload:
    """Unpickling this runs ``code``: what an attacker plants."""

    def __init__(self, code: str):
        self.code = code

    def __reduce__(self):
        return builtins.exec, (self.code,)


def _arrays(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(zstandard.ZstdDecompressor().decompress(data)), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _pack(arrays: dict, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=allow_pickle, **arrays)
    return zstandard.ZstdCompressor(write_checksum=True).compress(buf.getvalue())


def _flip(data: bytes, at: float) -> bytes:
    b = bytearray(data)
    b[int(len(b) * at)] ^= 0x01
    return bytes(b)


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_every_kind_of_bad_cache_is_an_input_error_naming_the_file(tmp_path):
    from mining.pipeline.cache import decode_frames, encode_frames

    out = str(tmp_path / "out")
    _, windows = _observed(out)
    good = (Path(out) / cache_path(windows[0])).read_bytes()
    frames = decode_frames(good, "good")
    assert len(frames) == 6 and sum(len(f.observations) for f in frames) > 0
    assert encode_frames(frames) == good, "the format round-trips"

    marker = tmp_path / "pwned"
    arrays = _arrays(good)
    bad = {
        "empty": (b"", "not a zstd frame"),
        "a pickle": (pickle.dumps(_Payload(f"open({str(marker)!r}, 'w')")), "not a zstd frame"),
        "a plain NPZ": (_np_bytes(arrays), "not a zstd frame"),
        "truncated": (good[: len(good) // 2], "damaged observation cache"),
        "a flipped bit (early)": (_flip(good, 0.1), "damaged observation cache"),
        "a flipped bit (late)": (_flip(good, 0.9), "damaged observation cache"),
        "another version": (_pack({**arrays, "version": np.array(99)}), "version 99"),
        "another format": (_pack({**arrays, "format": np.array("something else")}), "format something else"),
        "an array missing": (_pack({k: v for k, v in arrays.items() if k != "boxes"}), "without ['boxes']"),
        "a wrong shape": (_pack({**arrays, "boxes": arrays["boxes"][:-1]}), "boxes has"),
        "a wrong dtype": (_pack({**arrays, "position": arrays["position"].astype(np.float64)}), "position has"),
        "an object array": (_pack({**arrays, "boxes": np.array([_Payload(f"open({str(marker)!r}, 'w')")] * 3,
                                                               dtype=object)}, allow_pickle=True),
                            "damaged observation cache"),
    }
    for what, (data, reason) in bad.items():
        with pytest.raises(InputError) as e:
            decode_frames(data, "/out/_cache/obs/w.npz.zst")
        assert "/out/_cache/obs/w.npz.zst" in str(e.value) and reason in str(e.value), what
    assert not marker.exists(), "a planted payload ran"


def _np_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_planted_pickles_never_run_on_resubmit(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps(_Payload(f"open({str(marker)!r}, 'w').write('ran')"))
    pickle.loads(payload)  # the control: the payload is live
    assert marker.read_text() == "ran"
    marker.unlink()

    cfg = tiny_cfg()
    clean = str(tmp_path / "clean")
    assert mine_job(cfg, clean, executor=LocalExecutor).ok == 2

    # A job whose observe steps ran and whose driver died before any track.
    out = str(tmp_path / "out")
    job, schedule, _ = open_job(cfg, out)
    for w in schedule.windows:
        assert Observe(job).run(w).ok
    store = Store(out)
    planted = []
    for w in schedule.windows:
        for name in CACHE_NAMES:
            rel = f"_cache/obs/dataset={w.dataset}/sequence={w.sequence}/{name.format(w=w.name)}"
            store.write_bytes(rel, payload)
            planted.append(rel)
    assert len(planted) == 4 and all(store.exists(rel) for rel in planted)

    summary = mine_job(cfg, out, executor=LocalExecutor)  # the resubmission

    assert not marker.exists(), "a planted pickle ran"
    assert summary.ok == 2 and not summary.failed
    assert sorted(summary.recomputed) == [w.name for w in schedule.windows], "the planted caches are reported"
    assert _tubes(out) == _tubes(clean), "the recomputed windows give the clean run's catalogue"
    assert not any(store.exists(rel) for rel in planted), "the caches (and the old .pkl ones) are gone after use"
