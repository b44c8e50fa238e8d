"""``--frames A:B`` past a sequence's end is cut to the frames it has, and the summary says so
(before, `mine submit` and `mine render` cut it silently): a user who asked for 0:400 of a
12-frame sequence reads ``frames 0:400 asked, 0:12 exist: mined 0:12``."""

from __future__ import annotations

import pytest

from _jobs import N_FRAMES, SEQ, tiny_cfg

from mining.checks import clamped_note
from mining.export.render import run_render
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job


def test_the_note_says_what_was_asked_what_exists_and_what_was_done():
    assert clamped_note("0005", (0, 400), 16) == "sequence 0005: frames 0:400 asked, 0:16 exist: mined 0:16"
    assert clamped_note("0005", (3, 400), 16, "rendered") == "sequence 0005: frames 3:400 asked, 0:16 exist: rendered 3:16"
    assert clamped_note("0005", (0, 16), 16) is None and clamped_note("0005", (0, None), 16) is None


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_submit_says_a_range_past_the_end_was_cut(tmp_path):
    summary = mine_job(tiny_cfg(), str(tmp_path / "cat"), ["0000"], (0, 400), executor=LocalExecutor)
    lines = summary.lines()
    assert "sequence 0000: frames 0:400 asked, 0:12 exist: mined 0:12" in lines, lines
    assert summary.ok == 2 and summary.frames == 12
    fits = mine_job(tiny_cfg(), str(tmp_path / "cat2"), ["0000"], (0, 12), executor=LocalExecutor)
    assert not any("asked" in ln for ln in fits.lines()), fits.lines()


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_render_says_a_range_past_the_end_was_cut(base_catalogue, tmp_path, capsys):
    out, _ = base_catalogue
    capsys.readouterr()
    assert run_render(str(out), SEQ, str(tmp_path / "all.webm"), frames=(10, 400)) == 0
    said = capsys.readouterr().out.splitlines()
    assert said[0] == f"mine render: sequence {SEQ}: frames 10:400 asked, 0:{N_FRAMES} exist: rendered 10:{N_FRAMES}"
    assert said[1].startswith(f"mine render: {N_FRAMES - 10} frames, "), said


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_render_all_candidates_draws_the_unselected_ones_dimmed(base_catalogue, tmp_path, capsys):
    """``--all-candidates``: the candidates co-selection left out are drawn too (outline and
    label in a dimmed colour), under the selected tubes, and counted apart."""
    import cv2
    import numpy as np

    from mining.catalog.views import connect

    out, _ = base_catalogue
    con = connect(out)
    unselected = con.sql(f"SELECT count(*) FROM tubes WHERE sequence = '{SEQ}' AND NOT selected AND t_start < 4 "
                         "AND t_end >= 0").fetchone()[0]
    con.close()
    assert unselected > 0, "the base job has no unselected candidates in frames 0:4: nothing to tell apart"
    plain, every = tmp_path / "plain.webm", tmp_path / "every.webm"
    assert run_render(str(out), SEQ, str(plain), frames=(0, 4)) == 0
    first = capsys.readouterr().out.splitlines()[-1]
    assert run_render(str(out), SEQ, str(every), frames=(0, 4), all_candidates=True) == 0
    said = capsys.readouterr().out.splitlines()[-1]
    n_sel = int(first.split(" frames, ")[1].split(" tubes")[0])
    assert said.startswith(f"mine render: 4 frames, {n_sel} tubes and "), (first, said)
    assert int(said.split(" tubes and ")[1].split(" unselected")[0]) > 0, said

    def frames(path):
        cap, got = cv2.VideoCapture(str(path)), []
        while (ok := cap.read())[0]:
            got.append(ok[1].astype(np.int16))
        cap.release()
        return got

    a, b = frames(plain), frames(every)
    assert len(a) == len(b) == 4
    changed = [np.mean(np.abs(x - y).max(axis=2) > 40) for x, y in zip(a, b)]  # the candidates' outlines and labels
    assert max(changed) > 0.001, changed
    cv2.imwrite(str(tmp_path / "every0.png"), b[0].astype(np.uint8))
