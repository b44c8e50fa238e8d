"""The command registry of ``mining/cli.py``: every ``mine GROUP NAME`` command's module adds its
options and runs it, and a command's module is imported only when that command is parsed."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from conftest import REPO
from mining.cli import COMMANDS, GROUPS, build_parser


def test_every_command_module_offers_add_arguments_and_run():
    assert {c.group for c in COMMANDS} == set(GROUPS)
    assert len({(c.group, c.name) for c in COMMANDS}) == len(COMMANDS)
    for c in COMMANDS:
        module = importlib.import_module(c.module)
        assert callable(module.add_arguments) and callable(module.run), c.module


@pytest.mark.parametrize("argv, module", [
    (["bench", "scenarios", "--half"], "mining.bench.scenarios"),
    (["eval", "synthetic"], "mining.bench.synthetic"),
    (["eval", "kitti-mot", "--gt", "tests", "--results", "tests", "--sequences", "0000"], "mining.eval.kitti_mot"),
    (["track", "images", "--sequence", "0000", "--out", "o", "--frames", "2:5"], "mining.pipeline.track_images"),
])
def test_a_parsed_command_runs_its_module(argv, module, monkeypatch):
    monkeypatch.chdir(REPO)  # the input folders the command lines name (--gt, --results) exist there
    args = build_parser().parse_args(argv)
    assert args.func is importlib.import_module(module).run


def test_parsing_another_command_imports_no_command_module():
    # OpenCV, SciPy and ONNX Runtime come with the bench modules: `mine status` must not load them.
    code = ("import sys; from mining.cli import COMMANDS, build_parser; build_parser().parse_args(['status']); "
            "print(sorted(c.module for c in COMMANDS if c.module in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "[]"
