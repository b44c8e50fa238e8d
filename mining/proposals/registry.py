"""The proposers: one entry each, the one list every proposer name, kind and factory comes from.

A ``proposals.proposer`` setting names one proposer or a union of them (``"onnx+stereo"``).
Each entry of ``PROPOSERS`` says of one proposer:

* ``name``: what the setting calls it (and what its proposals' ``proposer`` rows say);
* ``section``: the ``ProposalConfig`` field it reads (``[proposals.<section>]``);
* ``kind``: ``FRAME``, it needs the frame's geometry or index and runs where the geometry is
  (``stereo``, ``json``); or ``MODEL``, it runs a network on the left image alone, so it runs
  batched and, where the job has one, on a proposal stage of its own (a GPU actor,
  ``mining/pipeline/proposal_stage.py``);
* ``classifies``: it gives each proposal an 81-way class posterior (a classifier looked);
  ``classifies_if`` names the condition where it does only sometimes (said in summaries);
* ``module`` and ``factory``: the function, in ``mining.proposals.<module>``, that builds it as
  ``factory(cfg: ProposalConfig, frame_size: (height, width))``. A ``FRAME`` factory returns a
  ``Proposer``: ``proposer(frame, geometry) -> Proposals``. A ``MODEL`` factory returns a
  ``ModelBatch``: ``batch(frames, images)`` → per frame a list of ``Proposals``, its own first,
  then one per part of ``extras`` that is on;
* ``extras``: further parts the same network run gives, each its own proposer name and config
  section and on where that section's ``enabled`` is (the ONNX model's generic candidates). A
  union takes them last, after every named proposer, so they add only what no other part found.

The factories are named as text and imported when a proposer is built: this module imports no
proposer, so the config's validator reads the names here without loading a model library, and
a proposer whose extra is not installed (``torch``) fails with its ConfigError only where it is
configured.

Adding a proposer: write its module (the proposer and its factory function), declare its
settings as a dataclass field of ``ProposalConfig`` named as its ``section`` (in
``proposals/config.py``, like every section of the job config), and add one entry below. The
config's validator, ``make.make_one``, the model factory, the proposal stage and the proposer
contract test (``tests/test_proposals_contract.py``, which runs every entry; a proposer that
needs a model file gets its settings there) read this list; nothing else names proposers.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mining.errors import ConfigError
from mining.types import FrameGeometry, Proposals, StereoFrame

if TYPE_CHECKING:  # the config module imports this one (its validator): annotations only
    from mining.proposals.config import ProposalConfig

Proposer = Callable[[StereoFrame, FrameGeometry], Proposals]
ModelBatch = Callable[[list[int], list[np.ndarray]], list[list[Proposals]]]

FRAME = "frame"  # needs the frame's geometry or index: runs where the geometry is
MODEL = "model"  # a network on the left image alone: batched, on the proposal stage where there is one


@dataclass(frozen=True)
class ProposerEntry:
    name: str  # in proposals.proposer
    section: str  # the ProposalConfig field it reads
    kind: str  # FRAME or MODEL
    classifies: bool  # its rows carry an 81-way class posterior
    module: str  # mining.proposals.<module> holds its factory
    factory: str  # factory(cfg: ProposalConfig, frame_size) -> Proposer (FRAME) or ModelBatch (MODEL)
    extras: tuple[str, ...] = ()  # parts the same network run adds, each on where its section's `enabled` is
    classifies_if: str = ""  # where it classifies only sometimes: the condition, said in summaries

    def load(self) -> Callable[[ProposalConfig, tuple[int, int]], Proposer | ModelBatch]:
        """The factory (its module imported now: a missing extra raises its ConfigError here)."""
        return getattr(importlib.import_module(f"mining.proposals.{self.module}"), self.factory)


PROPOSERS: dict[str, ProposerEntry] = {e.name: e for e in (
    ProposerEntry("stereo", "stereo", FRAME, False, "stereo", "stereo_proposer"),
    ProposerEntry("onnx", "onnx", MODEL, True, "onnx_yolo", "onnx_model", extras=("onnx_generic",)),
    # Classifies unless its checkpoint is class-agnostic (mining/proposals/mprcnn_torch.py).
    ProposerEntry("torch", "torch", MODEL, True, "mprcnn_torch", "torch_model"),
    ProposerEntry("json", "json", FRAME, True, "precomputed", "json_proposer",
                  classifies_if="if its files carry classes"),  # second_posterior or COCO category ids
    # Class-agnostic: objectness from their own scores, no posterior (in a union the classifier's rows
    # give the class, union.py).
    ProposerEntry("fastsam", "fastsam", MODEL, False, "fastsam", "fastsam_model"),
    ProposerEntry("sam", "sam", MODEL, False, "sam", "sam_model"),
)}
NAMES = tuple(PROPOSERS)
CLASSIFYING = tuple(n for n, e in PROPOSERS.items() if e.classifies)  # a classifier looked at their rows
MODELS = tuple(n for n, e in PROPOSERS.items() if e.kind == MODEL)  # they run a network on the left image alone


def proposer_names(proposer: str) -> list[str]:
    """The proposers of a ``proposals.proposer`` setting ("onnx+stereo" → ["onnx", "stereo"])."""
    return [n.strip() for n in proposer.split("+") if n.strip()]


def unknown_proposers(proposer: str) -> str | None:
    """What is wrong with a ``proposals.proposer`` setting, or None (the config's rule)."""
    names = proposer_names(proposer)
    if not names:
        return f"names no proposer; known: {', '.join(NAMES)} or a union like 'onnx+stereo'"
    bad = [n for n in names if n not in NAMES]
    if bad:
        return f"unknown proposer {', '.join(map(repr, bad))}; known: {', '.join(NAMES)} or a union like 'onnx+stereo'"
    return None


def entry(name: str) -> ProposerEntry:
    """The entry of proposer ``name``; ConfigError naming the known ones where there is none."""
    if name not in PROPOSERS:
        raise ConfigError(f"proposals.proposer: unknown proposer {name!r}; known: {NAMES} "
                          f"or a union like 'onnx+stereo'")
    return PROPOSERS[name]


def extra_parts(cfg: ProposalConfig) -> list[str]:
    """The extra parts that are on for the configured proposers, in their order (each entry's ``extras``)."""
    return [x for n in proposer_names(cfg.proposer) if n in PROPOSERS
            for x in PROPOSERS[n].extras if getattr(cfg, x).enabled]
