"""`mine view`: a local web app to browse a catalogue — the standard library's HTTP server.

``http.server.ThreadingHTTPServer`` (one thread per request) serves three things:

* pages and their script/style, read once from the package's ``static/`` folder (plain HTML,
  vanilla JS and CSS; no build step): ``/`` the gallery, ``/tube?id=…`` a tube;
* a JSON API: ``/api/facets?set=…``, ``/api/tubes?<filter>`` (``filters.py``),
  ``/api/tube?id=…``; a bad parameter is 400 with the message, an unknown tube 404, a
  damaged catalogue table 503 naming the file;
* pictures: ``/img/thumb?id=…`` and ``/img/frame?id=…&frame=N&size=full|strip`` (JPEG,
  ``images.py``). Where the frames cannot be read the picture is a placeholder saying why
  (header ``X-Placeholder``), so the gallery still works.

It listens on 127.0.0.1 unless told otherwise (there is no authentication), and logs at most
one line per request, and only with ``log_requests`` (errors always).
"""

from __future__ import annotations

import json
import sys
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import ClassVar
from urllib.parse import parse_qs, urlsplit

import duckdb

from mining.errors import InputError
from mining.view.catalogue import CatalogueBrowser
from mining.view.filters import FilterError, TubeFilter
from mining.view.images import SIZES, FrameSource, ImageCache, TubeImages, best_frame, default_cache_dir

DEFAULT_PORT = 8765  # ours
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml"}
PAGES = {"/": "index.html", "/index.html": "index.html", "/tube": "tube.html"}


class HttpError(Exception):
    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


def static_files() -> dict[str, tuple[bytes, str]]:
    """name → (bytes, content type) of every file in the package's static/ folder."""
    out = {}
    for entry in resources.files("mining.view").joinpath("static").iterdir():
        suffix = Path(entry.name).suffix
        if entry.is_file() and suffix in CONTENT_TYPES:
            out[entry.name] = (entry.read_bytes(), CONTENT_TYPES[suffix])
    return out


class ViewApp:
    """The catalogue, its pictures and the static files behind one server."""

    def __init__(self, out: str | Path, cache_dir: Path | None, log_requests: bool = False):
        self.browser = CatalogueBrowser(out)
        out_dir = Path(out).resolve()
        if cache_dir is not None and cache_dir.resolve().is_relative_to(out_dir):
            raise InputError("the picture cache may not live inside the catalogue; choose another --cache", cache_dir)
        job_error = self.browser.job_error
        self.source = FrameSource(self.browser.job, f"job.json cannot be read ({job_error})" if job_error else None)
        self.images = TubeImages(self.source, ImageCache(cache_dir))
        self.static = static_files()
        self.log_requests = log_requests

    # ------------------------------------------------------------------ routes

    def _tube(self, query: dict[str, list[str]]) -> dict:
        ids = query.get("id", [])
        if len(ids) != 1 or not ids[0]:
            raise HttpError(HTTPStatus.BAD_REQUEST, "give one tube id: ?id=DATASET/SEQUENCE/FRAME.OBS")
        tube = self.browser.tube(ids[0])
        if tube is None:
            raise HttpError(HTTPStatus.NOT_FOUND, f"no tube {ids[0]!r} in this catalogue")
        return tube

    def api_facets(self, query: dict[str, list[str]]) -> dict:
        which = (query.get("set") or ["selected"])[0]
        if which not in ("selected", "all"):
            raise HttpError(HTTPStatus.BAD_REQUEST, f"parameter 'set' is 'selected' or 'all', got {which!r}")
        facets = self.browser.facets(which == "all")
        facets["frames_unavailable"] = self.source.reason
        return facets

    def api_tubes(self, query: dict[str, list[str]]) -> dict:
        try:
            flt = TubeFilter.from_query(query)
        except FilterError as e:
            raise HttpError(HTTPStatus.BAD_REQUEST, str(e)) from None
        return self.browser.page(flt)

    def api_tube(self, query: dict[str, list[str]]) -> dict:
        tube = self._tube(query)
        detail = self.browser.detail(tube["tube_id"])
        detail["frames_unavailable"] = self.source.reason
        return detail

    def img_thumb(self, query: dict[str, list[str]]) -> tuple[bytes, str | None]:
        tube = self._tube(query)
        frames = self.browser.frames(tube)
        if not frames:
            raise HttpError(HTTPStatus.NOT_FOUND, f"tube {tube['tube_id']!r} has no frames in tube_frames")
        return self.images.thumbnail(tube, best_frame(frames))

    def img_frame(self, query: dict[str, list[str]]) -> tuple[bytes, str | None]:
        tube = self._tube(query)
        size = (query.get("size") or ["full"])[0]
        if size not in SIZES:
            raise HttpError(HTTPStatus.BAD_REQUEST, f"size is one of {', '.join(SIZES)}, got {size!r}")
        text = (query.get("frame") or [""])[0]
        try:
            n = int(text)
        except ValueError:
            raise HttpError(HTTPStatus.BAD_REQUEST, f"frame must be an integer, got {text!r}") from None
        frame = self.browser.frame(tube, n)
        if frame is None:
            raise HttpError(HTTPStatus.NOT_FOUND, f"tube {tube['tube_id']!r} has no frame {n}")
        return self.images.frame(tube, frame, size)

    API: ClassVar = {"/api/facets": api_facets, "/api/tubes": api_tubes, "/api/tube": api_tube}
    IMAGES: ClassVar = {"/img/thumb": img_thumb, "/img/frame": img_frame}


