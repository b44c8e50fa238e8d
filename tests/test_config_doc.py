"""docs/CONFIG.md is what `python -m mining.configdoc` writes from the config dataclasses, so a field
added, removed, renamed, re-typed, re-defaulted or re-commented shows there (regenerate and commit)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from mining import configdoc
from mining.checks import Count, Fraction, OneOf

REPO = Path(__file__).resolve().parents[1]


def test_config_md_is_generated_from_the_dataclasses():
    expected = configdoc.render()
    actual = (REPO / "docs" / "CONFIG.md").read_text()
    assert actual == expected, "docs/CONFIG.md is stale: run `python -m mining.configdoc` and commit it"


def test_every_job_config_key_is_listed():
    """Each plain field of JobConfig's dataclasses, at any depth, is one row with its dotted key."""
    def keys(cls: type, prefix: str = "") -> list[str]:
        out = []
        for f in dataclasses.fields(cls):
            if dataclasses.is_dataclass(f.default_factory if f.default_factory is not dataclasses.MISSING else None):
                out += keys(f.default_factory, f"{prefix}{f.name}.")
            else:
                out.append(f"{prefix}{f.name}")
        return out

    listed = [k.path for s in configdoc.sections() for k in s.keys]
    assert sorted(listed) == sorted(keys(configdoc.JobConfig)) and len(set(listed)) == len(listed)
    assert "select.price.reference" in listed and "geometry.stereo.num_disparities" in listed


@dataclass
class Inner:
    """An inner section."""

    depth: Count = 3  # REFERENCE: three levels


@dataclass
class Small:
    mode: Annotated[str, OneOf(("a", "b"))] = "a"  # ours: trailing comment
    # ours: the comment lines
    # directly above a field
    share: Fraction = 0.5
    widths: list[int] = field(
        default_factory=lambda: [1, 2]
    )  # REFERENCE: after a multi-line default
    inner: Inner = field(default_factory=Inner)


@dataclass
class SmallPlus:
    mode: Annotated[str, OneOf(("a", "b"))] = "a"  # ours: trailing comment
    # ours: the comment lines
    # directly above a field
    share: Fraction = 0.5
    widths: list[int] = field(
        default_factory=lambda: [1, 2]
    )  # REFERENCE: after a multi-line default
    inner: Inner = field(default_factory=Inner)
    added: float = 1.0  # ours: a new field


def test_generator_reads_types_rules_defaults_and_comments():
    text = configdoc.render(Small, header="# Small")
    assert '| `mode` | `str` | one of "a", "b" | `"a"` | ours: trailing comment |' in text
    assert "| `share` | `float` | in [0, 1] | `0.5` | ours: the comment lines directly above a field |" in text
    assert "| `widths` | `list[int]` | ≥ 0 | `[1, 2]` | REFERENCE: after a multi-line default |" in text
    assert "## inner" in text and "An inner section." in text
    assert "| `inner.depth` | `int` | ≥ 1 | `3` | REFERENCE: three levels |" in text


def test_an_added_field_changes_the_document(tmp_path):
    """The check fails when a dataclass gains a field the written document does not list."""
    before = configdoc.render(Small, header="# Small")
    after = configdoc.render(SmallPlus, header="# Small")
    assert before != after
    assert "| `added` | `float` | ≥ 0 | `1.0` | ours: a new field |" in after
    assert "`added`" not in before


def test_check_mode_reports_a_stale_file(tmp_path):
    out = tmp_path / "CONFIG.md"
    assert configdoc.main(["--check", "--output", str(out)]) == 1  # missing
    assert configdoc.main(["--output", str(out)]) == 0
    assert configdoc.main(["--check", "--output", str(out)]) == 0
    out.write_text(out.read_text().replace("`select.price.reference`", "`select.price.reference_one`"))
    assert configdoc.main(["--check", "--output", str(out)]) == 1
