"""The source frames of an export's videos, re-read through the job's source (``--images``):
``read_frames`` and the frame rate and even-sided size a 4:2:0 video of them has (what the
FiftyOne and Rerun exports share), and ``write_images``, the frames as JPEG files (YouTube-VIS,
TAO, BURST)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from mining.config import JobConfig
from mining.errors import InputError
from mining.export.selection import Video, job_source
from mining.names import inside
from mining.progress import Ticker
from mining.types import SequencePlan, StereoFrame

DEFAULT_FPS = 10.0  # ours: frame rate when the timestamps give none (KITTI records at 10 Hz), as `mine render`
JPEG_QUALITY = 95  # ours: --images JPEG quality


def frame_rate(t_ns: dict[int, int]) -> float:
    """Frames per second of a sequence from the times of some of its frames (frame → ns):
    the median time per frame step over consecutive known frames; DEFAULT_FPS without two."""
    frames = sorted(t_ns)
    steps = [(t_ns[b] - t_ns[a]) / (b - a) for a, b in zip(frames, frames[1:]) if t_ns[b] > t_ns[a]]
    return float(1e9 / np.median(steps)) if steps else DEFAULT_FPS


def even_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) with even sides: 4:2:0 video (H.264's yuv420p) needs them, so an odd
    side gets one black row or column (KITTI's 375 rows → 376), as `mine render` does."""
    return width + width % 2, height + height % 2


def pad_even(image: np.ndarray) -> np.ndarray:
    """``image`` with a black row / column added where a side is odd (``even_size``)."""
    h, w = image.shape[:2]
    pw, ph = even_size(w, h)
    if (pw, ph) == (w, h):
        return image
    out = np.zeros((ph, pw, *image.shape[2:]), image.dtype)
    out[:h, :w] = image
    return out


def read_frames(job: JobConfig | None, sequence: str, frames: list[int], size: tuple[int, int],
                what: str) -> tuple[SequencePlan, Iterator[StereoFrame]]:
    """(the plan, the rectified stereo pairs of ``frames`` in that order) re-read through the
    job's source; an InputError naming the source's root and frame for a frame the source
    lacks or an image of another (height, width) than ``size``, the masks'."""
    source = job_source(job, what)
    root = job.source.root
    survey = source.survey(sequence)
    position = {f: p for p, f in enumerate(survey.frames)}
    missing = [f for f in frames if f not in position]
    if missing:
        raise InputError(f"frame {missing[0]} of the catalogue is not in the source's sequence {sequence!r}",
                         root, missing[0])
    # only the exported frames need to read (problems elsewhere in the sequence do not matter)
    plan = source.plan(sequence, min(position[f] for f in frames), max(position[f] for f in frames) + 1)

    def pairs() -> Iterator[StereoFrame]:
        for frame in frames:
            pair = source.read_frame(plan, position[frame])
            if pair.left.shape[:2] != tuple(size):
                raise InputError(f"image of {pair.left.shape[1]}×{pair.left.shape[0]}, masks of {size[1]}×{size[0]}",
                                 root, frame)
            yield pair
    return plan, pairs()


def ticking(label: str) -> Callable[[int, int], None]:
    """A ``write_images`` progress hook on a ``Ticker`` made at the first call (the total known then)."""
    state: dict = {}

    def hook(done: int, total: int) -> None:
        t = state.setdefault("t", Ticker(label, total))
        t.tick(done)
        if done >= total:
            t.close()
    return hook


def write_images(job: JobConfig | None, vids: list[Video], folder: Path,
                 progress: Callable[[int, int], None] | None = None,
                 path_of: Callable[[Video, int], str] = Video.file_name) -> int:
    """The rectified left frame of every video frame as ``folder/<path_of(video, frame)>``
    (``<file_name>`` by default); the count."""
    source = job_source(job, "--images")
    root = job.source.root
    total, done = sum(len(v.frames) for v in vids), 0
    for v in vids:
        survey = source.survey(v.sequence)
        position = {f: p for p, f in enumerate(survey.frames)}
        missing = [f for f in v.frames if f not in position]
        if missing:
            raise InputError(f"frame {missing[0]} of the catalogue is not in the source's sequence {v.sequence!r}",
                             root, missing[0])
        # only the video's frames need to read (problems elsewhere in the sequence do not matter)
        plan = source.plan(v.sequence, min(position[f] for f in v.frames), max(position[f] for f in v.frames) + 1)
        for frame in v.frames:
            image = source.read_frame(plan, position[frame]).left
            if image.shape[:2] != (v.height, v.width):
                raise InputError(f"image of {image.shape[1]}×{image.shape[0]}, masks of {v.width}×{v.height}",
                                 root, frame)
            path = inside(folder, path_of(v, frame))
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                raise InputError("cannot write JPEG", path)
            done += 1
            if progress is not None:
                progress(done, total)
    return done
