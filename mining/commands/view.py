"""``mine view``: browse the catalogue in a web browser, a gallery of tubes and a page per tube
(``view/server.py`` serves it)."""

from __future__ import annotations

import argparse

from mining.checks import count, output_folder, path_text


def add_arguments(viw: argparse.ArgumentParser) -> None:
    viw.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    viw.add_argument("--port", type=count(0, 65535), default=8765, help="port to listen on (default 8765; 0 picks a free one)")
    viw.add_argument("--host", default="127.0.0.1",
                     help="IP address to listen on, exactly (default 127.0.0.1: this machine only; 0.0.0.0 or :: "
                          "for every interface; there is no login)")
    viw.add_argument("--cache", type=output_folder, help="folder for rendered pictures (default: tube-miner/view in $XDG_CACHE_HOME or "
                                     "~/.cache, made 0700; refused when not yours alone; not inside the catalogue)")
    viw.add_argument("--log", action="store_true", help="log one line per request on standard error")
    viw.add_argument("--author", help="the author of labels made in this viewer (default: the login name)")


def run(args: argparse.Namespace) -> int:
    from mining.view.server import run_view

    return run_view(args.out, args.host, args.port, args.cache, args.log, args.author)
