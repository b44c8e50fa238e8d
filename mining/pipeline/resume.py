"""What earlier runs of a job left in its catalogue: ``read_resume`` → ``Resume``, for the schedule.

Read from the records (``catalog/records.py``) and checked against what is there
(``catalog/integrity.py``): a window is done when its manifest row says so with these params
and this window's core and context (``ManifestRow.says_done``) and its parts are all there as
its files record lists them; a sequence is finalized when its marker is of this job
(``SequenceMarker.of_job``), its compacted files are all there as the marker records them,
and no failed-stitch row of it is unreadable. Anything else is recomputed: a record that does
not read vouches for nothing, a window with a damaged part runs again, a sequence with a
damaged compacted file (or record) is stitched again. ``mine status`` reads the same records
with the same predicates (``status.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from mining.catalog.integrity import marker_damage, window_damage
from mining.catalog.layout import STITCH_ROW
from mining.catalog.records import ManifestRow, SequenceMarker, Unreadable
from mining.catalog.store import Store
from mining.types import Window


@dataclass(frozen=True)
class Resume:
    """What earlier runs of the job left in its catalogue."""

    done: Mapping[str, bool] = field(default_factory=dict)  # window done → was its context complete then
    finalized: Mapping[str, frozenset[str]] = field(default_factory=dict)  # sequence → windows its catalogue holds


def read_resume(store: Store, dataset: str, windows: list[Window], params_hash: str, verify: bool = False) -> Resume:
    """The windows of ``windows`` that are done and vouched for (sizes of their parts; checksums
    too with ``verify``), each with whether its context was complete when it was tracked; and
    the sequences finalized with these params whose compacted files are all there as recorded
    (the windows each holds)."""
    done = {}
    for w in windows:
        row = ManifestRow.load(store, w.dataset, w.sequence, w.name)
        if isinstance(row, ManifestRow) and row.says_done(params_hash, w) and not window_damage(store, w, verify):
            done[w.name] = row.context_complete is not False
    finalized = {}
    contexts = {w.name: tuple(w.context) for w in windows}
    for seq in dict.fromkeys(w.sequence for w in windows):
        marker = SequenceMarker.load(store, dataset, seq)
        if (isinstance(marker, SequenceMarker) and marker.of_job(params_hash, contexts)
                and not isinstance(ManifestRow.load(store, dataset, seq, STITCH_ROW), Unreadable)
                and not marker_damage(store, marker, verify)):
            finalized[seq] = frozenset(marker.windows)
    return Resume(done, finalized)
