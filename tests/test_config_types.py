"""Job configuration loading and the shared types."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO

from mining.config import load_config
from mining.errors import ConfigError, InputError
from mining.types import SequencePlan, StereoCalib, plan_windows

REPO_JOBS = REPO / "jobs"


def test_defaults_come_from_reference():
    cfg = load_config()
    assert cfg.geometry.egomotion.ransac_iterations == 200
    assert cfg.geometry.egomotion.inlier_threshold_px == 2.0
    assert cfg.geometry.ground.iterations == 3000
    assert cfg.geometry.ground.min_points == 1000
    assert cfg.geometry.flow.match_radius_px == 200.0


@pytest.mark.parametrize("name", ["synthetic", "kitti", "oxford"])
def test_job_files_load(name):
    cfg = load_config(REPO_JOBS / f"{name}.toml")
    assert cfg.source.dataset == name


def test_overrides_and_hash(tmp_path):
    base = load_config()
    changed = load_config(overrides=["geometry.stereo.num_disparities=96"])
    assert changed.geometry.stereo.num_disparities == 96
    assert changed.params_hash != base.params_hash
    # Where the data lives does not change the results.
    moved = load_config(overrides=['source.root="/elsewhere"'])
    assert moved.params_hash == base.params_hash


def test_unknown_key_and_bad_type_are_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(overrides=["geometry.stereo.num_disparitys=96"])
    with pytest.raises(ConfigError, match="expected int"):
        load_config(overrides=['geometry.stereo.num_disparities="many"'])
    bad = tmp_path / "bad.toml"
    bad.write_text("[source\n")
    with pytest.raises(ConfigError, match="bad.toml"):
        load_config(bad)


def test_calib_projection_round_trip():
    c = StereoCalib(721.5, 721.5, 609.6, 172.9, 0.5327, 1242, 375)
    p = np.array([[1.0, 0.5, 10.0], [-3.0, 1.2, 40.0]])
    uv = c.project(p)
    back = c.backproject(uv[:, 0], uv[:, 1], p[:, 2])
    np.testing.assert_allclose(back, p, atol=1e-9)
    disp = np.array([c.bf / 10.0, 0.0, np.nan], np.float32)
    z = c.depth_from_disparity(disp)
    assert z[0] == pytest.approx(10.0, rel=1e-5) and np.isnan(z[1]) and np.isnan(z[2])


def test_plan_windows_cover_sequence_once():
    calib = StereoCalib(1, 1, 0, 0, 1, 10, 10)
    plan = SequencePlan("synthetic", "0000", calib, tuple(range(250)), tuple(range(250)))
    ws = plan_windows(plan, core=100, before=5, after=10)
    assert [w.core for w in ws] == [(0, 100), (100, 200), (200, 250)]
    assert ws[1].context == (95, 210) and ws[2].context == (195, 250)
    assert len({w.name for w in ws}) == 3


def test_input_error_names_file_and_frame():
    e = InputError("truncated PNG", "/x/000003.png", frame=3)
    assert "/x/000003.png" in str(e) and "frame 3" in str(e) and "truncated" in str(e)


def test_a_recorded_job_reads_back_as_the_typed_config_it_was_made_from():
    from mining.catalog.records import JobRecord
    from mining.config import JobConfig

    cfg = JobConfig()
    cfg.select.price.reference = 7.5
    record = JobRecord("r", cfg.params_hash, cfg.to_dict(), [])
    assert record.job_config() == cfg


def test_a_recorded_job_of_older_code_has_its_moved_keys_renamed():
    from mining.catalog.records import JobRecord
    from mining.config import JobConfig

    old = JobConfig().to_dict()
    del old["localise"]["velocity_noise_factor"]
    old["tubes"]["kalman"]["velocity_noise_factor"] = 3.0  # where it was before da118f8
    assert JobRecord("r", "h", old, []).job_config().localise.velocity_noise_factor == 3.0


def test_a_recorded_job_from_before_the_filters_moved_reads_them_under_localise():
    from mining.catalog.records import JobRecord
    from mining.config import JobConfig

    old = JobConfig().to_dict()
    old["proposals"]["filters"] = old["localise"].pop("filters")  # where it was before issue 27
    old["proposals"]["filters"]["noise_sigmas"] = 0.0
    assert JobRecord("r", "h", old, []).job_config().localise.filters.noise_sigmas == 0.0


def test_a_moved_key_in_a_job_file_or_set_is_refused_saying_where_it_lives_now(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key.*proposals\.filters is now localise\.filters"):
        load_config(overrides=["proposals.filters.noise_sigmas=0.0"])
    job = tmp_path / "old.toml"
    job.write_text("[proposals.filters]\nmin_objectness = 0.3\n")
    with pytest.raises(ConfigError, match=r"old\.toml: unknown key.*proposals\.filters is now localise\.filters"):
        load_config(job)
    with pytest.raises(ConfigError, match=r"tubes\.kalman\.velocity_noise_factor is now localise\.velocity_noise_factor"):
        load_config(overrides=["tubes.kalman.velocity_noise_factor=2.0"])
    assert load_config(REPO_JOBS / "kitti-detections.toml").localise.filters.min_objectness == 0.3


def test_a_recorded_job_from_before_the_mode_tables_reads_its_twins_into_them():
    from mining.catalog.records import JobRecord
    from mining.config import JobConfig

    old = JobConfig().to_dict()
    del old["select"]["price"], old["tubes"]["association_floor"], old["score"]["known_margin"]
    old["select"] |= {"epsilon1": 7.5, "epsilon1_calibrated": 0.5}  # where they were before issue 38
    old["select"]["overlap_weight"] = {"calibrated": 3.0}
    old["select"]["epsilon2"] = 2.0
    old["tubes"] |= {"min_association": 0.03, "min_association_normalised": 0.1}
    old["score"] |= {"known_log_margin": -0.5, "known_log_margin_calibrated": -2.0}
    cfg = JobRecord("r", "h", old, []).job_config()
    assert (cfg.select.price.reference, cfg.select.price.calibrated) == (7.5, 0.5)
    assert (cfg.select.overlap_weight.reference, cfg.select.overlap_weight.calibrated) == (2.0, 3.0)
    assert (cfg.tubes.association_floor.reference, cfg.tubes.association_floor.normalised,
            cfg.tubes.association_floor.innovation) == (0.03, 0.1, 0.1)
    assert (cfg.score.known_margin.reference, cfg.score.known_margin.calibrated) == (-0.5, -2.0)


@pytest.mark.parametrize("old, new", [
    ("select.epsilon1=5.0", r"select\.epsilon1 is now select\.price\.reference"),
    ("select.epsilon2_calibrated=1.0", r"select\.epsilon2_calibrated is now select\.overlap_weight\.calibrated"),
    ("tubes.min_association_normalised=0.1",
     r"tubes\.min_association_normalised is now tubes\.association_floor\.normalised and "
     r"tubes\.association_floor\.innovation"),
    ("score.known_log_margin_calibrated=0.0", r"score\.known_log_margin_calibrated is now score\.known_margin\.calibrated"),
])
def test_a_mode_twin_in_a_job_file_or_set_is_refused_naming_its_table_entry(old, new, tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key.*" + new):
        load_config(overrides=[old])
    section, rest = old.split(".", 1)
    job = tmp_path / "old.toml"
    job.write_text(f"[{section}]\n{rest.replace('=', ' = ')}\n")
    with pytest.raises(ConfigError, match=r"old\.toml: unknown key.*" + new):
        load_config(job)


def test_a_table_by_mode_checks_each_entry_and_refuses_a_mode_it_does_not_have():
    cfg = load_config(overrides=["select.price.calibrated=-1.5", "tubes.association_floor.innovation=0.1"])
    assert cfg.select.price.calibrated == -1.5 and cfg.select.price.reference == 20.0  # the other entry keeps its default
    assert cfg.tubes.association_floor.innovation == 0.1 and cfg.tubes.association_floor.normalised == 0.068
    with pytest.raises(ConfigError, match=r"--set select\.price\.auto: unknown key\(s\) \['select\.price\.auto'\]; known: \['calibrated', 'reference'\]"):
        load_config(overrides=["select.price.auto=1.0"])
    with pytest.raises(ConfigError, match=r"select\.overlap_weight\.calibrated = -1\.0: must be ≥ 0"):
        load_config(overrides=["select.overlap_weight.calibrated=-1.0"])
    with pytest.raises(ConfigError, match=r"tubes\.association_floor\.normalised = 2\.0: must be in \[0, 1\]"):
        load_config(overrides=["tubes.association_floor.normalised=2.0"])
    with pytest.raises(ConfigError, match=r"select\.price: expected a table"):
        load_config(overrides=["select.price=1.0"])


def test_every_table_by_mode_has_exactly_its_modes():  # (no twin field: tests/test_house.py)
    import dataclasses
    import typing

    from mining.checks import OneOf, split_hint
    from mining.config import BY_MODE, JobConfig

    def field_of(path: str):
        cls, hint = JobConfig, None
        for name in path.split("."):
            hint = typing.get_type_hints(cls, include_extras=True)[name]
            cls = split_hint(hint)[0]
        return hint

    for table, mode in BY_MODE.items():
        keys = {f.name for f in dataclasses.fields(split_hint(field_of(table))[0])}
        choices = next(r.choices for r in split_hint(field_of(mode))[1] if isinstance(r, OneOf))
        assert keys == set(choices) - {"auto"}, (table, mode)  # score.model "auto" resolves to one of the two


def test_a_recorded_job_with_a_key_no_version_had_is_refused_naming_the_key():
    from mining.catalog.records import JobRecord, UnreadableRecord
    from mining.config import JobConfig

    d = JobConfig().to_dict()
    d["select"]["no_such_key"] = 1
    with pytest.raises(UnreadableRecord, match="no_such_key"):
        JobRecord("r", "h", d, []).job_config("/x/job.json")


def test_the_source_section_opens_its_source():
    from mining.config import SourceConfig

    source = SourceConfig(dataset="synthetic").open()
    assert source.sequences()[:1]


def test_a_set_typo_names_the_key_and_the_near_real_key_not_the_file(tmp_path):
    job = tmp_path / "job.toml"
    job.write_text("[window]\ncore = 8\n")
    with pytest.raises(ConfigError) as e:
        load_config(job, ["proposals.proposr=onnx"])
    msg = str(e.value)
    assert msg.startswith("--set proposals.proposr:") and "job.toml" not in msg
    assert "did you mean proposals.proposr → proposals.proposer?" in msg
    with pytest.raises(ConfigError, match=r"^--set window\.core: window\.core = -3"):
        load_config(job, ["window.core=-3"])
    job.write_text("[window]\ncroe = 8\n")  # the file's own typo is still the file's
    with pytest.raises(ConfigError, match=r"job\.toml: unknown key.*did you mean window\.croe → window\.core"):
        load_config(job, ["window.core=4"])
