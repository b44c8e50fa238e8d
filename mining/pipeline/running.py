"""Running windows: the marker a driver leaves while a window's work is under way.

``mine status`` must tell a window being worked on from one nobody has started. The
manifest row is written only when a window ends, so the driver writes a marker
(``_running/dataset=D/sequence=S/<window>.json``, ``layout.running_path``) when it hands
the window's first step (observe) to a worker, refreshes it when it hands over the track
step, and removes it when the track's result is in — also when the driver stops early
(an error, Ctrl-C). A marker holds the driver's host, pid, run id and params hash and
when the window and its current step started.

A window is *running* when it has a marker of this job's params whose driver is alive:
on the host ``mine status`` runs on, the driver's pid must still exist; a driver on
another host is taken as alive (``mine status`` shows where it runs and since when).
A marker whose driver is gone (killed with SIGKILL, a lost machine) is stale: the window
is *pending*, and the next ``mine submit`` runs it and sweeps such markers away.
"""

from __future__ import annotations

import json
import os
import posixpath
import socket
from datetime import datetime, timezone

from mining.catalog.layout import RUNNING, running_path
from mining.catalog.store import Store
from mining.errors import MiningError
from mining.types import Window


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class RunningMarkers:
    """The markers one driver writes for the windows it runs."""

    def __init__(self, store: Store, run_id: str, params_hash: str):
        self.store, self.run_id, self.params_hash = store, run_id, params_hash
        self.host, self.pid = socket.gethostname(), os.getpid()
        self.started: dict[str, tuple[Window, str]] = {}  # window name → (window, when its work started)

    def mark(self, window: Window, step: str) -> None:
        """The driver hands ``step`` of ``window`` to a worker."""
        first = self.started.setdefault(window.name, (window, _now()))[1]
        record = {"window": window.name, "step": step, "run_id": self.run_id, "params_hash": self.params_hash,
                  "driver_host": self.host, "driver_pid": self.pid, "started": first, "step_started": _now()}
        self.store.write_bytes(running_path(window.dataset, window.sequence, window.name),
                               json.dumps(record, indent=1).encode())

    def clear(self, window: Window) -> None:
        """The window's result is recorded (its manifest row written)."""
        if self.started.pop(window.name, None) is not None:
            self.store.remove(running_path(window.dataset, window.sequence, window.name))

    def sweep(self, todo: set[str]) -> None:
        """Remove markers an earlier driver left (killed before it could) for windows that
        are not to run now, or whose driver is gone: one listing of the folder."""
        for rel in self.store.list(RUNNING, suffix=".json"):
            marker = _load(self.store, rel)
            window = posixpath.basename(rel)[: -len(".json")]
            if window not in todo or marker is None or not driver_alive(marker):
                self.store.remove(rel)

    def clear_all(self) -> None:
        """The driver stops: none of its windows runs any more."""
        for w, _ in list(self.started.values()):
            self.clear(w)


def _load(store: Store, rel: str) -> dict | None:
    """A marker, or None when it is gone or does not read as one (it then says nothing)."""
    try:
        marker = json.loads(store.read_bytes(rel))
    except (ValueError, RecursionError, MiningError):  # not JSON (or nested past the parser); removed since it was listed
        return None
    return marker if isinstance(marker, dict) else None


def read_marker(store: Store, window: Window) -> dict | None:
    """The window's marker, or None (also for an unreadable one: a crash mid-write leaves none)."""
    rel = running_path(window.dataset, window.sequence, window.name)
    return _load(store, rel) if store.exists(rel) else None


def driver_alive(marker: dict) -> bool:
    """Whether the marker's driver may still run: its pid exists here, or it runs on another host."""
    if marker.get("driver_host") != socket.gethostname():
        return True
    try:
        os.kill(int(marker["driver_pid"]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, another user's
        return True
    except (KeyError, TypeError, ValueError):
        return False
    return True
