"""``mine config``: every job config key with its value, default, source and comment (of the
defaults, or of the job options given), as text or JSON (``configdoc.py`` reads the keys)."""

from __future__ import annotations

import argparse

from mining.errors import ConfigError
from mining.pipeline.arguments import add_job_options, job_config


def add_arguments(cfg: argparse.ArgumentParser) -> None:
    cfg.add_argument("keys", nargs="?", metavar="KEYS",
                     help="only the keys starting with this (e.g. tubes. or select.epsilon), else those holding it")
    add_job_options(cfg)
    cfg.add_argument("--format", choices=["text", "json"], default="text")


def run(args: argparse.Namespace) -> int:
    import difflib
    import json

    from mining.config import JobConfig
    from mining.configdoc import all_keys, matching_keys, source_tag, toml_value, value_at

    given = bool(args.config or args.set or args.dataset or args.root or args.option)
    cfg = job_config(args) if given else JobConfig()
    keys = all_keys()
    shown = matching_keys(keys, args.keys)
    if not shown:
        words = sorted({k.path for k in keys} | {k.path.rsplit(".", 1)[0] + "." for k in keys if "." in k.path})
        near = difflib.get_close_matches(args.keys, words, n=3)
        hint = f"; did you mean {' or '.join(repr(w) for w in near)}?" if near else ""
        raise ConfigError(f"no config key matches {args.keys!r}{hint} (`mine config` lists all {len(keys)})")
    rows = [{"key": k.path, "value": value_at(cfg, k.path), "default": k.default, "source": source_tag(k.comment),
             "type": k.type, "rules": k.rules, "comment": k.comment} for k in shown]
    if args.format == "json":
        print(json.dumps(rows, indent=1, ensure_ascii=False, default=str))
        return 0
    origin = " + ".join(([str(args.config)] if args.config else []) + (["the options given"] if given and (
        args.set or args.option or args.dataset or args.root) else [])) or "the defaults"
    print(f"{len(rows)} of {len(keys)} job config keys, values of {origin}; [where the default comes from]; "
          "rules: docs/CONFIG.md")
    for r in rows:
        value = toml_value(r["value"])
        differs = f"  (default {r['default']})" if value != r["default"] else ""
        print(f"{r['key']} = {value}{differs}  [{r['source']}]")
        if r["comment"]:
            print(f"    {r['comment']}")
    return 0
