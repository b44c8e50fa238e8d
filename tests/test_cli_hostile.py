"""No traceback reaches a user: every option of every ``mine`` command is checked before any
work starts, and a bad value is one line on standard error, exit status 2.

The commands are found by walking ``cli.build_parser()`` (every group's sub-commands are
loaded), so a new command or option is covered without a line here. Each option is put in
one class by its argparse ``type``: a checked number (``mining.checks.count`` / ``real``…,
the frame range, a memory size) gets the hostile numbers, a checked path
(``input_file``, ``output_file``, ``path_text``…) the hostile paths; an option of neither
kind must be a choice, a flag, or listed in FREE_TEXT with the reason it is no number and no
path. An option with a bare ``type=int`` or ``float`` (which take ``nan``, ``inf``, ``1e308``)
fails ``test_every_option_is_checked_by_its_type``.

Each case runs ``mine`` in this process (``_run.cli``): the refusal must come from the parser
or the preflight (``cli.main``'s ``check_paths``), within milliseconds; an alarm fails a
case that starts real work instead. A value an option legitimately takes (``--port 0``,
frame 0) is listed in ALLOWED with the reason, and not run.
"""

from __future__ import annotations

import argparse
import signal
import time
from pathlib import Path

import pytest

from _run import cli, command_parsers, valued_options
from mining import cli as cli_module
from mining.checks import Number, PathType
from mining.cli import build_parser
from mining.pipeline.arguments import frame_range

HOSTILE_NUMBERS = ["nan", "inf", "-inf", "-1", "0", "1e308", "1" + "0" * 30, "１"]  # the last: a full-width digit one
HOSTILE_PATHS = {
    "300-character name": "x" * 300,
    "path too long": "/" + "d/" * 2100,
    "under /proc": "/proc/x/y",
    "undecodable bytes": "caf\udce9",  # b"caf\xe9" (Latin-1) as Python decodes an argument that is not UTF-8
    "newline": "a\nb",
    "text-direction override": "report\u202enosj.exe",
}
# (command, option, value) → why the value is fine for that option (such a case starts real work: not run)
ALLOWED = {
    ("submit", "--lock-wait", "0"): "0 s: refuse at once when another submit holds the lock (the default)",
    ("query", "--limit", "0"): "0 = show every row",
    ("label", "--lock-wait", "0"): "0 s: --compact refuses at once when a submit holds the lock (the default)",
    ("export", "--margin", "0"): "no context around the box",
    ("embed", "--margin", "0"): "no context around the box",
    ("embed", "--actors", "-1"): "-1 = one actor per GPU Ray lists, else one per CPU (the default)",
    ("embed", "--actors", "0"): "0 = actors on the CPUs only, one per CPU, even where Ray lists GPUs",
    ("embed", "--lock-wait", "0"): "0 s: refuse at once when a submit holds the lock (the default)",
    ("view", "--port", "0"): "0 picks a free port",
    ("bench calibrate", "--epsilon1", "0"): "a log-odds price: 0 is the default",
    ("bench calibrate", "--epsilon1", "-1"): "a log-odds price is signed (select.price.calibrated)",
    ("bench calibrate", "--epsilon2", "0"): "no overlap penalty (select.overlap_weight.calibrated ≥ 0)",
    ("eval synthetic", "--min-visible-px", "0"): "0 keeps every object",
    ("bench scale", "--gpus", "0"): "a cluster without GPUs (the models on the CPU cores)",
    ("bench scale", "--ray-frames", "0"): "0 skips the job on a local Ray",
    ("bench scale", "--ray-gpus", "0"): "0: the local Ray announces the GPUs it finds",
    ("bench stages", "--gpu-ms", "0"): "an emulated GPU that takes no time (the CPU front alone)",
    ("bench similar", "--group-size", "0"): "0 skips the grouping",
    ("label", "--group", "0"): "group 0 is the first group",
    ("label", "--group", "-1"): "-1 labels the tubes HDBSCAN left out of every group (its noise)",
}
FRAME_ZERO = "frame 0 is the first frame (A = 0, one frame)"
# Options that are neither numbers nor paths: why (their values are checked where they are used).
FREE_TEXT = {
    "--dataset": "a source name, checked by the config (mining/checks.py OneOf)",
    "--set": "KEY=VALUE config overrides, checked by the config's rules before any work (tests/test_config_*)",
    "--option": "KEY=VALUE source options, checked by the source's rules before any work",
    "--grid": "KEY=V1,V2 config overrides of a grid, checked by the config's rules",
    "--sequences": "names, checked by mining/names.py (cli._check_names, the preflight)",
    "--sequence": "a name, checked by mining/names.py",
    "--seeds": "synthetic sequence names",
    "--train-seeds": "synthetic sequence names",
    "--test-seed": "a synthetic sequence name",
    "--synthetic-sequence": "a synthetic sequence name",
    "--scenarios": "scenario names, looked up in mining/sources/synthetic/scenarios.py",
    "--classes": "KITTI class names",
    "--address": "a URL or HOST:PORT of a Ray cluster",
    "--host": "an interface address (IP)",
    "--job": "a Ray Jobs submission id",
    "--where": "an SQL predicate (read-only, mining/catalog/views.py)",
    "--output": "mine embed: an output name of the ONNX model, checked against the model's outputs",
    "--tag": "a free label, checked by mining/catalog/labels.check_text",
    "--untag": "a free label, checked by mining/catalog/labels.check_text",
    "--author": "a name, checked by mining/catalog/labels.check_text",
    "sql": "an SQL statement (read-only, mining/catalog/views.py)",
    "keys": "mine config's filter: matched against the config's key names, never a path or a number",
    "tube_id": "a tube id, checked by mining/names.py (tube_id_argument) in the parser",
    "--like": "a tube id, checked by mining/names.py (tube_id_argument) in the parser",
    "--undo-like": "a tube id, checked by mining/names.py (tube_id_argument) in the parser",
    "--model": "mine similar: an embedding model's file name or sha256 prefix, matched against tube_embeddings",
    "--sizes": "comma-separated tube counts, each checked by mining/checks.py count in the parser",
}
CASE_S = 10  # seconds one case may take before it counts as real work started


