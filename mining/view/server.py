"""`mine view`: a local web app to browse a catalogue — the standard library's HTTP server.

``http.server``'s request handler serves three things:

* pages and their script/style, read once from the package's ``static/`` folder (plain HTML,
  vanilla JS and CSS; no build step): ``/`` the gallery, ``/tube?id=…`` a tube;
* a JSON API: ``/api/facets?set=…``, ``/api/tubes?<filter>`` (``filters.py``),
  ``/api/tube?id=…``, and the one write, ``POST /api/labels`` (a verdict or tag for several
  tubes: ``catalog/labels.py``, appended as a new file, never a rewrite); a bad or unknown parameter is 400 naming it, an unknown tube 404, a
  request over a limit 413 saying which, a damaged catalogue table 503 naming the file;
* pictures: ``/img/thumb?id=…`` and ``/img/frame?id=…&frame=N&size=full|strip`` (JPEG,
  ``images.py``). Where the frames cannot be read the picture is a placeholder saying why
  (header ``X-Placeholder``), so the gallery still works.

It listens on 127.0.0.1 unless told otherwise (there is no authentication), and logs at most
one line per request, and only with ``log_requests`` (errors always).

What a hostile page, catalogue or client can do is bounded here:

* every header value is printable ASCII (``header_value``): text from ``job.json`` or a
  source's error message cannot add a header or a body;
* the ``Host`` header must name this server (``HostRule``: the bound address and the names
  it resolves to, e.g. 127.0.0.1 and localhost, any port), so a page whose own name was
  rebound to 127.0.0.1 (DNS rebinding) is answered 400 and reads nothing;
* connections wait in one selector, not in threads (``ViewServer``): a connection takes a
  handler thread (``Limits.workers`` of them) only once its whole request head has arrived,
  idle ones are closed after ``Limits.idle_timeout_s``, and past ``Limits.max_connections``
  the longest-waiting one is closed, so idle sockets cannot starve a real request;
* a POST is answered only from this server's own pages: a JSON body (which another site's
  page cannot send without a CORS preflight, never granted), an ``Origin`` (when sent) of this
  server's own address, at most ``MAX_BODY_BYTES`` (``_post_problem``);
* one request costs at most one picture of ``images.MAX_PICTURE_PIXELS`` and
  ``catalogue.MAX_TUBE_FRAMES`` frames (413 past either).
"""

from __future__ import annotations

import errno
import io
import ipaddress
import json
import queue
import re
import resource
import selectors
import socket
import sys
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, HTTPServer
from importlib import resources
from pathlib import Path
from typing import ClassVar
from urllib.parse import parse_qs, urlsplit

import duckdb

from mining.errors import InputError
from mining.view.catalogue import CHOICE_COLUMNS, CatalogueBrowser
from mining.view.filters import FilterError, TooLarge, TubeFilter
from mining.view.images import SIZES, FrameSource, ImageCache, TubeImages, best_frame, default_cache_dir

