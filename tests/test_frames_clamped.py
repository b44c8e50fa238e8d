"""``--frames A:B`` past a sequence's end is cut to the frames it has, and the summary says so
(before, `mine submit` and `mine render` cut it silently): a user who asked for 0:400 of a
12-frame sequence reads ``frames 0:400 asked, 0:12 exist: mined 0:12``."""

from __future__ import annotations

from _jobs import N_FRAMES, SEQ, tiny_cfg

from mining.checks import clamped_note
from mining.export.render import run_render
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job


def test_the_note_says_what_was_asked_what_exists_and_what_was_done():
    assert clamped_note("0005", (0, 400), 16) == "sequence 0005: frames 0:400 asked, 0:16 exist: mined 0:16"
    assert clamped_note("0005", (3, 400), 16, "rendered") == "sequence 0005: frames 3:400 asked, 0:16 exist: rendered 3:16"
    assert clamped_note("0005", (0, 16), 16) is None and clamped_note("0005", (0, None), 16) is None


def test_submit_says_a_range_past_the_end_was_cut(tmp_path):
    summary = mine_job(tiny_cfg(), str(tmp_path / "cat"), ["0000"], (0, 400), executor=LocalExecutor)
    lines = summary.lines()
    assert "sequence 0000: frames 0:400 asked, 0:12 exist: mined 0:12" in lines, lines
    assert summary.ok == 2 and summary.frames == 12
    fits = mine_job(tiny_cfg(), str(tmp_path / "cat2"), ["0000"], (0, 12), executor=LocalExecutor)
    assert not any("asked" in ln for ln in fits.lines()), fits.lines()


def test_render_says_a_range_past_the_end_was_cut(base_catalogue, tmp_path, capsys):
    out, _ = base_catalogue
    capsys.readouterr()
    assert run_render(str(out), SEQ, str(tmp_path / "all.webm"), frames=(10, 400)) == 0
    said = capsys.readouterr().out.splitlines()
    assert said[0] == f"mine render: sequence {SEQ}: frames 10:400 asked, 0:{N_FRAMES} exist: rendered 10:{N_FRAMES}"
    assert said[1].startswith(f"mine render: {N_FRAMES - 10} frames, "), said
