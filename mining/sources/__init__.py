"""Source adapters: each plans a sequence from timestamps and reads frame ranges lazily.

``open_source(dataset, root, **options)`` returns the adapter for a dataset name.
"""

from __future__ import annotations

import importlib
from typing import Any

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


def open_source(dataset: str, root: str | None = None, **options: Any) -> Source:
    """The source adapter for ``dataset`` reading from ``root``."""
    try:
        target = DATASETS[dataset]
    except KeyError:
        raise ConfigError(f"unknown dataset {dataset!r}; known: {sorted(DATASETS)}") from None
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)(root, **options)


__all__ = ["DATASETS", "Source", "open_source"]