DEFAULT_PORT = 8765  # ours
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml"}
PAGES = {"/": "index.html", "/index.html": "index.html", "/tube": "tube.html"}
# The pages load only their own scripts, styles and pictures, and no other site may frame them.
PAGE_POLICY = ("default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
               "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
# Answers that are data (JSON, pictures), opened on their own, run nothing.
DATA_POLICY = "default-src 'none'; sandbox; frame-ancestors 'none'"
MAX_HEADER_CHARS = 1000  # ours: a placeholder's reason is cut here in its header (the picture says it whole)
MAX_FRAME = 2**31 - 1  # frame numbers are int32 in the catalogue
MAX_BODY_BYTES = 1 << 20  # ours: a labelling request's JSON (MAX_LABEL_TUBES ids of ~25 characters fit many times)
MAX_LABEL_TUBES = 1000  # ours: tubes one request labels (a gallery page is at most filters.MAX_LIMIT)
_NOT_PRINTABLE = re.compile(r"[^\x20-\x7e]")
_HOST = re.compile(r"(?:\[(?P<v6>[0-9a-f:.]+)\]|(?P<name>[^:\[\]]+))(?::(?P<port>[0-9]{1,5}))?")
_HEAD_END = re.compile(rb"\r?\n\r?\n")
WILDCARD_HOSTS = ("", "0.0.0.0", "::")


class HttpError(Exception):
    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


def _not_json(constant: str) -> None:
    """``json.loads``'s hook for NaN / Infinity, which JSON does not have."""
    raise ValueError(f"{constant} is not JSON")


def header_value(value: object) -> str:
    """``value`` as a header value that cannot end its header: printable ASCII only (control
    characters, CR and LF among them, and anything non-ASCII become '?'), at most MAX_HEADER_CHARS."""
    return _NOT_PRINTABLE.sub("?", str(value))[:MAX_HEADER_CHARS]


def printable(text: str) -> str:
    """``text`` for a log line: control characters escaped, so a request cannot drive the terminal."""
    return _NOT_PRINTABLE.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


def static_files() -> dict[str, tuple[bytes, str]]:
    """name → (bytes, content type) of every file in the package's static/ folder."""
    out = {}
    for entry in resources.files("mining.view").joinpath("static").iterdir():
        suffix = Path(entry.name).suffix
        if entry.is_file() and suffix in CONTENT_TYPES:
            out[entry.name] = (entry.read_bytes(), CONTENT_TYPES[suffix])
    return out


def _one(query: dict[str, list[str]], name: str, allowed: frozenset[str], path: str) -> str | None:
    """The one value of parameter ``name`` (None when absent); 400 for a repeated or unknown parameter."""
    unknown = sorted(set(query) - allowed)
    if unknown:
        raise HttpError(HTTPStatus.BAD_REQUEST,
                        f"unknown parameter {unknown[0]!r}; {path} takes: {', '.join(sorted(allowed))}")
    values = query.get(name, [])
    if len(values) > 1:
        raise HttpError(HTTPStatus.BAD_REQUEST, f"parameter {name!r} given {len(values)} times; it takes one value")
    return values[0] if values else None


def _frame_number(text: str) -> int:
    """Parameter ``frame`` as a frame number; 400 saying why not."""
    try:
        n = int(text)
    except ValueError:
        raise HttpError(HTTPStatus.BAD_REQUEST, f"parameter 'frame': the frame must be an integer, got {text!r}") from None
    if not 0 <= n <= MAX_FRAME:
        raise HttpError(HTTPStatus.BAD_REQUEST, f"parameter 'frame': the frame must be in 0..{MAX_FRAME}, got {n}")
    return n


class HostRule:
    """Which ``Host`` headers a server bound to ``host`` answers.

    A browser sends the name it resolved; a page of another site whose name was rebound to
    this machine's address sends that site's name. So the name must be the bound address
    or one of its names (127.0.0.1 → 127.0.0.1, localhost, and what the resolver calls it);
    bound to every interface (0.0.0.0, ::), the machine's names, localhost, or any address
    literal (an address cannot be rebound, and behind NAT or in a container the address a
    client uses need not be one of ours). Any port: a tunnel or port forward changes it."""

    def __init__(self, host: str):
        self.bound = host
        self.any_address = host in WILDCARD_HOSTS
        names = {host.strip("[]").lower()} - {""}
        addresses: set[str] = set()
        if self.any_address:
            names |= {"localhost", "127.0.0.1", "::1", socket.gethostname().lower(), socket.getfqdn().lower()}
        else:
            try:
                addresses = {info[4][0] for info in socket.getaddrinfo(host.strip("[]"), None)}
            except OSError:
                addresses = set()
        for address in addresses:
            names.add(address.lower())
            try:
                name, aliases, _ = socket.gethostbyaddr(address)
                names |= {n.lower() for n in (name, *aliases)}
            except OSError:  # no reverse entry: the address itself still answers
                pass
            ip = ipaddress.ip_address(address.split("%")[0])
            if ip.is_loopback:
                names.add("localhost")
            else:  # another interface: the machine's own names reach it too
                names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.names = frozenset(n.rstrip(".") for n in names)

    def problem(self, headers: list[str] | None) -> str | None:
        """Why a request with these Host header values is refused, or None."""
        if not headers:
            return "the request has no Host header"
        if len(headers) > 1:
            return "the request has more than one Host header"
        m = _HOST.fullmatch(headers[0].strip().lower())
        if m is not None:
            name = (m["v6"] or m["name"]).rstrip(".")
            if name in self.names:
                return None
            if self.any_address:
                try:
                    ipaddress.ip_address(name)
                    return None
                except ValueError:
                    pass
        shown = ", ".join(sorted(self.names)) + (" or any address" if self.any_address else "")
        return (f"Host {header_value(headers[0])!r} is not this server: it answers to {shown} (any port). "
                "A page that reached it under another name is refused (DNS rebinding).")


@dataclass(frozen=True)
class Limits:
    """What one server holds at once (every bound ours)."""

    workers: int = 8  # handler threads: requests answered at once (the frame source draws one at a time anyway)
    max_connections: int = 256  # open connections, idle ones included; also at most a quarter of the open-file limit
    idle_timeout_s: float = 15.0  # a connection without a whole request head for this long is closed
    write_timeout_s: float = 30.0  # a client that does not take its answer for this long is dropped
    max_head_bytes: int = 16384  # request line and headers; longer is 431


def connection_cap(wanted: int) -> int:
    """``wanted``, or fewer where the open-file limit is low: connections must not take the descriptors
    that DuckDB, the source's files and the next accept need."""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (ValueError, OSError):
        return wanted
    return wanted if soft == resource.RLIM_INFINITY else max(8, min(wanted, soft // 4))


class ViewApp:
    """The catalogue, its pictures and the static files behind one server."""

    def __init__(self, out: str | Path, cache_dir: Path | None, log_requests: bool = False, author: str | None = None):
        self.browser = CatalogueBrowser(out, author)
        out_dir = Path(out).resolve()
        if cache_dir is not None and cache_dir.resolve().is_relative_to(out_dir):
            raise InputError("the picture cache may not live inside the catalogue; choose another --cache", cache_dir)
        job_error = self.browser.job_error
        self.source = FrameSource(self.browser.job, f"job.json cannot be read ({job_error})" if job_error else None)
        self.images = TubeImages(self.source, ImageCache(cache_dir))
        self.static = static_files()
        self.log_requests = log_requests

    # ------------------------------------------------------------------ routes

    def _tube(self, query: dict[str, list[str]], path: str, allowed: frozenset[str]) -> dict:
        tube_id = _one(query, "id", allowed, path)
        if not tube_id:
            raise HttpError(HTTPStatus.BAD_REQUEST, "give one tube id: ?id=DATASET/SEQUENCE/FRAME.OBS")
        tube = self.browser.tube(tube_id)
        if tube is None:
            raise HttpError(HTTPStatus.NOT_FOUND, f"no tube {tube_id!r} in this catalogue")
        return tube

    def api_facets(self, query: dict[str, list[str]]) -> dict:
        which = _one(query, "set", frozenset({"set"}), "/api/facets") or "selected"
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
        allowed = frozenset({"id", "frame"})
        tube = self._tube(query, "/api/tube", allowed)
        text = _one(query, "frame", allowed, "/api/tube")
        frame = None if text in (None, "") else _frame_number(text)
        detail = self.browser.detail(tube["tube_id"], frame)
        detail["frames_unavailable"] = self.source.reason
        return detail

    def img_thumb(self, query: dict[str, list[str]]) -> tuple[bytes, str | None]:
        tube = self._tube(query, "/img/thumb", frozenset({"id"}))
        frames = self.browser.frames(tube, CHOICE_COLUMNS)  # no masks: only the chosen frame's is read
        if not frames:
            raise HttpError(HTTPStatus.NOT_FOUND, f"tube {tube['tube_id']!r} has no frames in tube_frames")
        frame = self.browser.frame(tube, best_frame(frames)["frame"])
        return self.images.thumbnail(tube, frame)

    def img_frame(self, query: dict[str, list[str]]) -> tuple[bytes, str | None]:
        allowed = frozenset({"id", "frame", "size"})
        tube = self._tube(query, "/img/frame", allowed)
        size = _one(query, "size", allowed, "/img/frame") or "full"
        if size not in SIZES:
            raise HttpError(HTTPStatus.BAD_REQUEST, f"parameter 'size': the size is one of {', '.join(SIZES)}, got {size!r}")
        n = _frame_number(_one(query, "frame", allowed, "/img/frame") or "")
        frame = self.browser.frame(tube, n)
        if frame is None:
            raise HttpError(HTTPStatus.NOT_FOUND, f"tube {tube['tube_id']!r} has no frame {n}")
        return self.images.frame(tube, frame, size)

    def api_labels(self, body: object) -> dict:
        """POST /api/labels: {"tubes": [ids], and one of "verdict": V (null: take it back),
        "tag": T, "untag": T}; the tubes' labels after it."""
        if not isinstance(body, dict):
            raise HttpError(HTTPStatus.BAD_REQUEST, "the body is a JSON object: {\"tubes\": [ids], \"verdict\" | \"tag\" | \"untag\": …}")
        unknown = sorted(set(body) - {"tubes", "verdict", "tag", "untag"})
        if unknown:
            raise HttpError(HTTPStatus.BAD_REQUEST, f"unknown field {unknown[0]!r}; /api/labels takes tubes and one of "
                                                    "verdict, tag, untag")
        ids = body.get("tubes")
        if not isinstance(ids, list) or not ids or not all(isinstance(t, str) for t in ids):
            raise HttpError(HTTPStatus.BAD_REQUEST, "field 'tubes' is a non-empty list of tube ids")
        if len(ids) > MAX_LABEL_TUBES:
            raise TooLarge(f"{len(ids)} tubes in one labelling; at most {MAX_LABEL_TUBES}")
        actions = [k for k in ("verdict", "tag", "untag") if k in body]
        if len(actions) != 1:
            raise HttpError(HTTPStatus.BAD_REQUEST, "give exactly one of the fields verdict, tag, untag")
        action = actions[0]
        value = body[action]
        kind, op = {"verdict": ("verdict", "unset" if value is None else "set"), "tag": ("tag", "set"),
                    "untag": ("tag", "unset")}[action]
        try:
            rows = self.browser.label(list(dict.fromkeys(ids)), kind, value, op)
        except InputError as e:
            raise HttpError(HTTPStatus.NOT_FOUND if str(e).startswith("no tube") else HTTPStatus.BAD_REQUEST,
                            str(e)) from None
        return {"labelled": rows, "author": self.browser.author}

    API: ClassVar = {"/api/facets": api_facets, "/api/tubes": api_tubes, "/api/tube": api_tube}
    POSTS: ClassVar = {"/api/labels": api_labels}
    IMAGES: ClassVar = {"/img/thumb": img_thumb, "/img/frame": img_frame}


class Handler(BaseHTTPRequestHandler):
    """One request: a page, a static file, an API answer or a picture.

    ``ViewServer`` hands it a connection whose whole request head has already arrived
    (``request`` is (socket, head)), so reading never waits on the client; after one answer
    the connection goes back to the server's selector (keep-alive) or is closed."""

    app: ViewApp  # set on the subclass make_server builds
    server: ViewServer
    server_version = "tube-miner-view"
    protocol_version = "HTTP/1.1"

    def setup(self) -> None:  # the socketserver hook
        sock, head, self.leftover = self.request
        self.request = self.connection = sock
        sock.settimeout(self.server.limits.write_timeout_s)
        self.rfile = io.BytesIO(head)
        self.wfile = sock.makefile("wb")  # buffered: every write is whole; flushed after each answer

    def handle(self) -> None:  # one request; the server keeps the connection between requests
        self.close_connection = True
        self.handle_one_request()

    def send_header(self, keyword: str, value: str) -> None:
        """Every header goes through here, its value made safe (``header_value``)."""
        super().send_header(keyword, header_value(value))

    def _send(self, status: HTTPStatus, body: bytes, content_type: str, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", PAGE_POLICY if content_type.startswith("text/html") else DATA_POLICY)
        self.send_header("Cross-Origin-Resource-Policy", "same-origin")
        self.send_header("Referrer-Policy", "no-referrer")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    @staticmethod
    def _json(status: HTTPStatus, obj) -> tuple[HTTPStatus, bytes, str, dict[str, str]]:
        body = json.dumps(obj, allow_nan=False, default=str).encode()
        return status, body, "application/json; charset=utf-8", {"Cache-Control": "no-store"}

    def _answer(self) -> tuple[tuple[HTTPStatus, bytes, str, dict[str, str]], str | None]:
        """(the response, a note for the log: why it failed, or None)."""
        problem = self.server.hosts.problem(self.headers.get_all("Host"))
        if problem:
            return self._json(HTTPStatus.BAD_REQUEST, {"error": problem}), None
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
                    headers["X-Placeholder"] = reason
                return (ok, data, "image/jpeg", headers), None
            raise HttpError(HTTPStatus.NOT_FOUND, f"no such page {url.path!r}")
        except HttpError as e:
            return self._json(e.status, {"error": str(e)}), None
        except TooLarge as e:
            return self._json(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, {"error": str(e)}), None
        except duckdb.Error as e:  # a damaged table names its file (catalog/views.py)
            note = str(e).splitlines()[0]
            return self._json(HTTPStatus.SERVICE_UNAVAILABLE, {"error": f"the catalogue cannot answer: {e}"}), note
        except Exception as e:  # a bug: answer 500 with its name, log it, keep serving
            note = f"{type(e).__name__}: {e}"
            return self._json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": note}), note

    def do_GET(self) -> None:  # the http.server name
        t0 = time.perf_counter()
        if self.headers.get("Content-Length", "0").strip() not in ("", "0") or "Transfer-Encoding" in self.headers:
            self.close_connection = True  # a body is never read: the connection cannot carry another request
        self._finish(t0, *self._answer())

    def do_POST(self) -> None:  # the http.server name
        t0 = time.perf_counter()
        self._finish(t0, *self._answer_post())

    def _finish(self, t0: float, answer: tuple[HTTPStatus, bytes, str, dict[str, str]], note: str | None) -> None:
        status, body, ctype, headers = answer
        # At most one line per request, written before the answer leaves (so it is there when the client has it).
        if self.app.log_requests:
            tail = f" ({note})" if note else ""
            sys.stderr.write(printable(f"{self.command} {self.path} {int(status)} "
                                       f"{1000 * (time.perf_counter() - t0):.0f} ms{tail}") + "\n")
        elif note:
            self.log_error("%s %s %d: %s", self.command, self.path, int(status), note)
        try:
            self._send(status, body, ctype, headers)
            self.wfile.flush()
        except OSError:  # the client left or stopped reading (write timeout)
            self.close_connection = True

    def _post_problem(self) -> str | None:
        """Why a POST is not from this server's own pages, or None. A page of another site can
        send a form (urlencoded, multipart, text/plain) here without asking; a JSON body it can
        send only after a CORS preflight, which this server never grants; and a browser names
        the page's origin, which must be this server's."""
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return f"a POST body is application/json, got {ctype or 'none'!r}"
        origin = self.headers.get("Origin")
        host = (self.headers.get("Host") or "").strip().lower()
        if origin is not None and origin.strip().lower() not in (f"http://{host}", f"https://{host}"):
            return f"the request comes from another site ({header_value(origin)!r}); labels are made on this server's pages"
        site = self.headers.get("Sec-Fetch-Site")
        if site is not None and site.strip().lower() not in ("same-origin", "none"):
            return f"the request comes from another site (Sec-Fetch-Site: {header_value(site)!r})"
        return None

    def _read_body(self) -> bytes:
        """The request's body (Content-Length bytes): what arrived with the head, then the socket."""
        if "Transfer-Encoding" in self.headers:
            self.close_connection = True
            raise HttpError(HTTPStatus.LENGTH_REQUIRED, "a POST gives its Content-Length (no chunked bodies)")
        text = (self.headers.get("Content-Length") or "").strip()
        if not text.isdigit():
            self.close_connection = True
            raise HttpError(HTTPStatus.LENGTH_REQUIRED, "a POST gives its Content-Length")
        n = int(text)
        if n > MAX_BODY_BYTES:
            self.close_connection = True  # the body is not read: the connection cannot carry another request
            raise TooLarge(f"a body of {n} bytes; at most {MAX_BODY_BYTES}")
        body, self.leftover = bytes(self.leftover[:n]), self.leftover[n:]
        while len(body) < n:  # the socket's write timeout bounds the wait (Limits.write_timeout_s)
            try:
                chunk = self.connection.recv(n - len(body))
            except OSError:
                chunk = b""
            if not chunk:
                self.close_connection = True
                raise HttpError(HTTPStatus.BAD_REQUEST, f"the body ended after {len(body)} of {n} bytes")
            body += chunk
        return body

    def _answer_post(self) -> tuple[tuple[HTTPStatus, bytes, str, dict[str, str]], str | None]:
        problem = self.server.hosts.problem(self.headers.get_all("Host"))
        if problem:
            self.close_connection = True
            return self._json(HTTPStatus.BAD_REQUEST, {"error": problem}), None
        path = urlsplit(self.path).path
        try:
            body = self._read_body()
            if path not in ViewApp.POSTS:
                raise HttpError(HTTPStatus.NOT_FOUND if path not in PAGES and path not in ViewApp.API
                                else HTTPStatus.METHOD_NOT_ALLOWED, f"no POST to {path!r}; POST /api/labels only")
            problem = self._post_problem()
            if problem:
                raise HttpError(HTTPStatus.FORBIDDEN, problem)
            try:
                obj = json.loads(body, parse_constant=_not_json)
            except (ValueError, UnicodeDecodeError) as e:
                raise HttpError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {e}") from None
            return self._json(HTTPStatus.OK, ViewApp.POSTS[path](self.app, obj)), None
        except HttpError as e:
            return self._json(e.status, {"error": str(e)}), None
        except TooLarge as e:
            return self._json(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, {"error": str(e)}), None
        except (duckdb.Error, OSError) as e:  # a damaged labels file, a full disk: named
            note = str(e).splitlines()[0]
            return self._json(HTTPStatus.SERVICE_UNAVAILABLE, {"error": f"the labels cannot be written: {e}"}), note
        except Exception as e:  # a bug: answer 500 with its name, log it, keep serving
            note = f"{type(e).__name__}: {e}"
            return self._json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": note}), note

    do_HEAD = do_GET

    def log_message(self, format: str, *args) -> None:  # the http.server signature
        pass  # do_GET writes the one line per request (when asked)

    def log_error(self, format: str, *args) -> None:
        sys.stderr.write("mine view: " + printable(format % args) + "\n")


@dataclass
class _Waiting:
    """A connection in the selector: what it has sent of its next request, and when it must be whole."""

    address: tuple
    buffer: bytearray
    deadline: float


class ViewServer(HTTPServer):
    """``HTTPServer`` whose connections wait in one selector thread, not one thread each.

    ``serve_forever`` accepts; each connection is parked in the selector until its request
    head has arrived whole (``_HEAD_END``), then one of ``Limits.workers`` handler threads
    answers it and parks it again (keep-alive) or closes it. A connection that has not sent a
    whole head within ``idle_timeout_s`` is closed; past ``max_connections`` (see
    ``connection_cap``) the longest-waiting parked connection is closed first, so a flood of
    idle sockets costs descriptors we bound, not threads, and a new request still gets in."""

    request_queue_size = 128  # the listen backlog (socketserver's 5 overflows under a burst of connects)

    def __init__(self, address: tuple[str, int], handler: type[Handler], limits: Limits, hosts: HostRule):
        self.limits, self.hosts = limits, hosts
        self.cap = connection_cap(limits.max_connections)
        self._lock = threading.Lock()
        self._open = 0  # accepted and not yet closed: parked, queued or being answered
        self._commands: deque = deque()  # for the selector thread, which alone touches parked sockets
        self._work: queue.SimpleQueue = queue.SimpleQueue()
        self._closing = False
        self._threads: list[threading.Thread] = []
        self._wake_r, self._wake_w = socket.socketpair()
        for s in (self._wake_r, self._wake_w):
            s.setblocking(False)
        super().__init__(address, handler)  # binds and listens (OSError when the port is taken)
        self._threads = [threading.Thread(target=self._select_loop, name="mine-view-select", daemon=True)]
        self._threads += [threading.Thread(target=self._answer_loop, name=f"mine-view-{k}", daemon=True)
                          for k in range(limits.workers)]
        for t in self._threads:
            t.start()

    # ------------------------------------------------------------------ socketserver hooks

    def get_request(self) -> tuple[socket.socket, tuple]:
        try:
            return super().get_request()
        except OSError as e:
            if e.errno in (errno.EMFILE, errno.ENFILE):  # out of descriptors: free one for the next accept
                self._tell(("shed",))
                time.sleep(0.01)
            raise  # serve_forever ignores it and accepts again

    def process_request(self, request: socket.socket, client_address: tuple) -> None:
        with self._lock:
            self._open += 1
        self._tell(("park", request, client_address, b""))

    def server_close(self) -> None:
        super().server_close()
        self._closing = True
        if not self._threads:  # the port was taken: nothing started
            self._wake_r.close()
            self._wake_w.close()
            return
        self._tell(("stop",))
        for _ in range(self.limits.workers):
            self._work.put(None)
        self._threads[0].join(5)  # the selector thread closes the parked connections

    def open_connections(self) -> int:
        """Connections accepted and not yet closed (parked, queued or being answered)."""
        with self._lock:
            return self._open

    # ------------------------------------------------------------------ the selector thread

    def _tell(self, command: tuple) -> None:
        self._commands.append(command)
        try:
            self._wake_w.send(b"\0")
        except OSError:  # the wake-up pipe is full (the thread will see the commands) or closed
            pass

    def _close(self, sock: socket.socket) -> None:
        try:
            self.shutdown_request(sock)
        finally:
            with self._lock:
                self._open -= 1

    def _select_loop(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ)
        parked: OrderedDict[socket.socket, _Waiting] = OrderedDict()  # oldest first

        def drop(sock: socket.socket) -> None:
            sel.unregister(sock)
            del parked[sock]
            self._close(sock)

        def advance(sock: socket.socket) -> None:
            w = parked[sock]
            m = _HEAD_END.search(w.buffer)
            if (m.end() if m else len(w.buffer)) > self.limits.max_head_bytes:
                try:
                    sock.send(b"HTTP/1.1 431 Request Header Fields Too Large\r\nContent-Length: 0\r\n"
                              b"Connection: close\r\n\r\n")
                except OSError:
                    pass
                drop(sock)
            elif m:
                sel.unregister(sock)
                del parked[sock]
                sock.setblocking(True)
                self._work.put((sock, w.address, bytes(w.buffer[:m.end()]), bytes(w.buffer[m.end():])))

        try:
            while not self._closing:
                now = time.monotonic()
                first = next(iter(parked.values()), None)
                timeout = 1.0 if first is None else min(1.0, max(0.0, first.deadline - now))
                for key, _ in sel.select(timeout):
                    sock = key.fileobj
                    if sock is self._wake_r:
                        try:
                            while sock.recv(4096):
                                pass
                        except OSError:
                            pass
                        continue
                    if sock not in parked:
                        continue
                    try:
                        chunk = sock.recv(65536)
                    except (BlockingIOError, InterruptedError):
                        continue
                    except OSError:
                        chunk = b""
                    if not chunk:  # the client closed it
                        drop(sock)
                        continue
                    parked[sock].buffer += chunk
                    advance(sock)
                while self._commands:
                    command = self._commands.popleft()
                    if command[0] == "park":
                        _, sock, address, rest = command
                        try:
                            sock.setblocking(False)
                            sel.register(sock, selectors.EVENT_READ)
                        except (OSError, ValueError):  # closed under us: this connection only, not the thread
                            self._close(sock)
                            continue
                        # The deadline counts from now: parked connections stay in deadline order.
                        parked[sock] = _Waiting(address, bytearray(rest), time.monotonic() + self.limits.idle_timeout_s)
                        advance(sock)  # what it sent after its last request may be a whole one
                    elif command[0] == "shed" and parked:
                        drop(next(iter(parked)))
                while parked and self.open_connections() > self.cap:
                    drop(next(iter(parked)))  # the longest-waiting one: most likely idle, and a browser reconnects
                now = time.monotonic()
                while parked and next(iter(parked.values())).deadline <= now:
                    drop(next(iter(parked)))
        finally:
            for sock in list(parked):
                drop(sock)
            while self._commands:  # parked after the loop ended
                command = self._commands.popleft()
                if command[0] == "park":
                    self._close(command[1])
            sel.close()
            self._wake_r.close()
            self._wake_w.close()

    # ------------------------------------------------------------------ the handler threads

    def _answer_loop(self) -> None:
        while (item := self._work.get()) is not None:
            sock, address, head, rest = item
            keep = False
            try:
                handler = self.RequestHandlerClass((sock, head, rest), address, self)
                keep = not handler.close_connection and not self._closing
                rest = handler.leftover  # what the client sent after this request (less the body a POST read)
            except Exception:  # a bug in answering: say so, drop this connection, keep serving
                self.handle_error(sock, address)
            if keep:
                self._tell(("park", sock, address, rest))
            else:
                self._close(sock)

    def handle_error(self, request, client_address) -> None:
        import traceback

        sys.stderr.write("mine view: " + printable(traceback.format_exc().rstrip()) + "\n")


def make_server(out: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                cache_dir: Path | None = None, log_requests: bool = False, limits: Limits | None = None,
                author: str | None = None) -> ViewServer:
    """A server for catalogue ``out`` bound to ``host:port`` (0: a free port); accepting once serve_forever runs."""
    app = ViewApp(out, default_cache_dir() if cache_dir is None else cache_dir, log_requests, author)
    handler = type("BoundHandler", (Handler,), {"app": app})
    try:
        server = ViewServer((host, port), handler, limits or Limits(), HostRule(host))
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
        if host not in ("127.0.0.1", "localhost", "::1"):
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
