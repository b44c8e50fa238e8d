"""The JSON API of `mine view`: its routes and the handlers behind them (``ViewApp``), over
the catalogue (``catalogue.py``, ``filters.py``) and its pictures (``images.py``). The HTTP
side (the request handler, its limits and headers, the selector loop) is ``http.py``; the
server that binds them is ``server.py``.

Routes:

* pages and their script/style, read once from the package's ``static/`` folder (plain HTML,
  vanilla JS and CSS; no build step): ``/`` the gallery, ``/tube?id=…`` a tube, ``/groups`` one
  tile per group of the unknown set (``PAGES``);
* a JSON API: ``/api/facets?set=…``, ``/api/tubes?<filter>`` (``filters.py``),
  ``/api/tube?id=…`` (with its similar tubes), ``/api/groups``, and the one write, ``POST /api/labels`` (a verdict or tag for several
  tubes: ``catalog/labels.py``, appended as a new file, never a rewrite); a bad or unknown parameter is 400 naming it, an unknown tube 404, a
  request over a limit 413 saying which, a damaged catalogue table 503 naming the file;
* pictures: ``/img/thumb?id=…`` and ``/img/frame?id=…&frame=N&size=full|strip`` (JPEG,
  ``images.py``). Where the frames cannot be read the picture is a placeholder saying why
  (header ``X-Placeholder``), so the gallery still works.

A handler raises ``HttpError`` (its status and message) or ``filters.TooLarge`` (413); the
request handler turns either into the JSON answer ``{"error": …}``.
"""

from __future__ import annotations

from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import ClassVar

from mining.errors import InputError
from mining.view.catalogue import CHOICE_COLUMNS, CatalogueBrowser
from mining.view.filters import FilterError, TooLarge, TubeFilter
from mining.view.images import SIZES, FrameSource, ImageCache, TubeImages, best_frame

CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml"}
PAGES = {"/": "index.html", "/index.html": "index.html", "/tube": "tube.html", "/groups": "groups.html"}
MAX_FRAME = 2**31 - 1  # frame numbers are int32 in the catalogue
MAX_LABEL_TUBES = 1000  # ours: tubes one request labels (a gallery page is at most filters.MAX_LIMIT)


class HttpError(Exception):
    """An answer other than 200 from a route: its status and the message its JSON error carries."""

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

    def api_groups(self, query: dict[str, list[str]]) -> dict:
        if query:
            raise HttpError(HTTPStatus.BAD_REQUEST, f"/api/groups takes no parameter, got {sorted(query)[0]!r}")
        return self.browser.groups()

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

    API: ClassVar = {"/api/facets": api_facets, "/api/tubes": api_tubes, "/api/tube": api_tube, "/api/groups": api_groups}
    POSTS: ClassVar = {"/api/labels": api_labels}
    IMAGES: ClassVar = {"/img/thumb": img_thumb, "/img/frame": img_frame}
