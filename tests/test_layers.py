"""The floors of docs/ARCHITECTURE.md, read from the code's own imports (ast, no import run):
lower floors never import higher ones, eval/ is imported only by bench/ and the CLI, and no
two packages import each other."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("sources", "geometry", "proposals", "localise", "tubes", "score", "select", "catalog")
BELOW_PIPELINE = (*STAGES, "formats", "types", "errors", "names", "masks", "boxes", "config")


def _imports() -> dict[str, set[str]]:
    """Package (``mining.X``'s X; modules at the top are their own) → packages it imports."""
    out: dict[str, set[str]] = defaultdict(set)
    for path in (REPO / "mining").rglob("*.py"):
        parts = path.relative_to(REPO).with_suffix("").parts
        pkg = parts[1]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                bits = name.split(".")
                if bits[0] == "mining" and len(bits) > 1 and bits[1] != pkg:
                    out[pkg].add(bits[1])
    return out


def test_no_stage_or_catalogue_module_imports_eval():
    deps = _imports()
    assert {p for p in deps if "eval" in deps[p]} <= {"bench", "cli"}


def test_nothing_below_the_pipeline_imports_pipeline_bench_or_cli():
    deps = _imports()
    for pkg in BELOW_PIPELINE:
        assert not deps[pkg] & {"pipeline", "bench", "cli", "testing"}, pkg


def test_no_import_cycle_between_packages():
    deps = dict(_imports())

    def reaches(a: str, b: str, seen: set[str]) -> bool:
        return any(n == b or (n not in seen and reaches(n, b, seen | {n})) for n in deps.get(a, ()))

    cycles = sorted(p for p in deps if reaches(p, p, {p}))
    assert not cycles, f"packages on an import cycle: {cycles}"
