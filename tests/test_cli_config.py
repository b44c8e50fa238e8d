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
