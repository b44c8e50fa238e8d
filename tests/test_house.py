"""The house rules that are not imports (those are tests/test_layers.py): a value that depends on
a mode is a table keyed by that mode, every command is one row, every proposer one registry
entry, the docs name what exists, and no file or function grows past a size a reader can hold.

Each rule is a function over files or classes, and each is also run on a small planted case
that breaks it (the ``test_*_catches_*`` tests): a rule that cannot fail keeps nothing.
"""

from __future__ import annotations

import ast
import dataclasses
import re
import typing
from pathlib import Path

from conftest import REPO

# --- one setting per concept: a mode's values are a table keyed by the mode, not twin fields

TWIN_SUFFIXES = ("_calibrated", "_normalised", "_reference")


def twin_fields(cls: type, prefix: str = "") -> list[str]:
    """Every field of the config dataclass ``cls`` (and of the dataclasses it holds) whose name
    marks it as one mode's copy of another setting."""
    found = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        if f.name.endswith(TWIN_SUFFIXES):
            found.append(key)
        kind = typing.get_origin(hints[f.name]) or hints[f.name]
        if kind is typing.Annotated:
            kind = typing.get_args(hints[f.name])[0]
        if dataclasses.is_dataclass(kind):
            found += twin_fields(kind, f"{key}.")
    return found


def test_no_config_field_is_a_mode_twin():
    from mining.config import JobConfig

    assert dataclasses.fields(JobConfig)
    assert not twin_fields(JobConfig)


@dataclasses.dataclass
class PlantedSelect:
    price: dict[str, float] = dataclasses.field(default_factory=dict)
    price_calibrated: float = 0.0


@dataclasses.dataclass
class PlantedJob:
    select: PlantedSelect = dataclasses.field(default_factory=PlantedSelect)
    min_association_normalised: float = 0.1


def test_the_twin_rule_catches_a_nested_mode_twin():
    assert twin_fields(PlantedJob) == ["select.price_calibrated", "min_association_normalised"]


# --- the README is a newcomer's page: short, and no commit hashes (they go stale; RESULTS has runs)

README_MAX_BYTES = 25_000  # issue 38: the README regrew to 26.8 KB; measurements live in docs/RESULTS.md
COMMIT_HASH = re.compile(r"(?<![\w#-])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w-])")


def readme_faults(text: str) -> list[str]:
    faults = [f"{len(text.encode())} bytes > {README_MAX_BYTES}"] if len(text.encode()) > README_MAX_BYTES else []
    return faults + [f"line {text.count(chr(10), 0, m.start()) + 1}: commit hash {m.group()}"
                     for m in COMMIT_HASH.finditer(text)]


def test_the_readme_is_short_and_names_no_commit():
    assert not readme_faults((REPO / "README.md").read_text())


def test_the_readme_rule_catches_a_commit_hash_and_a_long_page():
    text = "Measured at c136a76 (see 58708cd3f).\nColour #a1b2c3d4 and 1234567 and deadbeef are not commits.\n"
    assert readme_faults(text) == ["line 1: commit hash c136a76", "line 1: commit hash 58708cd3f"]
    assert readme_faults("x" * (README_MAX_BYTES + 1)) == [f"{README_MAX_BYTES + 1} bytes > {README_MAX_BYTES}"]


# --- docs/ARCHITECTURE.md's layout names every module

def layout_entries(text: str) -> list[tuple[str, str]]:
    """(first word, text) of each entry of the layout's picture: an entry is a line indented by two
    spaces and the deeper lines under it."""
    block = text.split("\n## Layout", 1)[1].split("```", 2)[1]
    entries: list[list[str]] = []
    for line in block.splitlines()[1:]:
        if re.match(r"^  \S", line):
            entries.append([line.split()[0], line])
        elif entries and line.strip():
            entries[-1][1] += "\n" + line
    return [(head, body) for head, body in entries]


