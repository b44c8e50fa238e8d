"""The rules a setting's value must keep, written beside the field they govern.

A config dataclass field states its rules in its annotation, next to its default and the
comment that says where the default comes from::

    core: Annotated[int, Range(1)] = 100  # DESIGN.md: ...
    gate_box_iou: Fraction = 0.3  # REFERENCE: ...

``coerce(hint, value, key)`` checks a value against a field's type and rules and returns
it (ints become floats where a float is meant, lists become tuples where a tuple is);
anything else raises ConfigError naming the key, the value and the rule broken. The
config loader (``mining.config``) and the source options (``mining.sources``) use it, so
``--set window.core=-5`` or ``--option n_frames='"abc"'`` fails in the driver, before any
work starts, instead of as a traceback in every window.

Numbers are always finite (TOML can spell ``nan`` and ``inf``). A number without a
``Range`` must be ≥ 0 — nearly every setting is a count, a length, a threshold, a
variance or a weight — unless its annotation says ``SIGNED``.

The command-line options keep rules too, checked by argparse when it parses them (so before
any work): ``count``, ``real``, ``positive_float``, ``finite_float`` take ASCII decimal
numbers, finite, within a ``Range`` (``float()`` alone takes ``nan``, ``inf``, ``1e308`` and
other scripts' digits); ``input_file``, ``input_folder``, ``output_file``, ``output_folder``,
``path_text`` take a path the system can hold that prints on one line
(``names.path_problem``), an input that exists. ``pipeline/arguments.check_paths`` checks
the outputs once more after parsing (their folder, ``--overwrite``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Annotated, Any

from mining.errors import ConfigError
from mining.names import path_problem, shown

MAX_FRAMES = 10_000_000  # ours: the most frames (or the last position) an option may name: 11 days at 10 fps
MAX_WORKERS = 1024  # ours: processes or CPUs an option may ask for
MAX_SECONDS = 7 * 86400.0  # ours: the longest wait or time limit an option may set (a week)


class Rule:
    """One condition on a value; ``broken`` says how it is broken, or None."""

    numeric = False  # applies to each number (also inside lists/tuples) rather than to the value as a whole

    def broken(self, value: Any) -> str | None:  # pragma: no cover - interface
        raise NotImplementedError


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


@dataclass(frozen=True)
class Range(Rule):
    """``lo ≤ value ≤ hi`` (either end open with ``lo_open`` / ``hi_open``, or absent)."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    why: str = ""
    numeric = True

    def text(self) -> str:
        if self.lo is not None and self.hi is not None:
            return f"in {'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.hi_open else ']'}"
        if self.lo is not None:
            return f"{'>' if self.lo_open else '≥'} {_num(self.lo)}"
        return f"{'<' if self.hi_open else '≤'} {_num(self.hi)}"

    def broken(self, value: Any) -> str | None:
        ok = ((self.lo is None or (value > self.lo if self.lo_open else value >= self.lo))
              and (self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)))
        return None if ok else f"must be {self.text()}" + (f" ({self.why})" if self.why else "")


@dataclass(frozen=True)
class MultipleOf(Rule):
    n: int
    why: str = ""
    numeric = True

    def broken(self, value: Any) -> str | None:
        if value % self.n == 0:
            return None
        return f"must be a multiple of {self.n}" + (f" ({self.why})" if self.why else "")


@dataclass(frozen=True)
class Odd(Rule):
    why: str = ""
    numeric = True

    def broken(self, value: Any) -> str | None:
        return None if value % 2 == 1 else "must be odd" + (f" ({self.why})" if self.why else "")


@dataclass(frozen=True)
class OneOf(Rule):
    choices: tuple[Any, ...]

    def broken(self, value: Any) -> str | None:
        return None if value in self.choices else f"must be one of {', '.join(map(repr, self.choices))}"


@dataclass(frozen=True)
class Satisfies(Rule):
    """A rule in code: ``test(value)`` returns None when the value is fine, else what is wrong."""

    test: Callable[[Any], str | None]

    def broken(self, value: Any) -> str | None:
        return self.test(value)


@dataclass(frozen=True)
class _Signed(Rule):
    """Marker: this number may be negative (it is still finite)."""

    numeric = True

    def broken(self, value: Any) -> str | None:
        return None


SIGNED = _Signed()
NON_NEGATIVE = Range(0)  # the rule of a number without a Range of its own

# Short names for the common cases.
Count = Annotated[int, Range(1)]  # at least one
Positive = Annotated[float, Range(0, lo_open=True)]  # > 0
Fraction = Annotated[float, Range(0, 1)]  # a probability, an IoU, a share
Signed = Annotated[float, SIGNED]  # any finite number