class Handler(BaseHTTPRequestHandler):
    """One request: a page, a static file, an API answer or a picture."""

    app: ViewApp  # set on the subclass make_server builds
    server_version = "tube-miner-view"
    protocol_version = "HTTP/1.1"

    def _send(self, status: HTTPStatus, body: bytes, content_type: str, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    @staticmethod
    def _json(status: HTTPStatus, obj) -> tuple[HTTPStatus, bytes, str, dict[str, str]]:
        body = json.dumps(obj, allow_nan=False, default=str).encode()
        return status, body, "application/json; charset=utf-8", {"Cache-Control": "no-store"}

    def _answer(self) -> tuple[tuple[HTTPStatus, bytes, str, dict[str, str]], str | None]:
        """(the response, a note for the log: why it failed, or None)."""
        url = urlsplit(self.path)
        query = parse_qs(url.query, keep_blank_values=True)
        app = self.app
        ok = HTTPStatus.OK
        try:
            if url.path in PAGES:
                body, ctype = app.static[PAGES[url.path]]
                return (ok, body, ctype, {"Cache-Control": "no-cache"}), None
            if url.path.startswith("/static/") and url.path[len("/static/"):] in app.static:
                body, ctype = app.static[url.path[len("/static/"):]]
                return (ok, body, ctype, {"Cache-Control": "no-cache"}), None
            if url.path in ViewApp.API:
                return self._json(ok, ViewApp.API[url.path](app, query)), None
            if url.path in ViewApp.IMAGES:
                data, reason = ViewApp.IMAGES[url.path](app, query)
                headers = {"Cache-Control": "no-cache" if reason else "max-age=3600"}
                if reason:
                    headers["X-Placeholder"] = reason.encode("ascii", "replace").decode()
                return (ok, data, "image/jpeg", headers), None
            raise HttpError(HTTPStatus.NOT_FOUND, f"no such page {url.path!r}")
        except HttpError as e:
            return self._json(e.status, {"error": str(e)}), None
        except duckdb.Error as e:  # a damaged table names its file (catalog/views.py)
            note = str(e).splitlines()[0]
            return self._json(HTTPStatus.SERVICE_UNAVAILABLE, {"error": f"the catalogue cannot answer: {e}"}), note
        except Exception as e:  # a bug: answer 500 with its name, log it, keep serving
            note = f"{type(e).__name__}: {e}"
            return self._json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": note}), note

    def do_GET(self) -> None:  # the http.server name
        t0 = time.perf_counter()
        (status, body, ctype, headers), note = self._answer()
        # At most one line per request, written before the answer leaves (so it is there when the client has it).
        if self.app.log_requests:
            tail = f" ({note})" if note else ""
            sys.stderr.write(f"{self.command} {self.path} {int(status)} {1000 * (time.perf_counter() - t0):.0f} ms{tail}\n")
        elif note:
            self.log_error("%s %s %d: %s", self.command, self.path, int(status), note)
        try:
            self._send(status, body, ctype, headers)
        except (BrokenPipeError, ConnectionResetError):
            pass

    do_HEAD = do_GET

    def log_message(self, format: str, *args) -> None:  # the http.server signature
        pass  # do_GET writes the one line per request (when asked)

    def log_error(self, format: str, *args) -> None:
        sys.stderr.write("mine view: " + (format % args) + "\n")


def make_server(out: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                cache_dir: Path | None = None, log_requests: bool = False) -> ThreadingHTTPServer:
    """A server for catalogue ``out`` bound to ``host:port`` (0: a free port); not yet serving."""
    app = ViewApp(out, default_cache_dir() if cache_dir is None else cache_dir, log_requests)
    handler = type("BoundHandler", (Handler,), {"app": app})
    try:
        server = ThreadingHTTPServer((host, port), handler)
    except OSError as e:
        app.browser.close()
        raise InputError(f"cannot listen on {host}:{port} ({e.strerror or e}); pass another --port (0 picks a free one)") \
            from None
    server.daemon_threads = True
    server.app = app
    return server


def run_view(out: str, host: str, port: int, cache_dir: str | None, log_requests: bool) -> int:
    """`mine view`: serve until Ctrl-C."""
    t0 = time.perf_counter()
    server = make_server(out, host, port, Path(cache_dir) if cache_dir else None, log_requests)
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
        if host not in ("127.0.0.1", "localhost", "::1"):
            print(f"mine view: listening on {host}: anyone who can reach it can browse the catalogue (no login)",
                  file=sys.stderr)
        if app.images.cache.problem:
            print(f"mine view: {app.images.cache.problem}", file=sys.stderr)
        reason = app.source.reason
        if reason:
            print(f"mine view: pictures are placeholders: {reason}", file=sys.stderr)
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        app.browser.close()
    return 0
