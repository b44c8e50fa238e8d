"""The interface every source adapter implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator

from mining.types import SequencePlan, StereoFrame


class Source(ABC):
    """A dataset on disk (or generated) that yields rectified stereo frames.

    ``plan`` reads timestamps and calibration only, never image data. ``read`` decodes
    the frames at plan positions ``[start, stop)`` lazily, one at a time.
    """

    dataset: str = ""

    @abstractmethod
    def sequences(self) -> list[str]:
        """Names of the sequences available under the root."""

    @abstractmethod
    def plan(self, sequence: str) -> SequencePlan:
        """Frame indices, timestamps and calibration of a sequence, without decoding images."""

    @abstractmethod
    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        """Decode the frame at ``position`` in ``plan.frames``."""

    def read(self, sequence: str | SequencePlan, start: int = 0, stop: int | None = None) -> Iterator[StereoFrame]:
        """Frames at plan positions ``[start, stop)``, decoded one at a time."""
        plan = sequence if isinstance(sequence, SequencePlan) else self.plan(sequence)
        stop = len(plan) if stop is None else min(stop, len(plan))
        for pos in range(max(0, start), stop):
            yield self.read_frame(plan, pos)
