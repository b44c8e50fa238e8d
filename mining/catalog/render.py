"""`mine render`: one sequence's source frames with its selected tubes drawn, as a video.

Each frame is re-read through the source named in ``OUT/job.json`` (as the crops export
does) and every selected tube present in it is drawn: its mask filled semi-transparently
in its own colour (``tube_colours``: hues spread over the rendered tubes, fixed for a
tube through the video), the mask's outline, and a label with the short id and the category by the rule of
the ``known`` flag (a known tube's COCO class, ``unknown``, ``unclassified``). Frames where
the tube is only predicted (a gap between observations) get the outline and label without
the fill.

``--depth`` puts a depth panel beside each frame: the stereo depth of the job's own
geometry stage (its disparity step with the job's ``[geometry]``: ``stereo_depth``), colour-mapped with
OpenCV's turbo map on a fixed logarithmic range (near red, far blue; no depth black) with
its legend, and the tubes' outlines. The video is then twice as wide.

Container and codec: ``.mp4`` is H.264 (yuv420p, the index at the front so a browser starts
playing before the whole file has arrived), which OpenCV, ffmpeg, VLC and every browser play.
OpenCV's wheel (opencv-python-headless) carries no H.264 encoder, so it is written with PyAV
(the ``video`` extra: ``pip install 'tube-miner[video]'``; its wheel bundles FFmpeg with
libx264, GPL-licensed). Without PyAV, an OpenCV build with H.264 (``avc1``) is used, else
MPEG-4 Part 2 (``mp4v``), which OpenCV, ffmpeg and VLC play but browsers do not, and the
command says so. ``.webm`` is VP8 (OpenCV), which OpenCV and browsers (Chromium, Firefox)
play. The written file is read back with ``cv2.VideoCapture`` (frame count and size)
before the command reports success.

DEST, as for ``mine export``: an existing DEST is replaced only with ``--overwrite``, and
only when it is a plain file (a link or a folder there is refused, whatever the flag). The
video is written in a private folder beside DEST (``.<DEST name>.partial-<random>``, made
by ``mkdir`` under an unpredictable name, so no link can be planted where the encoder
writes), read back, then moved onto DEST (``safe_files.publish_file``: without
``--overwrite`` the name is claimed atomically, never replaced). A failed render leaves
DEST as it was.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import cv2
import duckdb
import numpy as np
from pycocotools import mask as mask_utils

from mining.catalog import safe_files
from mining.catalog.export import category_label, job_source, read_job, selected_rows
from mining.catalog.store import Store
from mining.catalog.views import connect, sql_string
from mining.errors import InputError, MiningError, NothingMatched
from mining.names import check_name

GOLDEN_HUE_STEP = 0.618034  # ours: hue step between tubes (the golden ratio's fraction spreads any count)
FILL_ALPHA = 0.45  # ours: opacity of a tube's mask fill
OUTLINE_PX = 2  # ours: width of a mask's outline
FONT = cv2.FONT_HERSHEY_SIMPLEX
FONT_SCALE = 0.5  # ours: label text size (≈ 11 px high)
DEFAULT_FPS = 10.0  # ours: frame rate when the plan's timestamps give none (KITTI records at 10 Hz)
DEPTH_NEAR_M = 2.0  # ours: the depth colour map's near end (red); KITTI's 128 px search reaches ≈ 3 m
DEPTH_TICKS_M = (2, 5, 10, 20, 50, 90)  # ours: legend ticks (the far end is the job's geometry.stereo.max_depth_m)
H264_CRF = 18  # ours: x264's constant rate factor (0 lossless … 51); 18 is visually lossless, so masks read true
H264_PRESET = "veryfast"  # ours: x264's speed / size trade-off; encoding stays a small part of a render's time
# Codecs by container, tried in order: the first this machine can write is used.
CODECS = {".mp4": ("h264", "avc1", "mp4v"), ".webm": ("VP80",)}
BROWSER_CODECS = {"h264", "avc1", "VP80"}


def tube_colours(tube_ids: list[str]) -> dict[str, tuple[int, int, int]]:
    """A BGR colour per tube: saturated hues a golden-ratio step apart in the order of the
    sorted ids, so neighbouring tubes differ and a tube keeps its colour in every frame (and
    in every render of the same tubes, whatever the frame range)."""
    out = {}
    for k, tid in enumerate(sorted(set(tube_ids))):
        hue = round((k * GOLDEN_HUE_STEP) % 1.0 * 180) % 180
        b, g, r = cv2.cvtColor(np.array([[[hue, 220, 255]]], np.uint8), cv2.COLOR_HSV2BGR)[0, 0]
        out[tid] = (int(b), int(g), int(r))
    return out


def short_id(tube_id: str) -> str:
    """``kitti/0005/0000012.003`` → ``12.3``: the first frame and observation, without the
    sequence (a render shows one sequence) or leading zeros."""
    last = tube_id.rsplit("/", 1)[-1]
    frame, _, obs = last.partition(".")
    try:
        return f"{int(frame)}.{int(obs)}"
    except ValueError:
        return last


@dataclass
class Drawn:
    """One tube in one frame, ready to draw."""

    tube_id: str
    label: str
    colour: tuple[int, int, int]
    mask: np.ndarray  # (H, W) uint8 0/1
    bbox: tuple[float, float, float, float]  # x1, y1, x2, y2
    observed: bool


def draw_tubes(image_bgr: np.ndarray, items: list[Drawn], fill: bool = True) -> np.ndarray:
    """``image_bgr`` with each item's mask filled (observed frames, when ``fill``), outlined
    and labelled; a new image."""
    out = image_bgr.copy()
    if fill:
        for it in items:
            if it.observed:
                m = it.mask.astype(bool)
                out[m] = ((1 - FILL_ALPHA) * out[m] + FILL_ALPHA * np.array(it.colour, np.float32)).astype(np.uint8)
    for it in items:
        contours, _ = cv2.findContours(it.mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, it.colour, OUTLINE_PX, cv2.LINE_AA)
    placed: list[tuple[int, int, int, int]] = []
    for it in items:
        _label(out, it.label if it.observed else it.label + " (predicted)", it.bbox, it.colour, placed)
    return out


def _overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _label(img: np.ndarray, text: str, bbox, colour: tuple[int, int, int],
           placed: list[tuple[int, int, int, int]] | None = None) -> None:
    """``text`` on a box of ``colour`` just above ``bbox`` (inside the image); where that box
    would cover a label already ``placed`` (x1, y1, x2, y2), the first free place stepping up,
    then down, by a label's height (labels of neighbouring tubes stay readable)."""
    (tw, th), base = cv2.getTextSize(text, FONT, FONT_SCALE, 1)
    h, w = img.shape[:2]
    x = int(np.clip(bbox[0], 0, max(0, w - tw - 4)))
    y = int(bbox[1]) - 3
    if y - th - base < 0:
        y = min(h - base - 1, int(bbox[1]) + th + 3)
    step = th + base + 1

    def box(yy: int) -> tuple[int, int, int, int]:
        return x, yy - th - base, x + tw + 4, yy + base - 1

    if placed is not None:
        tries = [y] + [y + k * d * step for k in range(1, 8) for d in (-1, 1)]
        tries = [t for t in tries if t - th - base >= 0 and t + base - 1 < h]
        y = next((t for t in tries if not any(_overlaps(box(t), b) for b in placed)), y)
        placed.append(box(y))
    x1, y1, x2, y2 = box(y)
    cv2.rectangle(img, (x1, y1), (x2, y2), colour, cv2.FILLED)
    ink = (0, 0, 0) if sum(colour) > 382 else (255, 255, 255)
    cv2.putText(img, text, (x + 2, y - 1), FONT, FONT_SCALE, ink, 1, cv2.LINE_AA)


