"""The interface every source adapter implements, and the calibration sanity check."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path

from mining.errors import InputError
from mining.types import SequencePlan, StereoCalib, StereoFrame


class Source(ABC):
    """A dataset on disk (or generated) that yields rectified stereo frames.

    ``plan`` reads timestamps and calibration only, never image data. ``read`` decodes
    the frames at plan positions ``[start, stop)`` lazily, one at a time.
    """

    dataset: str = ""
    # What ``sequences`` looks for under the root, for the "no sequences found" error ("" = not stated).
    layout: str = ""

    @abstractmethod
    def sequences(self) -> list[str]:
        """Names of the sequences available under the root."""

    @abstractmethod
    def survey(self, sequence: str) -> SequencePlan:
        """Frame indices, timestamps and calibration of a sequence, without decoding images;
        frames the listing shows to be unreadable are kept as ``SequencePlan.problems``."""

    def plan(self, sequence: str, start: int = 0, stop: int | None = None) -> SequencePlan:
        """``survey`` of a sequence; InputError when a frame at a position in ``[start, stop)``
        cannot be read (problems elsewhere in the sequence do not matter)."""
        plan = self.survey(sequence)
        if (problem := plan.problem_in(start, stop)) is not None:
            raise InputError(problem)
        return plan

    @abstractmethod
    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        """Decode the frame at ``position`` in ``plan.frames``."""

    def shared_state(self) -> object | None:
        """What planning learnt that would save each worker the same work (RobotCar: the
        indexes of its tar chunks), picklable; None when nothing. Workers get it through
        ``adopt_state``, and must still check it against the data (a changed file is read anew)."""
        return None

    def adopt_state(self, state: object) -> None:
        """Take ``shared_state`` from the source that planned the job."""

    def read(self, sequence: str | SequencePlan, start: int = 0, stop: int | None = None) -> Iterator[StereoFrame]:
        """Frames at plan positions ``[start, stop)``, decoded one at a time."""
        plan = sequence if isinstance(sequence, SequencePlan) else self.plan(sequence)
        stop = len(plan) if stop is None else min(stop, len(plan))
        for pos in range(max(0, start), stop):
            yield self.read_frame(plan, pos)


def check_calib(calib: StereoCalib, path: str | Path | None = None,
                fov_deg: tuple[float, float] | None = None, baseline_m: tuple[float, float] | None = None,
                aspect: tuple[float, float] | None = None) -> None:
    """InputError unless the focal lengths, the baseline and the image size are finite and
    positive and the principal point lies in the image; with ranges given, also unless the
    horizontal field of view, the baseline and fy / fx are plausible (``RunConfig``).

    A zero or NaN focal length would otherwise mine nothing (every depth is 0 or NaN) and
    end "done"; the message says which number is wrong, not a guess at why.
    """
    for name in ("fx", "fy", "baseline_m"):
        v = getattr(calib, name)
        if not (math.isfinite(v) and v > 0):
            raise InputError(f"calibration {name} = {v!r} is not a positive finite number", path)
    if not (calib.width > 0 and calib.height > 0):
        raise InputError(f"calibration image size {calib.width}×{calib.height} is not positive", path)
    if not (math.isfinite(calib.cx) and math.isfinite(calib.cy) and 0 <= calib.cx <= calib.width
            and 0 <= calib.cy <= calib.height):
        raise InputError(f"principal point ({calib.cx}, {calib.cy}) lies outside the {calib.width}×{calib.height} image",
                         path)
    if fov_deg is not None:
        fov = math.degrees(2 * math.atan(calib.width / (2 * calib.fx)))
        if not fov_deg[0] <= fov <= fov_deg[1]:
            raise InputError(f"calibration fx = {calib.fx:g} px gives a {fov:.1f}° horizontal field of view for a "
                             f"{calib.width} px wide image; plausible: {fov_deg[0]:g}–{fov_deg[1]:g}° "
                             "(run.calib_fov_deg)", path)
    if baseline_m is not None and not baseline_m[0] <= calib.baseline_m <= baseline_m[1]:
        raise InputError(f"calibration baseline {calib.baseline_m:g} m is implausible; plausible: "
                         f"{baseline_m[0]:g}–{baseline_m[1]:g} m (run.calib_baseline_m)", path)
    if aspect is not None and not aspect[0] <= calib.fy / calib.fx <= aspect[1]:
        raise InputError(f"calibration fy / fx = {calib.fy:g} / {calib.fx:g} = {calib.fy / calib.fx:.3f} is "
                         f"implausible for rectified images; plausible: {aspect[0]:g}–{aspect[1]:g} "
                         "(run.calib_aspect)", path)
