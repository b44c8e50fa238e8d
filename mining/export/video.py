"""Video files for `mine render`: the writers, their codecs, and the read-back check.

Container and codec: ``.mp4`` is H.264 (yuv420p, the index at the front so a browser starts
playing before the whole file has arrived), which OpenCV, ffmpeg, VLC and every browser play.
OpenCV's wheel (opencv-python-headless) carries no H.264 encoder, so it is written with PyAV
(the ``video`` extra: ``pip install 'tube-miner[video]'``; its wheel bundles FFmpeg with
libx264, GPL-licensed). Without PyAV, an OpenCV build with H.264 (``avc1``) is used, else
MPEG-4 Part 2 (``mp4v``), which OpenCV, ffmpeg and VLC play but browsers do not, and the
command says so (``codec_note``). ``.webm`` is VP8 (OpenCV), which OpenCV and browsers
(Chromium, Firefox) play. A written file is read back with ``cv2.VideoCapture`` (frame count
and size) before it counts as written (``check_video``).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from mining.errors import InputError, MiningError

H264_CRF = 18  # ours: x264's constant rate factor (0 lossless … 51); 18 is visually lossless, so masks read true
H264_PRESET = "veryfast"  # ours: x264's speed / size trade-off; encoding stays a small part of a render's time
# Codecs by container, tried in order: the first this machine can write is used.
CODECS = {".mp4": ("h264", "avc1", "mp4v"), ".webm": ("VP80",)}
BROWSER_CODECS = {"h264", "avc1", "VP80"}


def check_container(dest: Path) -> None:
    """Refuse a file name whose container (its suffix) is not one of ``CODECS``'."""
    if dest.suffix.lower() not in CODECS:
        raise InputError(f"the video must end in {' or '.join(CODECS)} (MP4: H.264, with PyAV; WebM: VP8; "
                         "both play in browsers)", dest)


def codec_note(codec: str) -> str:
    """What a user should know of a video written with ``codec``: nothing for one browsers play."""
    if codec in BROWSER_CODECS:
        return ""
    return (" — MPEG-4 Part 2: OpenCV, ffmpeg and VLC play it, browsers do not; for H.264 install PyAV "
            "(pip install 'tube-miner[video]'), or write a .webm")


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
    check_container(dest)
    ext = dest.suffix.lower()
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