def unnamed_modules(root: Path) -> list[str]:
    """Every module under ``root/mining`` the layout does not name: a top-level file by its name, a
    package's file by its name inside one of the package's entries (``score/``, ``score/unary.py``),
    a module of a sub-package by the sub-package's folder (``synthetic/``)."""
    entries = layout_entries((root / "docs/ARCHITECTURE.md").read_text())
    missing = []
    for path in sorted((root / "mining").rglob("*.py")):
        rel = path.relative_to(root / "mining").parts
        if rel[-1].startswith("__"):
            continue
        if len(rel) == 1:
            named = any(re.search(rf"(?<![\w/.]){re.escape(rel[0])}\b", body) for _, body in entries)
        else:
            pkg, want = rel[0], rel[1] if len(rel) == 2 else rel[1] + "/"
            named = any(head.startswith(pkg + "/") and (head == f"{pkg}/{want}"
                                                         or re.search(rf"(?<![\w.]){re.escape(want)}", body))
                        for head, body in entries)
        if not named:
            missing.append("/".join(rel))
    return missing


def test_the_architecture_layout_names_every_module():
    assert not unnamed_modules(REPO)


def test_the_layout_rule_catches_an_unnamed_module(tmp_path):
    for rel in ("mining/types.py", "mining/score/__init__.py", "mining/score/unary.py", "mining/score/call.py",
                "mining/score/fits/x.py", "mining/sources/synthetic/scene.py", "mining/bench/fit.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs/ARCHITECTURE.md").write_text(
        "# A\n\n## Layout\n\n```\nmining/\n  types.py   shared types\n  score/unary.py   the unary\n"
        "  sources/   adapters\n    synthetic/   rendered scenes\n  bench/   one module a bench (fit.py is not "
        "named by a prose mention of call.py)\n```\n")
    assert unnamed_modules(tmp_path) == ["score/call.py", "score/fits/x.py"]


# --- a size ratchet: no new function over 100 lines, no new file over 800; the exceptions of today
# are listed with their size and may only shrink (an entry that no longer needs to be here must go)

MAX_FUNCTION_LINES = 100
MAX_FILE_LINES = 800
LONG_FILES = {  # path → lines when listed
    "mining/sources/synthetic/meshes.py": 1279,
}
LONG_FUNCTIONS = {  # path:qualified name → lines when listed
    "mining/export/render.py:render": 133,
    "mining/sources/synthetic/meshes.py:_car_body": 177,
}


def sizes(root: Path) -> tuple[dict[str, int], dict[str, int]]:
    """(file → lines, function → lines) of everything over the limits under ``root/mining``."""
    files, functions = {}, {}
    for path in sorted((root / "mining").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        text = path.read_text()
        if len(text.splitlines()) > MAX_FILE_LINES:
            files[rel] = len(text.splitlines())

        def walk(node: ast.AST, prefix: str) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}"
                    lines = child.end_lineno - child.lineno + 1
                    if not isinstance(child, ast.ClassDef) and lines > MAX_FUNCTION_LINES:
                        functions[f"{rel}:{name}"] = lines
                    walk(child, f"{name}.")
                else:
                    walk(child, prefix)

        walk(ast.parse(text), "")
    return files, functions


def ratchet_faults(found: dict[str, int], listed: dict[str, int], what: str) -> list[str]:
    faults = [f"{k}: {n} lines, a new long {what}" for k, n in found.items() if k not in listed]
    faults += [f"{k}: grew from {listed[k]} to {n} lines" for k, n in found.items() if k in listed and n > listed[k]]
    return faults + [f"{k}: listed but no longer long: take it off the list" for k in listed if k not in found]


def test_no_file_or_function_grows_past_the_ratchet():
    files, functions = sizes(REPO)
    assert not ratchet_faults(files, LONG_FILES, "file") + ratchet_faults(functions, LONG_FUNCTIONS, "function")


def test_the_ratchet_catches_a_long_function_growth_and_a_stale_entry(tmp_path):
    body = "\n".join(f"        x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "mining").mkdir()
    (tmp_path / "mining/a.py").write_text(f"class K:\n    def long(self):\n{body}\n")
    (tmp_path / "mining/b.py").write_text("\n" * (MAX_FILE_LINES + 1))
    files, functions = sizes(tmp_path)
    assert functions == {"mining/a.py:K.long": MAX_FUNCTION_LINES + 1}
    assert ratchet_faults(functions, {}, "function") == ["mining/a.py:K.long: 101 lines, a new long function"]
    assert ratchet_faults(files, {"mining/b.py": 700, "mining/c.py": 900}, "file") == [
        "mining/b.py: grew from 700 to 801 lines", "mining/c.py: listed but no longer long: take it off the list"]
