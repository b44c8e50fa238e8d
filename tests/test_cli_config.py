"""`mine config`: every key of the job config with its value, default, source tag and comment
(the 284 keys could be read only in docs/CONFIG.md before); a job file's values show, and a
filter narrows the list."""

from __future__ import annotations

import dataclasses
import json

from _run import cli

from mining.config import JobConfig


def _dataclass_keys(cls: type, prefix: str = "") -> list[str]:
    """Every plain field of ``cls``'s dataclasses, at any depth, as a dotted key."""
    out = []
    for f in dataclasses.fields(cls):
        factory = f.default_factory if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(factory):
            out += _dataclass_keys(factory, f"{prefix}{f.name}.")
        else:
            out.append(f"{prefix}{f.name}")
    return out


def test_every_key_is_listed_with_its_default_source_and_comment(capsys):
    rc, out, err = cli(capsys, "config")
    assert rc == 0, err
    lines = out.splitlines()
    keys = _dataclass_keys(JobConfig)
    assert len(keys) > 200 and lines[0].startswith(f"{len(keys)} of {len(keys)} job config keys")
    listed = [ln.split(" = ", 1)[0] for ln in lines[1:] if not ln.startswith(" ")]
    assert listed and sorted(listed) == sorted(keys)
    # the defaults: nothing differs, so no "(default …)"
    assert not any("(default " in ln for ln in lines[1:] if not ln.startswith(" "))
    assert "select.price.reference = 20.0  [REFERENCE]" in lines
    jitter = lines.index("tubes.gate_jitter_px = 2.0  [ours]")
    assert lines[jitter + 1].startswith("    ours: δ px of jitter")
    rc, out, _ = cli(capsys, "config", "--format", "json")
    rows = json.loads(out)
    assert rc == 0 and [r["key"] for r in rows] == listed
    assert {r["source"] for r in rows} <= {"REFERENCE", "paper", "ours", "library", "REFERENCE/paper", "DESIGN.md", "—"}
    assert sum(r["source"] == "ours" for r in rows) > 100 and sum(r["source"] == "REFERENCE" for r in rows) > 50


def test_a_job_files_values_show_beside_the_defaults(tmp_path, capsys):
    job = tmp_path / "x.toml"
    job.write_text('[source]\ndataset = "synthetic"\n\n[tubes]\nassociation_floor.reference = 0.05\n')
    rc, out, err = cli(capsys, "config", "--config", str(job), "--set", "select.price.reference=7.5",
                       "tubes.association_floor.")
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].startswith(f"3 of {len(_dataclass_keys(JobConfig))} job config keys, values of {job} + the "
                               "options given")
    assert lines[1] == "tubes.association_floor.reference = 0.05  (default 0.02)  [REFERENCE]"
    rc, out, _ = cli(capsys, "config", "--config", str(job), "--set", "select.price.reference=7.5",
                     "select.price.reference", "--format", "json")
    assert rc == 0 and [(r["key"], r["value"], r["default"]) for r in json.loads(out)][0] == \
        ("select.price.reference", 7.5, "20.0")


def test_a_filter_narrows_and_a_wrong_one_says_what_is_near(capsys):
    rc, out, _ = cli(capsys, "config", "tubes.")
    listed = [ln.split(" = ", 1)[0] for ln in out.splitlines()[1:] if not ln.startswith(" ")]
    assert rc == 0 and sorted(listed) == sorted(k for k in _dataclass_keys(JobConfig) if k.startswith("tubes."))
    rc, out, _ = cli(capsys, "config", "price")  # no key starts with it: those holding it
    assert rc == 0 and {ln.split(" = ")[0] for ln in out.splitlines()[1:] if not ln.startswith(" ")} >= \
        {"select.price.reference", "select.price.calibrated"}
    rc, out, err = cli(capsys, "config", "tubs.")
    assert rc == 2 and out == "" and "no config key matches 'tubs.'; did you mean 'tubes.'" in err, err


# -- a user's file that is not UTF-8 text (issue 40, case 10) ---------------------------------

NOT_UTF8 = b"# fine\n" + b"x = \"caf\xe9\"\n"  # a Latin-1 é: byte 0xe9 at offset 15, line 2
NOT_UTF8_SAYS = "not UTF-8 text: byte 0xe9 at offset 15 (line 2)"


