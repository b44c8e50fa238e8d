"""The HTTP side of `mine view`: the request handler (``Handler``: a page, a static file, an API
answer or a picture, with its headers and checks) and the server loop (``ViewServer``: the
connections wait in one selector), with the bounds on what a client may cost. The routes and
their handlers are ``api.py``; the server that binds them is ``server.py``.

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
from urllib.parse import parse_qs, urlsplit

import duckdb

from mining.view.api import PAGES, HttpError, ViewApp
from mining.view.filters import TooLarge

# The pages load only their own scripts, styles and pictures, and no other site may frame them.
PAGE_POLICY = ("default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
               "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
# Answers that are data (JSON, pictures), opened on their own, run nothing.
DATA_POLICY = "default-src 'none'; sandbox; frame-ancestors 'none'"
MAX_HEADER_CHARS = 1000  # ours: a placeholder's reason is cut here in its header (the picture says it whole)
MAX_BODY_BYTES = 1 << 20  # ours: a labelling request's JSON (MAX_LABEL_TUBES ids of ~25 characters fit many times)
MAX_BODY_DEPTH = 32  # ours: arrays/objects nested in a POST body (a labelling request nests two)
_NOT_PRINTABLE = re.compile(r"[^\x20-\x7e]")
_HOST = re.compile(r"(?:\[(?P<v6>[0-9a-f:.]+)\]|(?P<name>[^:\[\]]+))(?::(?P<port>[0-9]{1,5}))?")
_HEAD_END = re.compile(rb"\r?\n\r?\n")
WILDCARD_HOSTS = ("0.0.0.0", "::")  # every interface (IPv4; IPv6 and, dual-stack, IPv4 too)


def _not_json(constant: str) -> None:
    """``json.loads``'s hook for NaN / Infinity, which JSON does not have."""
    raise ValueError(f"{constant} is not JSON")


def json_body(body: bytes) -> object:
    """A POST body parsed as JSON, or HttpError 400 saying why: not UTF-8, not JSON, or nested
    past MAX_BODY_DEPTH (a body of a million ``[`` is a RecursionError inside ``json.loads``)."""
    try:
        obj = json.loads(body.decode("utf-8"), parse_constant=_not_json)
    except UnicodeDecodeError as e:
        raise HttpError(HTTPStatus.BAD_REQUEST, f"the body is not UTF-8 text: byte 0x{body[e.start]:02x} at offset "
                                                f"{e.start}") from None
    except RecursionError:
        raise HttpError(HTTPStatus.BAD_REQUEST, f"the body nests arrays or objects deeper than {MAX_BODY_DEPTH}") \
            from None
    except ValueError as e:
        raise HttpError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {e}") from None
    level, depth = [obj], 0
    while level:  # breadth first, so a deep body cannot exhaust the stack here either
        depth += 1
        if depth > MAX_BODY_DEPTH:
            raise HttpError(HTTPStatus.BAD_REQUEST, f"the body nests arrays or objects deeper than {MAX_BODY_DEPTH}")
        level = [v for x in level if isinstance(x, (list, dict)) for v in (x.values() if isinstance(x, dict) else x)]
    return obj


def header_value(value: object) -> str:
    """``value`` as a header value that cannot end its header: printable ASCII only (control
    characters, CR and LF among them, and anything non-ASCII become '?'), at most MAX_HEADER_CHARS."""
    return _NOT_PRINTABLE.sub("?", str(value))[:MAX_HEADER_CHARS]


def printable(text: str) -> str:
    """``text`` for a log line: control characters escaped, so a request cannot drive the terminal."""
    return _NOT_PRINTABLE.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


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
            return self._json(HTTPStatus.OK, ViewApp.POSTS[path](self.app, json_body(body))), None
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

    def __init__(self, address: tuple[str, int], handler: type[Handler], limits: Limits, hosts: HostRule,
                 family: socket.AddressFamily = socket.AF_INET):
        self.address_family = family  # read by socketserver when it makes the listening socket
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
