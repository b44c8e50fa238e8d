"""Source adapters: each plans a sequence from timestamps and reads frame ranges lazily.

``open_source(dataset, root, **options)`` returns the adapter for a dataset name, after
``check_options`` has checked the options (``--option`` / ``[source.options]``) against
the adapter's keyword arguments: an unknown key or a value of the wrong type is a
ConfigError naming the key, the value and what the source expects.
"""

from __future__ import annotations

import importlib
import inspect
import typing
from typing import Any

from mining.checks import coerce
from mining.errors import ConfigError
from mining.sources.base import Source

# dataset name → "module:class"; imported on demand so a missing optional dependency of
# one adapter does not break the others.
DATASETS: dict[str, str] = {
    "kitti": "mining.sources.kitti:KittiTrackingSource",
    "kitti-raw": "mining.sources.kitti_raw:KittiRawSource",
    "oxford": "mining.sources.oxford:OxfordSource",
    "mcap": "mining.sources.mcap:McapSource",
    "synthetic": "mining.sources.synthetic:SyntheticSource",
}


def source_class(dataset: str) -> type[Source]:
    """The adapter class of ``dataset``."""
    try:
        target = DATASETS[dataset]
    except KeyError:
        raise ConfigError(f"unknown dataset {dataset!r}; known: {sorted(DATASETS)}") from None
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)


def check_options(dataset: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` checked against the keyword arguments of ``dataset``'s adapter (names,
    types, and ``mining.checks``' rules for numbers); returns them coerced (lists become
    tuples where a tuple is meant)."""
    cls = source_class(dataset)
    params = {n: p for n, p in inspect.signature(cls.__init__).parameters.items()
              if n not in ("self", "root") and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    unknown = sorted(set(options) - set(params))
    if unknown:
        raise ConfigError(f"source.options: unknown option(s) {unknown} of the {dataset} source; "
                          f"known: {sorted(params)}")
    hints = typing.get_type_hints(cls.__init__, include_extras=True)
    out = {}
    for key, value in options.items():
        try:
            out[key] = coerce(hints.get(key, Any), value, f"source.options.{key}")
        except ConfigError as e:
            raise ConfigError(f"{e} (an option of the {dataset} source)") from None
    return out


def open_source(dataset: str, root: str | None = None, **options: Any) -> Source:
    """The source adapter for ``dataset`` reading from ``root``."""
    return source_class(dataset)(root, **check_options(dataset, options))


__all__ = ["DATASETS", "Source", "check_options", "open_source", "source_class"]