def _caption(img: np.ndarray, text: str) -> None:
    (tw, th), base = cv2.getTextSize(text, FONT, FONT_SCALE, 1)
    cv2.rectangle(img, (0, 0), (tw + 8, th + base + 6), (0, 0, 0), cv2.FILLED)
    cv2.putText(img, text, (4, th + 3), FONT, FONT_SCALE, (255, 255, 255), 1, cv2.LINE_AA)


def depth_colours(depth_m: np.ndarray, far_m: float) -> np.ndarray:
    """(H, W, 3) BGR turbo colours of depth on the fixed log range [DEPTH_NEAR_M, far_m]:
    near red, far blue, no depth (NaN) black."""
    valid = np.isfinite(depth_m)
    z = np.clip(np.where(valid, depth_m, far_m), DEPTH_NEAR_M, far_m)
    t = (np.log(z) - np.log(DEPTH_NEAR_M)) / (np.log(far_m) - np.log(DEPTH_NEAR_M))
    out = cv2.applyColorMap(np.round((1.0 - t) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    out[~valid] = 0
    return out


def stereo_depth(matcher, frame, far_m: float) -> np.ndarray:
    """The geometry stage's depth of ``frame`` (``GeometryStage.run``'s disparity step: SGBM
    with the job's settings, NaN where invalid or beyond ``far_m``), without its flow,
    egomotion and ground steps, which the panel does not show (they would double its cost)."""
    depth = frame.calib.depth_from_disparity(matcher.compute(frame.left, frame.right))
    depth[depth > far_m] = np.nan
    return depth


def _depth_legend(img: np.ndarray, far_m: float) -> None:
    """The colour bar of ``depth_colours`` with its ticks, in the panel's bottom-left corner."""
    h, w = img.shape[:2]
    bar_w, bar_h, pad = min(300, w - 40), 12, 6
    x0, y0 = 10, h - bar_h - 34
    cv2.rectangle(img, (x0 - pad, y0 - 22), (x0 + bar_w + pad + 24, h - 4), (0, 0, 0), cv2.FILLED)
    z = np.exp(np.linspace(np.log(DEPTH_NEAR_M), np.log(far_m), bar_w, dtype=np.float32))
    img[y0:y0 + bar_h, x0:x0 + bar_w] = depth_colours(np.tile(z, (bar_h, 1)), far_m)
    cv2.putText(img, "depth (m), stereo", (x0, y0 - 7), FONT, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    span = np.log(far_m) - np.log(DEPTH_NEAR_M)
    for tick in (t for t in DEPTH_TICKS_M if DEPTH_NEAR_M <= t <= far_m):
        x = x0 + int(round((np.log(tick) - np.log(DEPTH_NEAR_M)) / span * (bar_w - 1)))
        cv2.line(img, (x, y0 + bar_h), (x, y0 + bar_h + 3), (255, 255, 255), 1)
        (tw, _), _ = cv2.getTextSize(str(tick), FONT, 0.4, 1)
        cv2.putText(img, str(tick), (x - tw // 2, y0 + bar_h + 15), FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence file descriptor 2 (FFmpeg's own log) while probing an encoder that may be absent."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class VideoWriter:
    """Frames (BGR, all of one size) into a video file: ``write`` each, then ``close``."""

    codec: str

    def write(self, bgr: np.ndarray) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class OpenCVWriter(VideoWriter):
    """``cv2.VideoWriter`` with a fourcc (``avc1``, ``mp4v``, ``VP80``)."""

    def __init__(self, writer: cv2.VideoWriter, fourcc: str):
        self._writer, self.codec = writer, fourcc

    def write(self, bgr: np.ndarray) -> None:
        self._writer.write(bgr)

    def close(self) -> None:
        self._writer.release()


class H264Writer(VideoWriter):
    """H.264 in MP4 through PyAV's libx264: yuv420p (what browsers decode), ``+faststart``."""

    codec = "h264"

    def __init__(self, dest: Path, fps: float, size: tuple[int, int]):
        import av  # the `video` extra

        self._av = av
        self._container = av.open(str(dest), "w", format="mp4", options={"movflags": "+faststart"})
        self._stream = self._container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        self._stream.width, self._stream.height = size
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": str(H264_CRF), "preset": H264_PRESET}

    def write(self, bgr: np.ndarray) -> None:
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(bgr), format="bgr24")
        self._container.mux(self._stream.encode(frame))

    def close(self) -> None:
        try:
            self._container.mux(self._stream.encode(None))  # flush the encoder's delayed frames
        finally:
            self._container.close()


def _pyav_h264() -> bool:
    """PyAV is installed and its FFmpeg has libx264."""
    try:
        import av
    except ImportError:
        return False
    return "libx264" in av.codecs_available


def open_video(dest: Path, fps: float, size: tuple[int, int]) -> VideoWriter:
    """A writer for ``dest`` (``.mp4`` or ``.webm``) with the first codec of ``CODECS`` this
    machine can write."""
    ext = dest.suffix.lower()
    if ext not in CODECS:
        raise InputError(f"the video must end in {' or '.join(CODECS)} (MP4: H.264, with PyAV; WebM: VP8; "
                         "both play in browsers)", dest)
    for codec in CODECS[ext]:
        if codec == "h264":
            if _pyav_h264():
                return H264Writer(dest, fps, size)
            continue
        with _quiet_stderr():
            writer = cv2.VideoWriter(str(dest), cv2.VideoWriter_fourcc(*codec), fps, size)
        if writer.isOpened():
            return OpenCVWriter(writer, codec)
        writer.release()
    raise InputError(f"cannot write {ext} here (tried {', '.join(CODECS[ext])})", dest)


def check_video(dest: Path, n_frames: int, size: tuple[int, int]) -> None:
    """Read ``dest`` back with OpenCV: ``n_frames`` frames of ``size`` (width, height)."""
    cap = cv2.VideoCapture(str(dest))
    try:
        if not cap.isOpened():
            raise MiningError(f"the video written to {dest} does not open with OpenCV")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        ok, first = cap.read()
    finally:
        cap.release()
    if not ok or (first.shape[1], first.shape[0]) != size or count != n_frames:
        got = None if not ok else f"{count} frames of {first.shape[1]}×{first.shape[0]}"
        raise MiningError(f"the video written to {dest} reads back as {got}, not {n_frames} frames of {size[0]}×{size[1]}")


class _Progress:
    """``frames done / total`` on standard error: one updating line on a terminal, else
    a line per tenth."""

    def __init__(self, total: int, what: str):
        self.total, self.what, self.t0 = total, what, time.perf_counter()
        self.tty = sys.stderr.isatty()
        self.step = max(1, -(-total // 10))

    def update(self, done: int) -> None:
        if not self.tty and done % self.step and done != self.total:
            return
        dt = time.perf_counter() - self.t0
        rate = done / dt if dt > 0 else 0.0
        eta = (self.total - done) / rate if rate > 0 else 0.0
        line = f"{self.what}: {done}/{self.total} frames, {rate:.1f} frames/s, {eta:.0f} s left"
        sys.stderr.write(f"\r{line}  " if self.tty else line + "\n")
        if self.tty and done == self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _fps(t_ns: tuple[int, ...]) -> float:
    dt = np.diff(np.asarray(t_ns, np.int64))
    dt = dt[dt > 0]
    return float(1e9 / np.median(dt)) if dt.size else DEFAULT_FPS


@dataclass
class RenderResult:
    dest: Path
    frames: int
    tubes: int  # tubes drawn in at least one rendered frame
    width: int
    height: int
    codec: str  # h264, avc1, mp4v or VP80
    fps: float
    seconds: float


def check_dest(dest: Path, overwrite: bool) -> None:
    """Refuse a DEST this render may not write: a container other than ``CODECS``', an
    existing entry without ``overwrite``, a link or a folder at DEST."""
    if dest.suffix.lower() not in CODECS:
        raise InputError(f"the video must end in {' or '.join(CODECS)} (MP4: H.264, with PyAV; WebM: VP8; "
                         "both play in browsers)", dest)
    if dest.is_symlink():
        raise safe_files.link_error(dest)
    if dest.exists() and not dest.is_file():
        raise InputError("DEST exists and is not a file", dest)
    if dest.exists() and not overwrite:
        raise InputError("DEST exists; pass --overwrite to replace it, or choose another name", dest)


def render(out: str | Path, sequence: str, dest: str | Path, where: str | None = None, depth: bool = False,
           fps: float | None = None, frames: tuple[int, int | None] | None = None,
           progress: bool = True, overwrite: bool = False) -> RenderResult:
    """Render ``sequence`` of catalogue ``out`` with its selected tubes (those matching
    ``where`` too, when given) to ``dest``; ``frames`` are plan positions [a, b) (default:
    the positions the catalogue mined). An existing ``dest`` is replaced only with
    ``overwrite`` (module docstring)."""
    t0 = time.perf_counter()
    dest = Path(dest)
    check_dest(dest, overwrite)
    check_name(sequence, "sequence", "--sequence")
    store = Store(out)
    job = read_job(store)
    source, src = job_source(job, "render")
    dataset = src["dataset"]
    con = connect(out)
    try:
        # The selection goes through the export's predicate helper; sequence and selection
        # are checked again below whatever the predicate did.
        pred = f"selected AND dataset = {sql_string(dataset)} AND sequence = {sql_string(sequence)}"
        tubes, tube_frames = selected_rows(con, pred if where is None else f"{pred} AND ({where})")
        mined = con.execute("SELECT min(position), max(position), count(*) FROM frames "
                            "WHERE dataset = ? AND sequence = ?", [dataset, sequence]).fetchone()
        n_tubes = con.execute("SELECT count(*) FROM tubes WHERE dataset = ? AND sequence = ?",
                              [dataset, sequence]).fetchone()[0]
        if not mined[2] and not n_tubes:
            known = [r[0] for r in con.execute("SELECT DISTINCT sequence FROM tubes UNION "
                                               "SELECT DISTINCT sequence FROM frames ORDER BY 1").fetchall()]
            raise InputError(f"sequence {sequence!r} of {dataset} is not in the catalogue (sequences: "
                             f"{', '.join(known) or 'none'})", out)
    except duckdb.Error as e:
        raise InputError(f"cannot read the catalogue: {e}", out) from None
    finally:
        con.close()
    tube_rows = [t for t in tubes.to_pylist() if t["selected"] and t["sequence"] == sequence and t["dataset"] == dataset]
    keep = {t["tube_id"] for t in tube_rows}
    if not tube_rows:
        raise NothingMatched(f"no selected tube of sequence {sequence!r} matches"
                             + ("" if where is None else f" --where {where!r}") + "; nothing written")
    plan = source.survey(sequence)
    if frames is not None:
        start, stop = frames
        stop = len(plan) if stop is None else min(stop, len(plan))
    elif mined[2]:
        start, stop = int(mined[0]), min(int(mined[1]) + 1, len(plan))
    else:
        position = {f: p for p, f in enumerate(plan.frames)}
        spans = [position.get(f) for f in tube_frames.column("frame").to_pylist()]
        start, stop = min(p for p in spans if p is not None), max(p for p in spans if p is not None) + 1
    start = max(0, start)
    if stop <= start:
        raise InputError(f"--frames {start}:{stop} holds no frame of {sequence!r} (the plan has {len(plan)})")
    plan = source.plan(sequence, start, stop)  # refuses a frame in the range the source cannot read
    fps = fps or _fps(plan.t_ns[start:stop])

    colours = tube_colours(list(keep))
    info = {t["tube_id"]: (f"{short_id(t['tube_id'])} {category_label(t)}", colours[t["tube_id"]]) for t in tube_rows}
    by_frame: dict[int, list[dict]] = {}
    for f in tube_frames.to_pylist():
        if f["tube_id"] in keep:
            by_frame.setdefault(f["frame"], []).append(f)

    matcher = far = None
    if depth:
        from mining.config import section_from_dict
        from mining.geometry.config import GeometryConfig
        from mining.geometry.disparity import StereoMatcher

        geo = section_from_dict(GeometryConfig, job.get("geometry", {}), "job.json [geometry]")
        matcher, far = StereoMatcher(geo.stereo), geo.stereo.max_depth_m

    h, w = plan.calib.height, plan.calib.width
    # 4:2:0 video needs even sides: an odd one gets a black row / column (KITTI's 375 rows → 376).
    width = 2 * w if depth else w
    size = (width + width % 2, h + h % 2)
    dest.parent.mkdir(parents=True, exist_ok=True)
    work = safe_files.private_dir(dest.parent, f".{dest.name}.partial-")
    tmp = work / dest.name  # the encoders open files by path: inside a folder only this render writes
    try:
        writer = open_video(tmp, fps, size)
    except BaseException:
        safe_files.remove_tree(work)
        raise
    bar = _Progress(stop - start, f"mine render {sequence}") if progress else None
    drawn: set[str] = set()  # the tubes present in the rendered frames
    try:
        for k, pos in enumerate(range(start, stop)):
            frame = source.read_frame(plan, pos)
            if frame.left.shape[:2] != (h, w):
                raise InputError(f"image of {frame.left.shape[1]}×{frame.left.shape[0]} where the calibration says "
                                 f"{w}×{h}", src.get("root"), frame.index)
            items = []
            for f in by_frame.get(frame.index, []):
                if (f["rle_h"], f["rle_w"]) != (h, w):
                    raise InputError(f"mask size {f['rle_h']}×{f['rle_w']} of tube {f['tube_id']} differs from the "
                                     f"image's {h}×{w}", src.get("root"), frame.index)
                label, colour = info[f["tube_id"]]
                mask = mask_utils.decode({"size": [h, w], "counts": f["rle_counts"].encode()})
                items.append(Drawn(f["tube_id"], label, colour, mask, tuple(f["bbox"]), f["observed"]))
                drawn.add(f["tube_id"])
            left = draw_tubes(cv2.cvtColor(frame.left, cv2.COLOR_RGB2BGR), items)
            _caption(left, f"{dataset}/{sequence} frame {frame.index}  {len(items)} tubes")
            if matcher is not None:
                panel = draw_tubes(depth_colours(stereo_depth(matcher, frame, far), far), items, fill=False)
                _depth_legend(panel, far)
                left = np.hstack([left, panel])
            writer.write(cv2.copyMakeBorder(left, 0, size[1] - left.shape[0], 0, size[0] - left.shape[1],
                                            cv2.BORDER_CONSTANT, value=(0, 0, 0)))
            if bar is not None:
                bar.update(k + 1)
    except BaseException:
        with contextlib.suppress(Exception):
            writer.close()
        safe_files.remove_tree(work)
        raise
    try:
        try:
            writer.close()
        except Exception as e:
            raise MiningError(f"the video for {dest} did not finish writing: {e}") from None
        check_video(tmp, stop - start, size)
        safe_files.publish_file(tmp, dest, overwrite)
    finally:
        safe_files.remove_tree(work)
    return RenderResult(dest, stop - start, len(drawn), size[0], size[1], writer.codec, fps, time.perf_counter() - t0)


def run_render(out: str | Path, sequence: str, dest: str | Path, where: str | None = None, depth: bool = False,
               fps: float | None = None, frames: tuple[int, int | None] | None = None, overwrite: bool = False) -> int:
    """`mine render`: 0 on success; NothingMatched (``cli.main``: exit 1) when no tube matches; 2 with a
    message otherwise."""
    try:
        r = render(out, sequence, dest, where, depth, fps, frames, overwrite=overwrite)
    except (MiningError, duckdb.Error) as e:
        print(f"mine render: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the system's error from a writer (a full disk…): one line naming the file
        print(f"mine render: {safe_files.write_error(e, e.filename or dest)}", file=sys.stderr)
        return 2
    note = "" if r.codec in BROWSER_CODECS else (" — MPEG-4 Part 2: OpenCV, ffmpeg and VLC play it, browsers do not; "
                                                  "for H.264 install PyAV (pip install 'tube-miner[video]'), or "
                                                  "write a .webm")
    print(f"mine render: {r.frames} frames, {r.tubes} tubes, {r.width}×{r.height} {r.codec} at {r.fps:g} fps → "
          f"{r.dest} ({r.seconds:.1f} s){note}")
    return 0
