"""The viewer's pictures: a tube's mask outlined on its real source frame, rendered on demand.

The catalogue keeps masks (COCO RLE) and boxes, not pixels; the pixels are re-read through
the source that ``OUT/job.json`` names (as ``mine export --format crops`` does), so a
catalogue copied to a machine without its frames still browses: every picture is then a
placeholder that says why (``FrameSource.reason``).

Two pictures: a gallery *thumbnail* (the tube's best view — its largest observed box not
cut by the image border — cropped with context around the box) and a *frame* (the full
frame, or a strip-sized copy, with the mask filled and outlined). They are drawn by
``mining/draw.py`` (as `mine render` draws), after resizing, so outlines stay two pixels wide.

Encoded JPEGs are cached twice: an LRU in memory, and files in a folder (``--cache``; by
default ``tube-miner/view`` in the user's own cache folder, never inside the catalogue). The
folder is only used when it is the user's and nobody else may write in it (created 0700;
one owned by someone else, or with group or other write bits, is refused: memory only, with
a note). It holds a secret ``key`` (32 random bytes, 0600); a file's name is the HMAC-SHA256
under that key of everything the picture depends on (the source, the frame, the mask, the
box, the kind and size, ``RENDER_VERSION``), so no name is built from a tube id, a changed
catalogue cannot serve a stale picture, and nobody without the key can tell which name a
picture will have. Each file also carries, in a JPEG comment after its start marker, an
HMAC of its name and its bytes: a file this viewer did not write is never served (it is
drawn again and replaced). Files are 0600, subfolders 0700.

One picture costs at most ``MAX_PICTURE_PIXELS``: a catalogue row whose mask is larger is
refused (``TooLarge``, answered 413) before any pixel is read or allocated, and a mask whose
runs do not add up to its size is a placeholder, never decoded (``catalog/rows.mask_rle``).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import stat
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from mining.catalog.rows import MAX_MASK_PIXELS, BadMask, decode_mask, mask_rle
from mining.config import JobConfig
from mining.draw import CALL_COLOURS, PREDICTED_COLOUR, draw_mask
from mining.errors import ConfigError, MiningError
from mining.view.filters import TooLarge

RENDER_VERSION = 2  # bump when drawing changes: every cached file name changes with it (2: draw.FILL_ALPHA)
THUMB_SIZE = (240, 180)  # ours: gallery thumbnail width × height (4:3)
THUMB_CONTEXT = 0.75  # ours: context on each side of the box, as a fraction of the box's larger side
THUMB_MIN_CONTEXT = 0.1  # ours: where the image is too small for that, at least this much beside the box
THUMB_MIN_CROP_PX = 96  # ours: the crop is at least this tall, so a 30 px box still shows its surroundings
STRIP_WIDTH = 200  # ours: width of a frame in the tube page's strip
BORDER_PX = 2  # ours: a box this close to the image edge counts as cut by it
JPEG_QUALITY = 85  # ours
MEMORY_CACHE_BYTES = 64 << 20  # ours: encoded pictures kept in memory
FRAME_CACHE = 24  # ours: decoded source frames kept in memory (neighbouring tubes share frames)
SIZES = ("full", "strip")
MAX_PICTURE_PIXELS = MAX_MASK_PIXELS  # an 8K UHD frame (catalog/rows.py): a larger mask is refused, 413
PLACEHOLDER_MAX_SIDE = 2048  # ours: a placeholder keeps the frame's shape, not its size
MAX_CACHED_FILE_BYTES = 16 << 20  # ours: a cache file larger than this is not read (ours are ~20-300 KB)
KEY_FILE = "key"
KEY_BYTES = 32
TAG_MARK = b"tube-miner-view\0"  # starts the JPEG comment that carries a cache file's HMAC
COM = b"\xff\xfe"  # JPEG comment marker
JPEG_MAGIC = b"\xff\xd8\xff"


def default_cache_dir() -> Path:
    """``tube-miner/view`` in the user's cache folder (``$XDG_CACHE_HOME``, else ``~/.cache``):
    a folder of the user's own, not a shared one such as /tmp where another user could
    have made it first. Without a home folder, ``tube-miner-view-<uid>`` in the system
    temporary folder (ImageCache still refuses it when it is not the user's alone)."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):  # the XDG rule: a relative value is ignored
        try:
            base = str(Path.home() / ".cache")
        except RuntimeError:
            return Path(tempfile.gettempdir()) / f"tube-miner-view-{os.getuid()}"
    return Path(base) / "tube-miner" / "view"


class Unavailable(Exception):
    """The frame cannot be read here; ``str()`` says why, for the placeholder."""


class FrameSource:
    """Left images of the catalogue's source, opened lazily; remembers why it cannot open."""

    def __init__(self, job: JobConfig | None, unavailable: str | None = None):
        self.config = None if job is None else job.source
        spec = {} if self.config is None else {"dataset": self.config.dataset, "root": self.config.root,
                                               "options": self.config.options}
        self.identity = json.dumps({k: spec.get(k) for k in ("dataset", "root", "options")}, sort_keys=True,
                                   default=str)
        self._source = None
        self._reason: str | None = unavailable
        if self._reason is None and self.config is None:
            self._reason = "the catalogue has no job.json naming its source, so its frames cannot be found"
        self._plans: dict[str, object] = {}
        self._plan_errors: dict[str, str] = {}
        self._frames: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()  # sources are not promised to be thread-safe

    def _open(self):
        if self._source is None and self._reason is None:
            try:
                self._source = self.config.open()
            except (MiningError, ConfigError, OSError) as e:
                self._reason = f"the frames are not on this machine ({e})"
        if self._source is None:
            raise Unavailable(self._reason)
        return self._source

    @property
    def reason(self) -> str | None:
        """Why no frame can be read (None when the source opens)."""
        with self._lock:
            try:
                self._open()
            except Unavailable:
                pass
            return self._reason

    def left(self, dataset: str, sequence: str, frame: int) -> np.ndarray:
        """The (H, W, 3) RGB left image of ``frame``; Unavailable with the reason otherwise."""
        with self._lock:
            key = (sequence, frame)
            if key in self._frames:
                self._frames.move_to_end(key)
                return self._frames[key]
            source = self._open()
            if dataset != self.config.dataset:
                raise Unavailable(f"the job's source is {self.config.dataset!r}, not {dataset!r}")
            if sequence in self._plan_errors:
                raise Unavailable(self._plan_errors[sequence])
            if sequence not in self._plans:
                try:
                    plan = source.plan(sequence)
                    self._plans[sequence] = (plan, {f: p for p, f in enumerate(plan.frames)})
                except (MiningError, OSError) as e:
                    self._plan_errors[sequence] = f"sequence {sequence} cannot be read here ({e})"
                    raise Unavailable(self._plan_errors[sequence]) from None
            plan, position = self._plans[sequence]
            if frame not in position:
                raise Unavailable(f"frame {frame} is not in the source's sequence {sequence}")
            try:
                image = source.read_frame(plan, position[frame]).left
            except (MiningError, OSError) as e:
                raise Unavailable(f"frame {frame} cannot be read ({e})") from None
            self._frames[key] = image
            while len(self._frames) > FRAME_CACHE:
                self._frames.popitem(last=False)
            return image


class CacheRefused(Exception):
    """The cache folder is not safe to use; ``str()`` says why."""


def _owned_folder(folder: Path) -> None:
    """Make ``folder`` (0700) or check a pre-existing one: the user's, and nobody else may write in it."""
    try:
        folder.mkdir(parents=True, mode=0o700)
    except FileExistsError:
        pass
    st = os.stat(folder)
    if not stat.S_ISDIR(st.st_mode):
        raise CacheRefused("it is not a folder")
    if st.st_uid != os.getuid():
        raise CacheRefused(f"it belongs to uid {st.st_uid}, not to you (uid {os.getuid()})")
    if st.st_mode & 0o022:
        raise CacheRefused(f"others may write in it (mode {stat.S_IMODE(st.st_mode):04o}); "
                           "chmod go-w it or choose another --cache")


def _secret_key(path: Path) -> bytes:
    """The folder's HMAC key: read (it must be the user's alone, 0600) or made once, atomically."""
    nofollow = getattr(os, "O_NOFOLLOW", 0)
    for _ in range(3):
        try:
            fd = os.open(path, os.O_RDONLY | nofollow)
        except FileNotFoundError:
            # Written to a private temporary file, then linked into place: a reader never sees half a key,
            # and of two viewers starting at once the second finds the first's key.
            key = secrets.token_bytes(KEY_BYTES)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | nofollow, 0o600)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(key)
                os.link(tmp, path)
                return key
            except FileExistsError:
                continue
            finally:
                tmp.unlink(missing_ok=True)
        with os.fdopen(fd, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
                raise CacheRefused(f"its key file {path} is not yours alone (mode {stat.S_IMODE(st.st_mode):04o}, "
                                   f"uid {st.st_uid})")
            key = f.read(KEY_BYTES + 1)
        if len(key) != KEY_BYTES:
            raise CacheRefused(f"its key file {path} is not {KEY_BYTES} bytes; delete it")
        return key
    raise CacheRefused(f"its key file {path} keeps changing")


class ImageCache:
    """Encoded pictures by name: an LRU in memory over files in ``folder`` (None: memory only).

    ``name(material)`` is the keyed hash of what a picture depends on; ``put`` returns the
    bytes to serve (the JPEG with its HMAC comment), which ``get`` gives back only when the
    HMAC checks out."""

    def __init__(self, folder: Path | None, memory_bytes: int = MEMORY_CACHE_BYTES):
        self.folder: Path | None = None
        self.memory_bytes = memory_bytes
        self._mem: OrderedDict[str, bytes] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()
        self.problem: str | None = None
        self._key = secrets.token_bytes(KEY_BYTES)  # memory only: a key of this process alone
        if folder is not None:
            try:
                _owned_folder(folder)
                self._key = _secret_key(folder / KEY_FILE)
                self.folder = folder
            except (CacheRefused, OSError) as e:  # pictures are still drawn, only not kept across restarts
                self.problem = f"cannot use {folder} as the picture cache ({e}): memory only"

    def name(self, material: bytes) -> str:
        """The file name (64 hex digits) of the picture that ``material`` describes."""
        return hmac.new(self._key, material, hashlib.sha256).hexdigest()

    def _path(self, name: str) -> Path:
        assert len(name) == 64 and all(c in "0123456789abcdef" for c in name)  # a hex digest only
        return self.folder / name[:2] / f"{name}.jpg"

    def _tag(self, name: str, jpeg: bytes) -> bytes:
        return hmac.new(self._key, name.encode() + b"\0" + jpeg, hashlib.sha256).digest()

    def _sealed(self, name: str, jpeg: bytes) -> bytes:
        """``jpeg`` with a comment segment right after its start marker holding the HMAC."""
        body = TAG_MARK + self._tag(name, jpeg)
        return jpeg[:2] + COM + (2 + len(body)).to_bytes(2, "big") + body + jpeg[2:]

    def _genuine(self, name: str, data: bytes) -> bool:
        """Whether ``data`` is a picture this cache sealed under ``name``."""
        head = 2 + 4 + len(TAG_MARK)  # start marker, comment marker and length, mark
        end = head + hashlib.sha256().digest_size
        if len(data) < end or data[2:4] != COM or data[6:head] != TAG_MARK:
            return False
        jpeg = data[:2] + data[end:]
        return jpeg.startswith(JPEG_MAGIC) and hmac.compare_digest(data[head:end], self._tag(name, jpeg))

    def get(self, name: str) -> bytes | None:
        with self._lock:
            if name in self._mem:
                self._mem.move_to_end(name)
                return self._mem[name]
        if self.folder is None:
            return None
        try:
            fd = os.open(self._path(name), os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
            with os.fdopen(fd, "rb") as f:
                st = os.fstat(f.fileno())
                if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_CACHED_FILE_BYTES:
                    return None
                data = f.read(MAX_CACHED_FILE_BYTES + 1)
        except OSError:
            return None
        if not self._genuine(name, data):
            return None  # not ours (planted, damaged, another key's): drawn again and replaced
        self._remember(name, data)
        return data

    def _remember(self, name: str, data: bytes) -> None:
        with self._lock:
            if name not in self._mem:
                self._mem[name] = data
                self._size += len(data)
            while self._size > self.memory_bytes and self._mem:
                _, old = self._mem.popitem(last=False)
                self._size -= len(old)

    def put(self, name: str, jpeg: bytes) -> bytes:
        """Keep ``jpeg`` under ``name``; returns the sealed bytes to serve."""
        data = self._sealed(name, jpeg)
        self._remember(name, data)
        if self.folder is None:
            return data
        path = self._path(name)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            path.parent.mkdir(mode=0o700, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except OSError:
            tmp.unlink(missing_ok=True)  # a full or read-only cache folder costs speed, not pictures
        return data


def check_size(tube: dict, frame: dict) -> None:
    """TooLarge when ``frame``'s mask (the size of the picture drawn from it) is over MAX_PICTURE_PIXELS."""
    h, w = frame["rle_h"], frame["rle_w"]
    if isinstance(h, int) and isinstance(w, int) and h * w > MAX_PICTURE_PIXELS:
        raise TooLarge(f"frame {frame['frame']} of tube {tube['tube_id']!r} has a {w}x{h} mask "
                       f"({h * w / 1e6:.0f} MP); a picture may have at most {MAX_PICTURE_PIXELS / 1e6:.1f} MP")


def best_frame(frames: list[dict], width: int | None = None, height: int | None = None) -> dict:
    """The tube frame a thumbnail shows: the largest observed box not cut by the image border,
    else the largest observed box, else the middle frame."""
    observed = [f for f in frames if f["observed"]]
    if not observed:
        return frames[len(frames) // 2]

    def area(f: dict) -> float:
        x1, y1, x2, y2 = f["bbox"]
        return max(0.0, x2 - x1) * max(0.0, y2 - y1)

    def inside(f: dict) -> bool:
        w, h = width or f["rle_w"], height or f["rle_h"]
        x1, y1, x2, y2 = f["bbox"]
        return x1 > BORDER_PX and y1 > BORDER_PX and x2 < w - BORDER_PX and y2 < h - BORDER_PX

    whole = [f for f in observed if inside(f)]
    return max(whole or observed, key=area)


def thumb_crop(bbox, width: int, height: int) -> tuple[int, int, int, int]:
    """[x0, x1) × [y0, y1): a 4:3 window centred on the box with context, shifted inside the image."""
    x1, y1, x2, y2 = (float(v) for v in bbox)
    side = max(x2 - x1, y2 - y1, 1.0)
    ch = max(side * (1 + 2 * THUMB_CONTEXT), THUMB_MIN_CROP_PX)
    cw = max(ch * THUMB_SIZE[0] / THUMB_SIZE[1], (x2 - x1) * (1 + 2 * THUMB_CONTEXT))
    ch = max(ch, cw * THUMB_SIZE[1] / THUMB_SIZE[0])
    cw, ch = min(cw, float(width)), min(ch, float(height))
    # Cut to the image's height, the window gives up side context before it gives up 4:3.
    cw = min(cw, max(ch * THUMB_SIZE[0] / THUMB_SIZE[1], min(float(width), (x2 - x1) * (1 + 2 * THUMB_MIN_CONTEXT))))
    cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
    x0 = round(min(max(cx - cw / 2, 0.0), width - cw))
    y0 = round(min(max(cy - ch / 2, 0.0), height - ch))
    return x0, min(width, x0 + round(cw)), y0, min(height, y0 + round(ch))


def _jpeg(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def placeholder(reason: str, size: tuple[int, int] = THUMB_SIZE) -> bytes:
    """A grey JPEG of ``size`` saying ``reason`` (ASCII; wrapped to the width)."""
    w, h = size
    img = np.full((h, w, 3), 60, np.uint8)
    scale = 0.4 if w < 400 else 0.6
    text = reason.encode("ascii", "replace").decode()
    max_chars = max(10, int(w / (scale * 20)))
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > max_chars:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    lines.append(line)
    step = int(28 * scale) + 4
    for k, ln in enumerate(lines[: max(1, (h - 10) // step)]):
        cv2.putText(img, ln, (6, 6 + step * (k + 1)), cv2.FONT_HERSHEY_SIMPLEX, scale, (230, 230, 230), 1, cv2.LINE_AA)
    return _jpeg(img)


class TubeImages:
    """Thumbnails and frames of tubes; (JPEG bytes, reason) where reason names a placeholder's cause."""

    def __init__(self, source: FrameSource, cache: ImageCache):
        self.source = source
        self.cache = cache

    def _name(self, kind: str, size: str, tube: dict, frame: dict) -> str:
        material = json.dumps([RENDER_VERSION, kind, size, self.source.identity, tube["dataset"], tube["sequence"],
                               frame["frame"], frame["rle_h"], frame["rle_w"], frame["rle_counts"],
                               [round(float(v), 3) for v in frame["bbox"]], tube["call"], frame["observed"]])
        return self.cache.name(material.encode())

    def _image_and_mask(self, tube: dict, frame: dict) -> tuple[np.ndarray, np.ndarray]:
        try:
            mask_rle(frame)  # first: a malformed row costs no image read
            image = self.source.left(tube["dataset"], tube["sequence"], frame["frame"])
            h, w = image.shape[:2]
            return image, decode_mask(frame, (h, w))
        except BadMask as e:
            if e.mismatch:
                raise Unavailable(f"the mask is {frame['rle_w']}x{frame['rle_h']} but frame {frame['frame']} of the "
                                  f"source is {w}x{h}: the job's source is not the one this catalogue was mined "
                                  "from") from None
            raise Unavailable(f"the catalogue's mask of frame {frame['frame']} is malformed ({e.problem})") from None

    def _cached(self, kind: str, size: str, tube: dict, frame: dict, draw) -> tuple[bytes, str | None]:
        check_size(tube, frame)  # before the cache, the image and any allocation
        name = self._name(kind, size, tube, frame)
        data = self.cache.get(name)
        if data is not None:
            return data, None
        try:
            image, mask = self._image_and_mask(tube, frame)
        except Unavailable as e:
            return None, str(e)
        return self.cache.put(name, _jpeg(draw(image, mask))), None

    def thumbnail(self, tube: dict, frame: dict) -> tuple[bytes, str | None]:
        """The gallery picture of ``tube`` on ``frame`` (best_frame's choice); TooLarge over the limit."""
        colour = CALL_COLOURS[tube["call"]]

        def draw(image, mask):
            h, w = image.shape[:2]
            x0, x1, y0, y1 = thumb_crop(frame["bbox"], w, h)
            crop, m = image[y0:y1, x0:x1], mask[y0:y1, x0:x1]
            s = min(THUMB_SIZE[0] / crop.shape[1], THUMB_SIZE[1] / crop.shape[0])
            cw, chh = max(1, round(crop.shape[1] * s)), max(1, round(crop.shape[0] * s))
            crop = cv2.resize(crop, (cw, chh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
            m = cv2.resize(m, (cw, chh), interpolation=cv2.INTER_NEAREST)
            canvas = np.full((THUMB_SIZE[1], THUMB_SIZE[0], 3), 30, np.uint8)
            ox, oy = (THUMB_SIZE[0] - cw) // 2, (THUMB_SIZE[1] - chh) // 2
            canvas[oy:oy + chh, ox:ox + cw] = draw_mask(crop, m, colour, fill=False)
            return canvas

        data, reason = self._cached("thumb", "thumb", tube, frame, draw)
        return (data, None) if reason is None else (placeholder(reason, THUMB_SIZE), reason)

    def frame(self, tube: dict, frame: dict, size: str) -> tuple[bytes, str | None]:
        """Frame ``frame`` of ``tube`` with its mask, at ``size`` (one of SIZES); TooLarge over the limit."""
        if size not in SIZES:
            raise ValueError(f"size is one of {SIZES}, got {size!r}")
        colour = CALL_COLOURS[tube["call"]] if frame["observed"] else PREDICTED_COLOUR

        def draw(image, mask):
            if size == "strip":
                h, w = image.shape[:2]
                new = (STRIP_WIDTH, max(1, round(h * STRIP_WIDTH / w)))
                image = cv2.resize(image, new, interpolation=cv2.INTER_AREA)
                mask = cv2.resize(mask, new, interpolation=cv2.INTER_NEAREST)
            return draw_mask(image, mask, colour, fill=True)

        data, reason = self._cached("frame", size, tube, frame, draw)
        if reason is None:
            return data, None
        w, h = max(1, int(frame["rle_w"] or 1)), max(1, int(frame["rle_h"] or 1))
        scale = STRIP_WIDTH / w if size == "strip" else min(1.0, PLACEHOLDER_MAX_SIDE / max(w, h))
        w, h = min(round(w * scale), PLACEHOLDER_MAX_SIDE), min(round(h * scale), PLACEHOLDER_MAX_SIDE)
        return placeholder(reason, (max(w, 120), max(h, 60))), reason
