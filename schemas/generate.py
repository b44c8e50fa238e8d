"""Write schemas/v<N>/ from the package, the one source of truth: the tables' JSON from
mining/catalog/schema.py, and views.sql copied from mining/catalog/views.sql (which ships in
the package, so that an installed `mine` opens catalogues).

    python schemas/generate.py          # rewrite the JSON files
    python schemas/generate.py --check  # exit 1 when the committed files differ

Each table's JSON lists its fields in order: name, Arrow type, nullable, the comment
from schema.py, and whether it is a partition column (a folder name, not in the file)
or a part-only column (per-window parts only).
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from mining.catalog import schema  # noqa: E402

SCHEMA_PY = Path(schema.__file__)
VIEWS_SQL = SCHEMA_PY.with_name("views.sql")


def field_comments() -> dict[str, dict[str, str]]:
    """``{schema variable: {field name: trailing comment}}`` read from schema.py's source."""
    source = SCHEMA_PY.read_text()
    lines = source.splitlines()
    out: dict[str, dict[str, str]] = {}

    def comment(lineno: int) -> str:
        line = lines[lineno - 1]
        return line.split("#", 1)[1].strip() if "#" in line else ""

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            key = node.targets[0].id
        else:
            continue
        for call in ast.walk(node.value):
            if (isinstance(call, ast.Call) and getattr(call.func, "attr", "") == "field" and call.args
                    and isinstance(call.args[0], ast.Constant)):
                out.setdefault(key, {})[call.args[0].value] = comment(call.end_lineno)
    return out


def generate() -> dict[str, str]:
    """File name → JSON text of every file under schemas/v<N>/ that this script owns."""
    comments = field_comments()
    var = {"tubes": "TUBES", "tube_frames": "TUBE_FRAMES", "frames": "FRAMES", "windows": "WINDOWS"}
    files = {}
    for table, s in schema.SCHEMAS.items():
        fields = [{"name": f.name, "type": str(f.type), "nullable": f.nullable,
                   "comment": comments.get(var[table], {}).get(f.name, ""),
                   "partition": f.name in schema.PARTITION} for f in s]
        part_only = [{"name": f.name, "type": str(f.type), "nullable": f.nullable,
                      "comment": comments.get("PART_EXTRA", {}).get(f.name, "")} for f in schema.PART_EXTRA[table]]
        doc = {"table": table, "schema_version": schema.SCHEMA_VERSION, "partitioning": list(schema.PARTITION),
               "fields": fields, "part_only_fields": part_only}
        files[f"{table}.json"] = json.dumps(doc, indent=2, ensure_ascii=False) + "\n"
    files["views.sql"] = VIEWS_SQL.read_text()
    return files


def folder() -> Path:
    return HERE / f"v{schema.SCHEMA_VERSION}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare instead of writing")
    args = ap.parse_args()
    stale = []
    for name, text in generate().items():
        path = folder() / name
        if args.check:
            if not path.is_file() or path.read_text() != text:
                stale.append(str(path))
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    if stale:
        print("out of date (run python schemas/generate.py):", *stale, sep="\n  ")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