def split_hint(hint: Any) -> tuple[Any, tuple[Rule, ...]]:
    """(the plain type, the rules) of a possibly ``Annotated`` type hint."""
    rules: tuple[Rule, ...] = ()
    while typing.get_origin(hint) is Annotated:
        rules += tuple(m for m in hint.__metadata__ if isinstance(m, Rule))
        hint = hint.__origin__
    return hint, rules


def _type_name(hint: Any) -> str:
    if hint is type(None):
        return "nothing (None)"
    if isinstance(hint, type):
        return hint.__name__
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(hint))
    if origin in (list, tuple):
        return f"a {origin.__name__}"
    return str(hint)


class _Mismatch(Exception):
    """The value is not of the type (a union tries its next member)."""


def _typed(hint: Any, value: Any, key: str, rules: tuple[Rule, ...]) -> Any:
    """``value`` as type ``hint``, with the numeric rules applied to every number in it."""
    hint, own = split_hint(hint)
    rules = rules + own
    origin = typing.get_origin(hint)
    if hint is Any or hint is object:
        return value
    if origin in (typing.Union, types.UnionType):
        for member in typing.get_args(hint):
            try:
                return _typed(member, value, key, rules)
            except _Mismatch:
                continue
        raise _Mismatch(f"expected {_type_name(hint)}")
    if origin is typing.Literal:
        if value not in typing.get_args(hint):
            raise _Mismatch(f"expected one of {', '.join(map(repr, typing.get_args(hint)))}")
        return value
    if hint is type(None):
        if value is not None:
            raise _Mismatch("expected None")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise _Mismatch("expected bool (true or false)")
        return value
    if hint in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (hint is int and isinstance(value, float)):
            raise _Mismatch(f"expected {hint.__name__}")
        value = float(value) if hint is float else value
        _number_rules(value, key, rules)
        return value
    if hint is str:
        if not isinstance(value, str):
            raise _Mismatch("expected str")
        return value
    if isinstance(hint, type) and issubclass(hint, PurePath):
        if not isinstance(value, (str, PurePath)):
            raise _Mismatch("expected a path (str)")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise _Mismatch(f"expected a {origin.__name__}")
        args = typing.get_args(hint)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise _Mismatch(f"expected a tuple of {len(args)} values, got {len(value)}")
            items = [coerce(a, v, f"{key}[{i}]", rules) for i, (a, v) in enumerate(zip(args, value))]
        else:
            elem = args[0] if args else Any
            items = [coerce(elem, v, f"{key}[{i}]", rules) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise _Mismatch("expected a table")
        _, vt = typing.get_args(hint) or (Any, Any)
        return {k: coerce(vt, v, f"{key}.{k}", rules) for k, v in value.items()}
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, hint):
            raise _Mismatch(f"expected a {hint.__name__} table")
        return value
    return value


def _number_rules(value: float, key: str, rules: tuple[Rule, ...]) -> None:
    if not math.isfinite(value):
        raise ConfigError(f"{key} = {value!r}: must be a finite number")
    numeric = [r for r in rules if r.numeric]
    if not any(isinstance(r, (Range, _Signed)) for r in numeric):
        numeric.append(NON_NEGATIVE)
    for r in numeric:
        if (why := r.broken(value)) is not None:
            raise ConfigError(f"{key} = {value!r}: {why}")


def coerce(hint: Any, value: Any, key: str, rules: tuple[Rule, ...] = ()) -> Any:
    """``value`` checked against type ``hint`` and its rules (see the module docstring);
    ConfigError ``"<key> = <value>: <rule>"`` when it does not fit."""
    hint_plain, own = split_hint(hint)
    try:
        value = _typed(hint, value, key, tuple(r for r in rules if r.numeric))
    except _Mismatch as e:
        raise ConfigError(f"{key} = {value!r}: {e}") from None
    for r in own:
        if not r.numeric and (why := r.broken(value)) is not None:
            raise ConfigError(f"{key} = {value!r}: {why}")
    return value


# -- command-line options: the same rules for a flag ------------------------------------------

_NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")
_INTEGER = re.compile(r"[+-]?\d+")
_SIZE = re.compile(r"(\d+(\.\d+)?)\s*[KMGT]i?B", re.IGNORECASE)


@dataclass(frozen=True)
class Number:
    """An argparse type: a decimal number in ASCII (``float()`` alone takes ``nan``, ``inf``
    and other scripts' digits), finite, within ``rule`` (a ``Range``, as a config field's)."""

    integer: bool
    rule: Range
    kind = "number"  # tests/test_cli_hostile.py tries hostile numbers on every option of this kind

    @property
    def __name__(self) -> str:  # argparse names the type in its own messages
        return "int" if self.integer else "float"

    def __call__(self, text: str) -> int | float:
        if not text.isascii() or not (_INTEGER if self.integer else _NUMBER).fullmatch(text.strip()):
            raise argparse.ArgumentTypeError(f"expects {'an integer' if self.integer else 'a number'}, "
                                             f"got {shown(text)!r}")
        value = int(text) if self.integer else float(text)
        if not math.isfinite(value):  # 1e999
            raise argparse.ArgumentTypeError(f"expects a finite number, got {text!r}")
        broken = self.rule.broken(value)
        if broken:
            raise argparse.ArgumentTypeError(f"{broken}, got {text.strip()}")
        return value


