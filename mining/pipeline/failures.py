"""Why a step failed, said in its first line: the step, the exception's type, its message.

A step that raises instead of returning a failed ``StepResult`` (a bug, a library error
such as ``cv2.error``, a full disk) reaches the driver as an exception: on Ray a
``RayTaskError`` whose text is ``ray::Worker.run() (pid=…)`` and the worker's traceback
in terminal colours, or, when the worker process died and Ray's retries are spent, an
``ActorDiedError`` and the like. ``describe`` turns any of them into one headline —
``<step> step raised <type>: <message>`` or ``system failure after <n> retries: <type>:
<message>`` — followed by the end of the worker's traceback, all without colour codes.
The run summary and ``mine status`` show the headline; the manifest's ``error`` column
keeps both. ``exit_reason`` says the same of a child process: how it ended.
"""

from __future__ import annotations

import re
import signal
import sys
import traceback

ANSI = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]")  # ECMA-48 control sequences (colours, bold, cursor)
DETAIL_CHARS = 2000  # ours: how much of the traceback's end the error column keeps after the headline


def plain(text: str) -> str:
    """``text`` without terminal control sequences."""
    return ANSI.sub("", text)


def type_name(error: BaseException) -> str:
    """``ValueError``, ``InputError``; a library's with its module: ``cv2.error``, ``pyarrow.lib.ArrowInvalid``."""
    t = type(error)
    module = t.__module__
    return t.__qualname__ if module == "builtins" or module.startswith("mining.") else f"{module}.{t.__qualname__}"


def message(error: BaseException) -> str:
    """The first non-empty line of the exception's text, without colour codes."""
    lines = [ln.strip() for ln in plain(str(error)).splitlines() if ln.strip()]
    return lines[0] if lines else "(no message)"


def exit_reason(rc: int) -> str:
    """'exit status N' or 'signal SIGSEGV' for a subprocess return code."""
    if rc < 0:
        try:
            return f"signal {signal.Signals(-rc).name}"
        except ValueError:  # a signal number this platform has no name for
            return f"signal {-rc}"
    return f"exit status {rc}"


def _tail(text: str) -> str:
    # Without Python's "^^^^" position markers: the lines they point at stay.
    text = "\n".join(ln for ln in plain(text).strip().splitlines() if ln.strip(" ^~"))
    if len(text) <= DETAIL_CHARS:
        return text
    cut = text[-DETAIL_CHARS:]
    return "…" + cut[cut.find("\n"):] if "\n" in cut else "…" + cut


def _ray_errors() -> tuple[type, type] | None:
    exceptions = sys.modules.get("ray.exceptions")  # loaded whenever a Ray error can exist
    return None if exceptions is None else (exceptions.RayTaskError, exceptions.RayError)


def describe(error: BaseException, step: str, retries: int) -> str:
    """The error text of a ``step`` that raised ``error`` (after ``retries`` retries on Ray)."""
    ray = _ray_errors()
    if ray is not None and isinstance(error, ray[0]):  # the step raised, on a worker
        cause = error.cause if error.cause is not None else error
        head = f"{step} step raised {type_name(cause)}: {message(cause)}"
        # What ray.get raises is a subclass of both RayTaskError and the cause's class, whose
        # text is "ray::Worker.run() (pid=…)" and the worker's traceback (it has no traceback_str).
        detail = vars(error).get("traceback_str") or str(error)
    elif ray is not None and isinstance(error, ray[1]):  # the worker or its node died
        head = f"system failure after {retries} retries: {type(error).__name__}: {message(error)}"
        detail = str(error)
    else:  # raised in this process (LocalExecutor)
        head = f"{step} step raised {type_name(error)}: {message(error)}"
        detail = "".join(traceback.format_exception(error))
    detail = _tail(detail)
    return f"{head}\n{detail}" if detail else head