PARSER = build_parser()  # one parser for every case (main's own build costs ~10 ms, a parse well under 1 ms)


COMMANDS = command_parsers(PARSER)


def _name(a: argparse.Action) -> str:
    return a.option_strings[-1] if a.option_strings else a.dest


def _kind(a: argparse.Action) -> str | None:
    if isinstance(a.type, Number) or a.type is frame_range or getattr(a.type, "kind", None) == "number":
        return "number"
    if isinstance(a.type, PathType):
        return "path"
    return None


def _benign(a: argparse.Action, tmp: Path) -> str:
    """A value a required option takes without complaint."""
    if a.choices:
        return str(next(iter(a.choices)))
    if isinstance(a.type, PathType):
        (tmp / "in").mkdir(exist_ok=True)
        (tmp / "in.txt").write_text("")
        return {"input-file": str(tmp / "in.txt"), "input-folder": str(tmp / "in"), "input": str(tmp / "in"),
                "output-file": str(tmp / "o" / "dest.mp4")}.get(a.type.role, str(tmp / "o" / "out"))
    return {"sql": "SELECT 1", "--sequence": "0000", "--sequences": "0000"}.get(_name(a), "x")


def test_every_option_is_checked_by_its_type():
    loose = []
    for command, parser in COMMANDS:
        for a in valued_options(parser):
            if a.choices or _kind(a) is not None or _name(a) in FREE_TEXT:
                continue
            loose.append(f"mine {command} {_name(a)} (type {getattr(a.type, '__name__', a.type)})")
    assert not loose, ("options without a checked type (mining/checks.py: count, real, input_file, output_file, …) "
                       f"or a reason in FREE_TEXT: {loose}")


def test_the_walk_finds_every_command():
    names = [c for c, _ in COMMANDS]
    assert {"submit", "status", "query", "export", "render", "config", "view", "label", "describe", "similar", "group",
            "embed"} \
        == {c.name for c in cli_module.COMMANDS if c.group is None}
    assert {" ".join(filter(None, (c.group, c.name))) for c in cli_module.COMMANDS} == set(names)
    assert len(set(names)) == len(names)


def _cases(command: str, parser: argparse.ArgumentParser) -> list[tuple[argparse.Action, str]]:
    out = []
    for a in valued_options(parser):
        kind = _kind(a)
        values = HOSTILE_NUMBERS if kind == "number" else list(HOSTILE_PATHS.values()) if kind == "path" else []
        for v in values:
            if (command, _name(a), v) in ALLOWED or (a.type is frame_range and v == "0"):
                continue
            out.append((a, v))
    return out


class _Alarm(Exception):
    pass


def _alarm(signum, frame):
    raise _Alarm()


@pytest.mark.parametrize("command", [c for c, _ in COMMANDS])
def test_hostile_values_are_one_line_and_exit_2_before_any_work(command, tmp_path, capsys, monkeypatch):
    parser = dict(COMMANDS)[command]
    monkeypatch.chdir(tmp_path)  # a value that slips through writes here, not in the checkout
    monkeypatch.setattr(cli_module, "build_parser", lambda: PARSER)
    required = [a for a in valued_options(parser) if a.required]
    failures = []
    old = signal.signal(signal.SIGALRM, _alarm)
    t0 = time.perf_counter()
    try:
        for action, value in _cases(command, parser):
            rest: list[str] = []
            for r in required:
                if r is not action:
                    rest += ([r.option_strings[-1]] if r.option_strings else []) + [_benign(r, tmp_path)]
            hostile = [action.option_strings[-1], value] if action.option_strings else [value]
            signal.setitimer(signal.ITIMER_REAL, CASE_S)
            try:
                rc, out, err = cli(capsys, *command.split(), *hostile, *rest)
            except _Alarm:
                failures.append(f"{_name(action)} {value!r}: still running after {CASE_S} s (real work started)")
                continue
            except BaseException as e:  # noqa: BLE001 - a traceback is the failure this test is for
                failures.append(f"{_name(action)} {value!r}: raised {type(e).__name__}: {e}")
                continue
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            lines = [ln for ln in err.splitlines() if ln.strip()]
            shown = value.encode("ascii", "backslashreplace").decode()
            named = lines and (_name(action) in lines[0] or action.dest.upper() in lines[0] or value in lines[0]
                               or shown in lines[0] or value[:40] in lines[0])
            if rc != 2 or len(lines) != 1 or "Traceback" in err or out or not named:
                failures.append(f"{_name(action)} {value[:50]!r}: rc {rc}, stdout {out[:100]!r}, stderr {err[-300:]!r}")
    finally:
        signal.signal(signal.SIGALRM, old)
    assert not failures, f"mine {command}:\n" + "\n".join(failures)
    assert time.perf_counter() - t0 < 30