def count(lo: int = 1, hi: int = MAX_FRAMES, why: str = "") -> Number:
    """An integer in [lo, hi] (by default at least one: frames, seeds, repeats)."""
    return Number(True, Range(lo, hi, why=why))


def real(lo: float, hi: float, lo_open: bool = False, why: str = "") -> Number:
    """A finite number in [lo, hi] (``lo_open``: > lo)."""
    return Number(False, Range(lo, hi, lo_open=lo_open, why=why))


def positive_float(hi: float, why: str = "") -> Number:
    """A finite number in (0, hi]."""
    return real(0.0, hi, lo_open=True, why=why)


def finite_float(bound: float, why: str = "") -> Number:
    """A finite number in [-bound, bound] (a signed weight or price)."""
    return real(-bound, bound, why=why)


worker_count = count(1, MAX_WORKERS)  # processes or CPUs
seconds = real(0.0, MAX_SECONDS)  # a wait: 0 = none
time_limit = positive_float(MAX_SECONDS)  # a time limit: > 0


@dataclass(frozen=True)
class MemorySize:
    """An argparse type: a memory size with its unit (``4GB``, ``512MiB``), more than zero."""

    kind = "number"

    @property
    def __name__(self) -> str:
        return "size"

    def __call__(self, text: str) -> str:
        m = _SIZE.fullmatch(text.strip()) if text.isascii() else None
        if m is None or not float(m.group(1)) > 0:
            raise argparse.ArgumentTypeError(f"expects a size such as 512MB or 4GB, got {shown(text)!r}")
        return text.strip()


memory_size = MemorySize()


class LocalInput(str):
    """An input that must exist where the command reads it: checked by ``check_paths`` after
    parsing, not on a machine that hands the job to a cluster (``mine submit --root``)."""


class OutputFile(str):
    """A file an option names for the command to write (``check_paths`` checks it after parsing)."""


class OutputFolder(str):
    """A folder an option names for the command to write in, made when absent (``check_paths`` too)."""


@dataclass(frozen=True)
class PathType:
    """An argparse type for a path: one the system can hold that prints on one line
    (``names.path_problem``); by ``role``, an ``input-file``, ``input-folder`` or ``input``
    (either) must exist; an ``output-file``, ``output-folder`` or ``local-input`` is marked for
    ``check_paths``; ``text`` (a catalogue folder or an object-store URI) needs no more."""

    role: str
    kind = "path"  # tests/test_cli_hostile.py tries hostile paths on every option of this kind

    @property
    def __name__(self) -> str:
        return "path"

    def __call__(self, text: str) -> str:
        problem = path_problem(text)
        if problem is not None:
            raise argparse.ArgumentTypeError(f"{shown(text)}: {problem}")
        p = Path(text)
        if self.role in ("input", "local-input") and "://" in text:  # a dataset root on an object store: its reader checks it
            return text
        if self.role == "input-file" and not p.is_file():
            raise argparse.ArgumentTypeError(f"{text}: {'is a folder, not a file' if p.is_dir() else 'no such file'}")
        if self.role == "input-folder" and not p.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: {'is a file, not a folder' if p.exists() else 'no such folder'}")
        if self.role == "input" and not p.exists():
            raise argparse.ArgumentTypeError(f"{text}: no such file or folder")
        if self.role == "output-file":
            return OutputFile(text)
        if self.role == "local-input":
            return LocalInput(text)
        if self.role == "output-folder" and "://" not in text:  # an object store (s3://…) is checked by its writer
            return OutputFolder(text)
        return text


input_file = PathType("input-file")
input_folder = PathType("input-folder")
input_path = PathType("input")
local_input = PathType("local-input")
output_file = PathType("output-file")
output_folder = PathType("output-folder")
path_text = PathType("text")


def clamped_note(sequence: str, frames: tuple[int, int | None], n_frames: int, verb: str = "mined") -> str | None:
    """``sequence 0005: frames 0:400 asked, 0:16 exist: mined 0:16`` when the range asked for
    ends past the sequence's last frame (the range is cut to it); None when it fits."""
    start, stop = frames
    if stop is None or stop <= n_frames:
        return None
    return f"sequence {sequence}: frames {start}:{stop} asked, 0:{n_frames} exist: {verb} {start}:{n_frames}"
