"""The floors of docs/ARCHITECTURE.md, read from the code's own imports (ast, no import run).

Each rule is a function over an import graph, so every rule is also tested on a small planted
tree that breaks it (the ``test_*_catches_*`` tests): a rule that cannot fail keeps nothing.
An import inside a function counts like one at the top (it runs too, only later); one under
``if TYPE_CHECKING:`` does not (it never runs).
"""

from __future__ import annotations

import ast
import functools
from collections import defaultdict
from pathlib import Path

from conftest import REPO

# The paper's stages, each a package; none imports another (they meet in pipeline/).
STAGES = ("sources", "geometry", "proposals", "localise", "tubes", "score", "select")
# The shared floor every stage may use: words, not work.
SHARED_FLOOR = ("types", "errors", "names", "files", "masks", "boxes", "checks", "progress", "draw", "formats")
# The export wing's shared modules; every other module of export/ is a format (export/registry.py),
# and a format imports only these, never another format (as TrackEval's datasets import only their base).
EXPORT_SHARED = ("registry", "selection", "source_frames", "json_annotations", "depth", "dest", "video")
# What the catalogue may import: the shared floor and the job config.
CATALOG_MAY_IMPORT = (*SHARED_FLOOR, "config")
BELOW_PIPELINE = (*STAGES, *SHARED_FLOOR, "catalog", "config")
# The floors above the catalogue: nothing below the pipeline imports them.
ABOVE = ("pipeline", "export", "view", "bench", "commands", "cli", "testing", "discovery")
# Discovery (floor 6, beside the pipeline, export and viewer) reads the catalogue and no stage: it
# works on what was mined, whatever mined it. The embedder crops a tube's views as the crops export
# does and re-reads them through the job's source as every export does (export/), and nothing more.
DISCOVERY_MAY_IMPORT = (*SHARED_FLOOR, "catalog", "config", "export")


def _modules(root: Path):
    """(package, module path, parsed tree) of every module under ``root/mining``; a module at
    the top (``mining/boxes.py``) is its own package."""
    return _parsed(root) if root == REPO else _parse(root)


@functools.cache
def _parsed(root: Path) -> tuple:
    """The repository's modules, parsed once for all the rules."""
    return tuple(_parse(root))