def test_a_job_file_that_is_not_utf8_text_is_one_line_naming_it(tmp_path):
    """Was a UnicodeDecodeError traceback from `mine config` and `mine submit`; a TOML file
    nested past tomllib's recursion was a RecursionError traceback."""
    import subprocess

    from _jobs import SYNTHETIC
    from _run import env, mine_cmd

    bad, deep = tmp_path / "bad.toml", tmp_path / "deep.toml"
    bad.write_bytes(NOT_UTF8)
    deep.write_text("v = " + "[" * 5000 + "]" * 5000 + "\n")
    out = tmp_path / "out"
    for job_file, says in [(bad, NOT_UTF8_SAYS), (deep, "not valid TOML: nested deeper")]:
        for command in (["config"], ["submit", *SYNTHETIC, "--out", str(out), "--workers", "1", "--no-progress"]):
            proc = subprocess.run(mine_cmd(*command, "--config", str(job_file)), capture_output=True, text=True,
                                  env=env(), timeout=120)
            where = (command[0], job_file.name)
            assert proc.returncode == 2 and "Traceback" not in proc.stderr, (where, proc.stderr[-2000:])
            assert len(proc.stderr.strip().splitlines()) == 1, (where, proc.stderr)
            assert proc.stderr.startswith(f"mine: error: file {job_file}: ") and says in proc.stderr, (where, proc.stderr)
            assert not out.exists(), where


def _readers(tmp_path):
    """(what, the file it reads, a call that reads it) of every reader of a user's text file."""
    from mining.config import load_config
    from mining.eval.kitti_mot import evaluate_first_frames
    from mining.formats.kitti_calib import read_calib_file
    from mining.formats.kitti_detections import read_kitti_detections
    from mining.formats.kitti_tracking import read_kitti_tracking, read_seqmap
    from mining.formats.oxford_labels import read_oxford_label_file
    from mining.formats.poses import read_poses
    from mining.proposals.precomputed import _bounded_text
    from mining.score.fits import read_fits
    from mining.sources.kitti_raw import KittiRawSource
    from mining.sources.oxford import load_camera_model

    f = tmp_path / "file.txt"
    (tmp_path / "fits").mkdir()
    return [("job config", f, lambda: load_config(f)),
            ("KITTI tracking file", f, lambda: read_kitti_tracking(f)),
            ("seqmap", f, lambda: read_seqmap(f)),
            ("poses", f, lambda: read_poses(f)),
            ("calibration", f, lambda: read_calib_file(f)),
            ("detections", f, lambda: read_kitti_detections(f)),
            ("oxford labels", f, lambda: read_oxford_label_file(f, "t", 0, 0)),
            ("proposals", f, lambda: _bounded_text(f, 0, 1 << 20)),
            ("kitti raw timestamps", f, lambda: KittiRawSource._timestamps(f, (0,))),
            ("oxford camera model", tmp_path / "cam.txt", lambda: load_camera_model(tmp_path, "cam")),
            ("ground truth", tmp_path / "0000.txt", lambda: evaluate_first_frames(tmp_path, tmp_path, ["0000"],
                                                                                  ["car"], 5)),
            ("fits", tmp_path / "fits" / "x.toml", lambda: read_fits(tmp_path / "fits"))]


def test_every_reader_of_a_users_text_file_names_a_byte_that_is_not_utf8(tmp_path):
    from mining.errors import MiningError

    for what, path, read in _readers(tmp_path):
        path.write_bytes(NOT_UTF8)
        try:
            read()
        except MiningError as e:
            assert str(path) in str(e) and NOT_UTF8_SAYS in str(e) and "\n" not in str(e), (what, str(e))
        except Exception as e:  # noqa: BLE001 - a raw UnicodeDecodeError is the failure this test is for
            raise AssertionError(f"{what}: {type(e).__name__}: {e}") from None
        else:
            raise AssertionError(f"{what}: read a file that is not UTF-8 without a word")
        path.unlink()


# Modules that read only files of their own (their source, their SQL, a record they wrote, /proc).
OWN_FILES_ONLY = ("mining/bench/", "mining/catalog/schema.py", "mining/catalog/views.py", "mining/configdoc.py",
                  "mining/export/dest.py")


def test_a_users_text_is_read_through_one_helper():
    """Every text read in mining/ outside OWN_FILES_ONLY is files.read_text / decode_text:
    no ``.read_text()`` and no text-mode ``open()`` for reading."""
    import ast

    from conftest import REPO

    found = []
    for path in sorted((REPO / "mining").rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if rel.startswith(OWN_FILES_ONLY):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            if isinstance(f, ast.Attribute) and f.attr == "read_text":
                found.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
            elif isinstance(f, ast.Name) and f.id == "open" or isinstance(f, ast.Attribute) and f.attr == "open" \
                    and not ast.unparse(f.value) == "os":  # os.open is a descriptor, not text
                args = node.args[1:] if isinstance(f, ast.Name) else node.args  # path.open(mode) vs open(path, mode)
                modes = [a.value for a in args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
                modes += [k.value.value for k in node.keywords if k.arg == "mode" and isinstance(k.value, ast.Constant)]
                text = any(k.arg == "encoding" for k in node.keywords) or any("b" not in m and "w" not in m
                                                                             for m in modes)
                # A bare x.open() may be a source's, not a file's: only a builtin open() is text by default.
                if text or (isinstance(f, ast.Name) and not modes):
                    found.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
    assert not found, "text read without mining.files.read_text:\n" + "\n".join(found)
