"""The command registry of ``mining/cli.py``: every command (a top-level verb of ``mining/commands/``
or a ``mine GROUP NAME`` command) is one row whose module adds its options and runs it, a
command's module is imported only when that command is parsed, and ``cli.main`` says every
error a command raises in one line with its exit status."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from conftest import REPO
from mining.cli import COMMANDS, GROUPS, build_parser, main


VERBS = ("submit", "status", "query", "export", "label", "describe", "embed", "similar", "group", "render", "config",
         "view")


def test_every_command_module_offers_add_arguments_and_run():
    assert {c.group for c in COMMANDS} == {None, *GROUPS}
    assert tuple(c.name for c in COMMANDS if c.group is None) == VERBS
    assert all(c.module == f"mining.commands.{c.name}" for c in COMMANDS if c.group is None)
    assert all(not c.names_errors for c in COMMANDS if c.group is not None)
    assert len({(c.group, c.name) for c in COMMANDS}) == len(COMMANDS)
    for c in COMMANDS:
        module = importlib.import_module(c.module)
        assert callable(module.add_arguments) and callable(module.run), c.module


@pytest.mark.parametrize("argv, module", [
    (["bench", "scenarios", "--half"], "mining.bench.scenarios"),
    (["eval", "synthetic"], "mining.bench.synthetic"),
    (["eval", "kitti-mot", "--gt", "tests", "--results", "tests", "--sequences", "0000"], "mining.eval.kitti_mot"),
    (["track", "images", "--sequence", "0000", "--out", "o", "--frames", "2:5"], "mining.pipeline.track_images"),
    (["status"], "mining.commands.status"),
    (["query", "SELECT 1"], "mining.commands.query"),
    (["label", "--compact"], "mining.commands.label"),
])
def test_a_parsed_command_runs_its_module(argv, module, monkeypatch):
    monkeypatch.chdir(REPO)  # the input folders the command lines name (--gt, --results) exist there
    args = build_parser().parse_args(argv)
    assert args.func is importlib.import_module(module).run


def test_parsing_another_command_imports_no_command_module():
    # OpenCV, SciPy and ONNX Runtime come with the bench modules, DuckDB and Arrow with the catalogue's
    # commands: `mine status` must not load them.
    code = ("import sys; from mining.cli import COMMANDS, build_parser; build_parser().parse_args(['status']); "
            "print(sorted(c.module for c in COMMANDS if c.module in sys.modules)); "
            "print(sorted(m for m in ('cv2', 'scipy', 'onnxruntime', 'duckdb', 'ray') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.split("\n")[:2] == ["['mining.commands.status']", "[]"], out


# -- every error one line, said once by cli.main ----------------------------------------------

def _main(capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(list(argv))
    got = capsys.readouterr()
    return rc, got.out, got.err


@pytest.mark.parametrize("argv, err", [
    (["query", "SELECT 1", "--format", "parquet"], "mine query: --format parquet needs --output FILE\n"),
    (["label", "--where", "true", "--compact"], "mine label: --compact takes no --where and no decision\n"),
    (["label"], 'mine label: give --where PREDICATE (the tubes to label), e.g. --where "known = false"\n'),
    (["label", "--where", "true", "--verdict", "object", "--tag", "x"],
     "mine label: give exactly one of --verdict V, --clear-verdict, --tag T, --untag T (got --verdict, --tag), "
     "or --compact\n"),
    (["export", "DEST", "--format", "kitti", "--margin", "0.2"], "mine export: --margin applies to --format crops only\n"),
    (["export", "DEST", "--format", "kitti", "--images"],
     "mine export: --images applies to --format youtube-vis, tao, burst, fiftyone, rerun only\n"),
    (["status", "--job", "x"], "mine: error: --job needs --address http://HEAD:8265\n"),
    (["submit", "--new-run", "--extend", "--dataset", "synthetic"],
     "mine: error: --new-run and --extend exclude each other\n"),
])
def test_a_commands_refusal_is_one_line_in_its_name_or_mines_with_exit_status_2(capsys, tmp_path, monkeypatch,
                                                                                  argv, err):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out" / "catalog").mkdir(parents=True)  # the default --out: a folder, no catalogue in it
    argv = [str(tmp_path / "dest") if a == "DEST" else a for a in argv]
    assert _main(capsys, *argv) == (2, "", err)


@pytest.mark.parametrize("command", ["query", "export", "render", "label", "embed"])
def test_a_missing_catalogue_is_said_in_the_commands_name(capsys, tmp_path, command):
    missing = tmp_path / "missing"
    (tmp_path / "model.onnx").write_bytes(b"not read: the catalogue is looked at first")
    argv = {"query": ["query", "SELECT 1"], "export": ["export", str(tmp_path / "d"), "--format", "kitti"],
            "render": ["render", str(tmp_path / "r.mp4"), "--sequence", "0000"],
            "label": ["label", "--where", "true", "--verdict", "object"],
            "embed": ["embed", "--model", str(tmp_path / "model.onnx"), "--local"]}[command]
    where = f"--out {missing}" if command == "label" else f"file {missing}"
    assert _main(capsys, *argv, "--out", str(missing)) == (2, "", f"mine {command}: {where}: catalogue folder not found\n")


def test_the_checks_before_a_command_runs_are_mines_and_a_bad_sequence_name_too(capsys, tmp_path):
    (tmp_path / "exists.csv").write_text("")
    rc, out, err = _main(capsys, "query", "SELECT 1", "--out", str(tmp_path), "--format", "csv",
                         "--output", str(tmp_path / "exists.csv"))
    assert (rc, out, err) == (2, "", f"mine: error: --output {tmp_path / 'exists.csv'}: exists; pass --overwrite "
                                     "to replace it, or choose another name\n")
    rc, out, err = _main(capsys, "render", str(tmp_path / "r.mp4"), "--out", str(tmp_path), "--sequence", "../x")
    assert (rc, out) == (2, "") and err.startswith("mine: error: sequence name '../x' from --sequence is not a safe "
                                                   "name"), err


def test_a_failed_write_and_a_duckdb_error_are_said_in_the_commands_name(capsys, tmp_path, monkeypatch):
    import duckdb

    from mining.catalog import query as query_module
    from mining.export import render as render_module
    from mining.export import run as export_module

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    def damaged(*args, **kwargs):
        raise duckdb.IOException("IO Error: the file is damaged")

    out = str(tmp_path / "out")
    monkeypatch.setattr(query_module, "query_table", full)
    dest = tmp_path / "q.csv"
    assert _main(capsys, "query", "SELECT 1", "--out", out, "--format", "csv", "--output", str(dest)) == (
        2, "", f"mine query: cannot write {dest}: [Errno 28] No space left on device\n")
    monkeypatch.setattr(query_module, "query_table", damaged)
    assert _main(capsys, "query", "SELECT 1", "--out", out) == (2, "", "mine query: IO Error: the file is damaged\n")
    for command, module, name, argv in (("export", export_module, "export", [str(tmp_path / "d"), "--format", "kitti"]),
                                        ("render", render_module, "render", [str(tmp_path / "r.mp4"), "--sequence", "s"])):
        monkeypatch.setattr(module, name, full)
        assert _main(capsys, command, *argv, "--out", out) == (
            2, "", f"mine {command}: file {argv[0]}: cannot be written: no space left on device (free some space "
                   "and run the command again)\n")
        monkeypatch.setattr(module, name, damaged)
        assert _main(capsys, command, *argv, "--out", out) == (2, "", f"mine {command}: IO Error: the file is damaged\n")


@pytest.mark.parametrize("argv", [["config"], ["--help"], ["config", "--help"]])
def test_a_reader_that_stops_reading_ends_the_command_quietly(argv):
    """`mine config | head` ended in a BrokenPipeError traceback: the reader closing the pipe is
    now the shell's quiet stop (status 141, 128 + SIGPIPE, as `cat` gives), nothing on stderr.
    The reader is gone before the command starts, so its first write meets the closed pipe."""
    import os

    r, w = os.pipe()
    os.close(r)
    try:
        proc = subprocess.run([sys.executable, "-m", "mining.cli", *argv], cwd=REPO, stdout=w,
                              stderr=subprocess.PIPE, timeout=60)
    finally:
        os.close(w)
    err = proc.stderr.decode()
    # argparse's help drops its own write errors (status 0); everything else stops at 141
    assert proc.returncode == (0 if "--help" in argv else 141) and err == "", (proc.returncode, err)