def _parse(root: Path):
    for path in sorted((root / "mining").rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        yield parts[1], path, ast.parse(path.read_text())


def _imported(node: ast.AST, path: Path, root: Path) -> list[tuple[str, list[str]]]:
    """(absolute module, names) an import statement takes; relative imports resolved."""
    if isinstance(node, ast.Import):
        return [(a.name, []) for a in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level == 0:
        module = node.module or ""
    else:
        base = path.relative_to(root).with_suffix("").parts[: -node.level]
        module = ".".join([*base, *([node.module] if node.module else [])])
    return [(module, [a.name for a in node.names])]


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` except those under ``if TYPE_CHECKING:`` (never run)."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return (n for n in ast.walk(tree) if id(n) not in skip)


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_graph(root: Path = REPO) -> dict[str, set[str]]:
    """Module → the other ``mining`` modules (files) it imports, at the top or inside a function.
    ``from mining.a import b`` imports ``mining.a.b`` where that is a module, else ``mining.a``."""
    files = {_module_name(path, root): (path, tree) for _, path, tree in _modules(root)}
    out: dict[str, set[str]] = defaultdict(set)
    for name, (path, tree) in files.items():
        for node in _runtime_nodes(tree):
            for module, names in _imported(node, path, root):
                for target in [f"{module}.{n}" for n in names if f"{module}.{n}" in files] or [module]:
                    if target in files and target != name:
                        out[name].add(target)
    return out


def module_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles between files: each strongly connected group of two or more modules,
    sorted (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(groups)


def export_format_imports(graph: dict[str, set[str]], formats: set[str]) -> list[str]:
    """Every import of one export format (or of ``render``, a product) by another format: a
    format imports only the wing's shared modules."""
    return sorted(f"{a} → {b}" for a in graph if a.startswith("mining.export.")
                  for b in graph[a] if b.startswith("mining.export.") and b.split(".")[2] not in EXPORT_SHARED
                  and a.split(".")[2] in formats | {"render"})


def import_graph(root: Path = REPO) -> dict[str, set[str]]:
    """Package → the other ``mining`` packages it imports."""
    out: dict[str, set[str]] = defaultdict(set)
    for pkg, path, tree in _modules(root):
        for node in ast.walk(tree):
            for module, _ in _imported(node, path, root):
                bits = module.split(".")
                if bits[0] == "mining" and len(bits) > 1 and bits[1] != pkg:
                    out[pkg].add(bits[1])
    return out


def private_imports(root: Path = REPO) -> list[str]:
    """Every ``from mining.x import _name`` across files (a name another file needs is public)."""
    found = []
    for _, path, tree in _modules(root):
        for node in ast.walk(tree):
            for module, names in _imported(node, path, root):
                if module.split(".")[0] != "mining":
                    continue
                for name in names:
                    if name.startswith("_") and not name.startswith("__"):
                        found.append(f"{path.relative_to(root)}: {module}.{name}")
    return found


def stage_imports(deps: dict[str, set[str]]) -> list[str]:
    return sorted(f"{p} → {q}" for p in STAGES for q in deps.get(p, ()) if q in STAGES)


def catalog_imports(deps: dict[str, set[str]]) -> list[str]:
    return sorted(f"catalog → {q}" for q in deps.get("catalog", ()) if q not in CATALOG_MAY_IMPORT)


def upward_imports(deps: dict[str, set[str]]) -> list[str]:
    return sorted(f"{p} → {q}" for p in BELOW_PIPELINE for q in deps.get(p, ()) if q in ABOVE)


def discovery_imports(deps: dict[str, set[str]]) -> list[str]:
    return sorted(f"discovery → {q}" for q in deps.get("discovery", ()) if q not in DISCOVERY_MAY_IMPORT)


def eval_importers(deps: dict[str, set[str]]) -> list[str]:
    return sorted(p for p in deps if "eval" in deps[p] and p not in ("bench", "cli", "commands"))


def eval_imports(deps: dict[str, set[str]]) -> list[str]:
    """What eval/ imports beyond the shared floor (it measures; the callers hand it what to measure)."""
    return sorted(f"eval → {q}" for q in deps.get("eval", ()) if q not in SHARED_FLOOR)


def cycles(deps: dict[str, set[str]]) -> list[str]:
    def reaches(a: str, b: str, seen: set[str]) -> bool:
        return any(n == b or (n not in seen and reaches(n, b, seen | {n})) for n in deps.get(a, ()))

    return sorted(p for p in deps if reaches(p, p, {p}))


# The rules, on the code.

def test_no_stage_imports_another_stage():
    assert not stage_imports(import_graph())


def test_the_catalogue_imports_only_the_shared_floor_and_the_config():
    assert not catalog_imports(import_graph())


def test_nothing_below_the_pipeline_imports_the_pipeline_exports_the_viewer_bench_or_cli():
    assert not upward_imports(import_graph())


def test_discovery_imports_only_the_catalogue_and_the_shared_floor():
    assert not discovery_imports(import_graph())


def test_the_discovery_rule_catches_discovery_importing_a_stage_or_the_viewer(tmp_path):
    root = _plant(tmp_path, {"mining/discovery/a.py": "from mining.score.call import x\nfrom mining.catalog import views\n",
                             "mining/discovery/b.py": "from mining.view import api\n"})
    assert discovery_imports(import_graph(root)) == ["discovery → score", "discovery → view"]


def test_only_bench_and_the_cli_import_eval():
    assert not eval_importers(import_graph())


def test_eval_imports_only_the_shared_floor():
    assert not eval_imports(import_graph())


def test_no_import_cycle_between_packages():
    assert not cycles(import_graph())


def test_no_import_cycle_between_files():
    assert not module_cycles(module_graph())


def test_no_export_format_imports_another():
    from mining.export.registry import FORMATS

    formats = {f.module for f in FORMATS.values()}
    assert formats and not formats & set(EXPORT_SHARED)
    assert not export_format_imports(module_graph(), formats)


def test_no_private_name_is_imported_across_files():
    assert not private_imports()


# Each rule fails on a planted violation.

def _plant(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in {"mining/__init__.py": "", **files}.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return tmp_path


def test_the_stage_rule_catches_a_stage_importing_a_stage(tmp_path):
    root = _plant(tmp_path, {"mining/tubes/a.py": "from mining.proposals.stereo import X\n"})
    assert stage_imports(import_graph(root)) == ["tubes → proposals"]


def test_the_catalogue_rule_catches_a_catalogue_module_importing_a_stage(tmp_path):
    root = _plant(tmp_path, {"mining/catalog/a.py": "import mining.geometry.disparity\n",
                             "mining/catalog/b.py": "from mining.formats import coco\nfrom mining.config import X\n"})
    assert catalog_imports(import_graph(root)) == ["catalog → geometry"]


def test_the_floor_rule_catches_a_stage_or_the_catalogue_importing_upward(tmp_path):
    root = _plant(tmp_path, {"mining/catalog/a.py": "from mining.export import kitti\n",
                             "mining/select/b.py": "from mining.view.server import serve\n"})
    assert upward_imports(import_graph(root)) == ["catalog → export", "select → view"]


def test_the_eval_rule_catches_a_stage_importing_eval(tmp_path):
    root = _plant(tmp_path, {"mining/score/a.py": "from mining.eval.hota import hota\n",
                             "mining/bench/b.py": "from mining.eval.hota import hota\n"})
    assert eval_importers(import_graph(root)) == ["score"]


def test_the_cycle_rule_catches_two_packages_importing_each_other(tmp_path):
    root = _plant(tmp_path, {"mining/pipeline/a.py": "from mining.view import b\n",
                             "mining/view/b.py": "from mining.pipeline import a\n"})
    assert cycles(import_graph(root)) == ["pipeline", "view"]


def test_the_private_name_rule_catches_absolute_and_relative_imports(tmp_path):
    root = _plant(tmp_path, {"mining/export/a.py": "from mining.export.b import _by_sequence, frame_digits\n",
                             "mining/export/c.py": "from .b import _frames_by_tube\n",
                             "mining/export/b.py": "from mining import __doc__\n"})
    assert private_imports(root) == ["mining/export/a.py: mining.export.b._by_sequence",
                                     "mining/export/c.py: mining.export.b._frames_by_tube"]


def test_the_eval_floor_rule_catches_eval_importing_a_stage(tmp_path):
    root = _plant(tmp_path, {"mining/eval/funnel.py": "from mining.score.calibrated import GROUPS\n",
                             "mining/eval/hota.py": "from mining.types import Tube\nfrom mining.formats import coco\n"})
    assert eval_imports(import_graph(root)) == ["eval → score"]


def test_the_file_cycle_rule_catches_a_lazy_import_loop_and_spares_type_checking(tmp_path):
    root = _plant(tmp_path, {
        "mining/proposals/__init__.py": "",
        "mining/proposals/config.py": "def check():\n    from mining.proposals.make import names\n",
        "mining/proposals/make.py": "from mining.proposals import stereo\n",
        "mining/proposals/stereo.py": "from mining.proposals.config import Config\n",
        "mining/bench/__init__.py": "",
        "mining/bench/a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from mining.bench.b import X\n",
        "mining/bench/b.py": "from mining.bench import a\n"})
    assert module_cycles(module_graph(root)) == [
        ["mining.proposals.config", "mining.proposals.make", "mining.proposals.stereo"]]


def test_the_format_rule_catches_a_format_importing_another(tmp_path):
    root = _plant(tmp_path, {"mining/export/__init__.py": "",
                             "mining/export/tao.py": "from mining.export.vis import frames\n",
                             "mining/export/vis.py": "from mining.export.selection import rows\n",
                             "mining/export/selection.py": "",
                             "mining/export/render.py": "def f():\n    from mining.export import tao\n"})
    assert export_format_imports(module_graph(root), {"tao", "vis"}) == [
        "mining.export.render → mining.export.tao", "mining.export.tao → mining.export.vis"]
