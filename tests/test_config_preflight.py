"""Preflight of ``mine submit`` (issue 11, item 7): a bad setting, option, frame range,
proposer, model file, output folder or job.json fails once, in the driver, before Ray
starts and before job.json is written — one clear line naming the key or file, the value
and the rule, exit status 2, no traceback.

Each case runs the real command line (``mining.cli.main``, in this process: nothing here
may get as far as starting Ray; one case runs ``mine`` as a subprocess). The old code
started Ray and failed every window, printed a traceback, or exited 0 with nothing mined.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from _jobs import SYNTHETIC
from _run import clean_error, cli, submit
from conftest import MODEL, REPO


def _submit(capsys, out: Path, *args: str) -> tuple[int, str, str]:
    return cli(capsys, "submit", *args, "--out", str(out), "--workers", "1", "--no-progress")


@pytest.fixture
def refused(tmp_path, capsys):
    def run(*args: str) -> str:
        return _refused(capsys, tmp_path, *args)
    return run


def _refused(capsys, tmp_path: Path, *args: str) -> str:
    out = tmp_path / "out"
    rc, stdout, stderr = _submit(capsys, out, *SYNTHETIC, *args)
    assert rc == 2, (rc, stdout, stderr)
    assert "windows:" not in stdout, "no window may run"
    assert not (out / "job.json").exists(), "a refused job must leave no job.json (the fixed command would be refused)"
    return clean_error(stderr)


@pytest.mark.parametrize("setting, expected", [
    ("window.core=-5", "window.core = -5: must be ≥ 1"),
    ("window.context_before=-5", "window.context_before = -5: must be ≥ 0"),
    ("window.context_after=-1", "window.context_after = -1: must be ≥ 0"),
    ("geometry.stereo.num_disparities=95", "geometry.stereo.num_disparities = 95: must be a multiple of 16"),
], ids=["core", "context-before", "context-after", "num-disparities"])
def test_bad_set_value_names_key_value_and_rule(refused, setting, expected):
    assert expected in refused("--set", setting)


def test_unknown_source_option_names_it_and_the_known_ones(refused):
    line = refused("--option", "bogus=1")
    assert "'bogus'" in line and "synthetic source" in line and "n_frames" in line


def test_source_option_of_wrong_type_names_key_value_and_type(refused):
    line = refused("--option", 'n_frames="abc"')
    assert "source.options.n_frames = 'abc': expected int" in line


def test_empty_frame_range_is_an_error(refused):
    line = refused("--frames", "50:10")
    assert "50:10" in line and "empty" in line


def test_bad_proposer_name_fails_once_before_ray(refused):
    line = refused("--set", 'proposals.proposer="onnx+yolo"')
    assert "proposals.proposer = 'onnx+yolo'" in line and "unknown proposer 'yolo'" in line


def test_missing_model_file_fails_once_before_ray(tmp_path, refused):
    model = tmp_path / "no-such-model.onnx"
    line = refused("--set", 'proposals.proposer="onnx"', "--set", f'proposals.onnx.model_path="{model}"')
    assert str(model) in line and "not found" in line


def test_unreadable_model_file_is_loaded_once_and_refused(tmp_path, refused):
    # The real model cut short: onnx cannot parse it. Loaded in the driver, not in every window.
    if not MODEL.is_file():
        pytest.skip(f"no ONNX model at {MODEL} (../shared absent)")
    model = tmp_path / "cut.onnx"
    model.write_bytes(MODEL.read_bytes()[:4096])
    line = refused("--set", 'proposals.proposer="onnx"', "--set", f'proposals.onnx.model_path="{model}"')
    assert str(model) in line


def _unwritable(tmp_path: Path) -> Path:
    """A folder this process cannot write: mode 0555, or (as root, who ignores modes) one on sysfs."""
    ro = tmp_path / "read-only"
    ro.mkdir()
    ro.chmod(0o555)
    return ro if not os.access(ro, os.W_OK) else Path("/sys/tube-miner-read-only-test")


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_read_only_output_folder_is_a_clear_error(tmp_path):
    # The real command line, as a subprocess: this one also shows the CLI's exit path.
    out = _unwritable(tmp_path)
    rc, stdout, stderr = submit(out, *SYNTHETIC, workers=1)
    assert rc == 2, (rc, stdout, stderr)
    line = clean_error(stderr)
    assert str(out) in line and "cannot be written" in line


def test_output_under_a_file_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    rc, stdout, stderr = _submit(capsys, tmp_path / "file" / "catalog", *SYNTHETIC)
    assert rc == 2, (rc, stdout, stderr)
    assert "cannot be written" in clean_error(stderr)


@pytest.mark.parametrize("content, expected", [
    (b'{"run_id": "abc", "params_hash": "0123", "windows": [', "not valid JSON"),
    (b"\x89PNG\r\n\x1a\n\x00\x00", "not valid JSON"),
    (b'{"run_id": "abc", "params_hash": "0123", "config": [], "windows": []}', "key 'config' holds an array, expected a job config"),
    (b'{"run_id": "abc", "params_hash": "0123", "config": {}, "windows": [{"dataset": "synthetic", '
     b'"sequence": "0000", "core": "ab", "context": [0, 8]}]}', "windows[0]: key 'core' holds a string"),
], ids=["truncated", "binary", "config-not-a-table", "bad-window"])
def test_corrupt_job_json_is_a_clear_error_for_submit_status_and_export(tmp_path, capsys, content, expected):
    out = tmp_path / "out"
    out.mkdir()
    (out / "job.json").write_bytes(content)
    for args in (["submit", *SYNTHETIC, "--out", str(out), "--no-progress"], ["status", "--out", str(out)],
                 ["export", str(tmp_path / "dest"), "--format", "crops", "--out", str(out)]):
        rc, stdout, stderr = cli(capsys, *args)
        assert rc == 2, (args[0], rc, stdout, stderr)
        line = clean_error(stderr)
        assert str(out / "job.json") in line and expected in line, (args[0], line)
    assert (out / "job.json").read_bytes() == content, "a refused job leaves job.json as it was"


def test_every_shipped_job_config_keeps_its_own_rules():
    from mining.config import load_config, validate

    for path in sorted((REPO / "jobs").glob("*.toml")):
        validate(load_config(path), str(path))
    validate(load_config())


def test_config_file_values_are_checked_like_overrides(tmp_path):
    from mining.config import load_config
    from mining.errors import ConfigError

    bad = tmp_path / "job.toml"
    bad.write_text("[tubes]\ngate_box_iou = 1.5\n[geometry.stereo]\nmax_depth_m = nan\n")
    with pytest.raises(ConfigError) as e:
        load_config(bad)
    assert str(bad) in str(e.value) and "tubes.gate_box_iou = 1.5: must be in [0, 1]" in str(e.value)
    with pytest.raises(ConfigError, match=r"geometry.stereo.max_depth_m = nan: must be a finite number"):
        load_config(overrides=["geometry.stereo.max_depth_m=nan"])
    with pytest.raises(ConfigError, match=r"localise.size_percentiles\[1\] = 150.0: must be in \[0, 100\]"):
        load_config(overrides=["localise.size_percentiles=[5, 150]"])
