"""`mine view`: a local web app to browse a catalogue — the standard library's HTTP server.

Its request handler, on ``http.server`` (``http.py``), serves pages, a JSON API and pictures
(``api.py``). This module makes the server of a catalogue (``make_server``) and runs it
(``run_view``).

It listens on 127.0.0.1 unless told otherwise (there is no authentication), and logs at most
one line per request, and only with ``log_requests`` (errors always). What a hostile page,
catalogue or client can do is bounded in ``http.py``.
"""

from __future__ import annotations

import ipaddress
import socket
import sys
import time
from pathlib import Path

import duckdb

from mining.errors import InputError
from mining.view.api import ViewApp
from mining.view.httpd import WILDCARD_HOSTS, Handler, HostRule, Limits, ViewServer, printable
from mining.view.images import default_cache_dir

DEFAULT_PORT = 8765  # ours


def address_family(host: str) -> socket.AddressFamily:
    """The socket family of ``host``, an IP address literal; InputError for anything else. A
    name could resolve to more than one address (or to a wildcard), so the server would not
    listen exactly where the user said."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        raise InputError(f"--host {host!r} is not an IP address: the viewer listens on exactly the address given "
                         "(127.0.0.1, ::1, a LAN address, or 0.0.0.0 / :: for every interface)") from None
    return socket.AF_INET6 if ip.version == 6 else socket.AF_INET


def make_server(out: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                cache_dir: Path | None = None, log_requests: bool = False, limits: Limits | None = None,
                author: str | None = None) -> ViewServer:
    """A server for catalogue ``out`` bound to exactly ``host:port`` (an IP address literal;
    0: a free port); accepting once serve_forever runs."""
    family = address_family(host)  # before the catalogue is opened or a socket made
    app = ViewApp(out, default_cache_dir() if cache_dir is None else cache_dir, log_requests, author)
    handler = type("BoundHandler", (Handler,), {"app": app})
    try:
        server = ViewServer((host, port), handler, limits or Limits(), HostRule(host), family)
    except OSError as e:
        app.browser.close()
        raise InputError(f"cannot listen on {host}:{port} ({e.strerror or e}); pass another --port (0 picks a free one)") \
            from None
    server.app = app
    return server


def run_view(out: str, host: str, port: int, cache_dir: str | None, log_requests: bool,
             author: str | None = None) -> int:
    """`mine view`: serve until Ctrl-C."""
    t0 = time.perf_counter()
    server = make_server(out, host, port, Path(cache_dir) if cache_dir else None, log_requests, author=author)
    app = server.app
    try:
        url = f"http://{host if ':' not in host else f'[{host}]'}:{server.server_address[1]}/"
        try:
            facets = app.browser.facets(False)
            what = f"{facets['selected']} selected of {facets['tubes']} tubes"
        except duckdb.Error as e:  # a damaged table: serve anyway, the pages say what is wrong
            what = "the catalogue cannot answer"
            print(f"mine view: {e}", file=sys.stderr)
        print(f"mine view: {out}: {what}; serving {url} (started in {time.perf_counter() - t0:.1f} s; Ctrl-C stops)",
              flush=True)
        if host in WILDCARD_HOSTS:
            print(f"mine view: listening on every interface (--host {host}): anyone who can reach this machine can "
                  f"browse the catalogue (no login); it answers to the names {', '.join(sorted(server.hosts.names))}"
                  " and any address", file=sys.stderr)
        elif not ipaddress.ip_address(host).is_loopback:
            print(f"mine view: listening on {host}: anyone who can reach it can browse the catalogue (no login); "
                  f"it answers to the names {', '.join(sorted(server.hosts.names))}"
                  + (" and any address" if server.hosts.any_address else ""), file=sys.stderr)
        if app.images.cache.problem:
            print(f"mine view: {app.images.cache.problem}", file=sys.stderr)
        reason = app.source.reason
        if reason:
            print(f"mine view: pictures are placeholders: {printable(reason)}", file=sys.stderr)
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        app.browser.close()
    return 0
