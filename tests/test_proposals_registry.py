"""The proposer registry (mining/proposals/registry.py): every entry whole, the names derived from it,
and a proposer added by one entry and one module, with no other list to edit."""

from __future__ import annotations

import ast
import dataclasses
import sys
import types

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from conftest import REPO
from mining.config import load_config
from mining.errors import ConfigError
from mining.proposals import registry
from mining.proposals.config import ProposalConfig
from mining.proposals.make import FrameProposer, classifiers_line, make_one
from mining.types import Proposals

SECTIONS = {f.name for f in dataclasses.fields(ProposalConfig)}


@pytest.mark.parametrize("name", registry.NAMES)
def test_every_entry_names_its_section_kind_and_a_factory_its_module_defines(name):
    e = registry.PROPOSERS[name]
    assert e.name == name and "+" not in name and name.strip() == name
    assert e.section in SECTIONS, f"{name}: no ProposalConfig field {e.section!r}"
    assert e.kind in (registry.FRAME, registry.MODEL)
    for x in e.extras:  # each extra part is switched by its own section's `enabled`
        assert x in SECTIONS and isinstance(getattr(ProposalConfig(), x).enabled, bool), x
        assert e.kind == registry.MODEL, "only a network run gives extra parts"
    # Read, not imported: the torch module fails to import where the extra is not installed.
    path = REPO / "mining" / "proposals" / f"{e.module}.py"
    defined = {n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}
    assert e.factory in defined, f"{name}: {path.name} defines no {e.factory}"


def test_the_name_lists_are_the_registry_s():
    assert registry.NAMES == ("stereo", "onnx", "torch", "json", "fastsam", "sam")
    assert registry.CLASSIFYING == ("onnx", "torch", "json")
    assert registry.MODELS == ("onnx", "torch", "fastsam", "sam")


def test_the_classifiers_line_says_what_the_entries_say():
    assert classifiers_line("json") == "classes: json (if its files carry classes) classified (proposer json)"
    assert classifiers_line("onnx+json") == "classes: onnx and json classified (proposer onnx+json)"
    assert classifiers_line("json+stereo").startswith("classes: json (if its files carry classes) classified "
                                                      "(proposer json+stereo); the other proposers' proposals")
    assert classifiers_line("fastsam+stereo").startswith("classes: no classifier ran")


def test_the_registry_imports_no_proposer():
    # The config's validator imports it: it must stay free of model libraries and of import loops.
    tree = ast.parse((REPO / "mining" / "proposals" / "registry.py").read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not {m for m in imported if m and m.startswith("mining.proposals")} - {"mining.proposals.config"}
    assert "mining.proposals.config" not in {n.module for n in tree.body if isinstance(n, ast.ImportFrom)}


def test_the_config_refuses_a_name_the_registry_lacks():
    with pytest.raises(ConfigError, match="unknown proposer 'nope'; known: stereo, onnx, torch, json, fastsam, sam"):
        load_config(None, ["proposals.proposer='onnx+nope'"])
    with pytest.raises(ConfigError, match="unknown proposer 'nope'"):
        make_one("nope", ProposalConfig(), (8, 8))


# --- a proposer added by one entry and one module ------------------------------------------------

H, W = 16, 32


def _box(frame: int, name: str, x0: int, score: float) -> Proposals:
    """One proposal: a 4×4 square at column ``x0``, named ``name``."""
    m = np.zeros((H, W), np.uint8)
    m[2:6, x0:x0 + 4] = 1
    rle = mask_utils.encode(np.asfortranarray(m))
    return Proposals(frame, [rle], np.array([[x0, 2, x0 + 4, 6]], np.float32), np.array([score], np.float32),
                     None, [name])


def _planted_module() -> types.ModuleType:
    """What a new proposer's module offers the registry: its factories."""
    mod = types.ModuleType("mining.proposals.planted")

    def frame_factory(cfg, frame_size):
        return lambda frame, geometry: _box(frame.index, "planted_frame", 0, 0.5)

    def model_factory(cfg, frame_size):
        extra = cfg.onnx_generic.enabled
        return lambda frames, images: [[_box(f, "planted_model", 8, 0.9)]
                                       + ([_box(f, "onnx_generic", 16, 0.1)] if extra else []) for f in frames]

    def other_factory(cfg, frame_size):
        return lambda frames, images: [[_box(f, "planted_other", 24, 0.7)] for f in frames]

    mod.frame_factory, mod.model_factory, mod.other_factory = frame_factory, model_factory, other_factory
    return mod


@pytest.fixture
def planted(monkeypatch):
    monkeypatch.setitem(sys.modules, "mining.proposals.planted", _planted_module())
    entries = dict(registry.PROPOSERS)
    entries["planted_frame"] = registry.ProposerEntry("planted_frame", "stereo", registry.FRAME, False, "planted",
                                                      "frame_factory")
    entries["planted_model"] = registry.ProposerEntry("planted_model", "onnx", registry.MODEL, False, "planted",
                                                      "model_factory", extras=("onnx_generic",))
    entries["planted_other"] = registry.ProposerEntry("planted_other", "fastsam", registry.MODEL, False, "planted",
                                                      "other_factory")
    monkeypatch.setattr(registry, "PROPOSERS", entries)
    monkeypatch.setattr(registry, "NAMES", tuple(entries))


def _frame(index: int):
    return types.SimpleNamespace(index=index, left=np.zeros((H, W, 3), np.uint8))


def test_a_new_entry_is_a_proposer_of_the_config_the_union_and_the_model_stage(planted):
    cfg = ProposalConfig(proposer="planted_model+planted_frame")
    assert registry.unknown_proposers(cfg.proposer) is None
    geometry = types.SimpleNamespace(disparity=None, depth=None)
    whole = FrameProposer(cfg, (H, W))
    assert whole.names == ["planted_model", "planted_frame", "onnx_generic"]  # the extra part last
    assert whole.model_names == ["planted_model", "onnx_generic"]
    p = whole(_frame(3), geometry)
    assert p.frame == 3 and sorted(p.proposer) == ["onnx_generic", "planted_frame", "planted_model"]
    # Split as the proposal stage splits it: the same proposals.
    here = FrameProposer(cfg, (H, W), models=False)
    models = FrameProposer(cfg, (H, W), frame_parts=False).propose_images([3], [_frame(3).left])[0]
    assert here.finish(_frame(3), geometry, models).proposer == p.proposer
    # make_one gives a model proposer's own proposals alone.
    assert make_one("planted_model", cfg, (H, W))(_frame(3), geometry).proposer == ["planted_model"]
    off = dataclasses.replace(cfg, onnx_generic=dataclasses.replace(cfg.onnx_generic, enabled=False))
    assert FrameProposer(off, (H, W)).names == ["planted_model", "planted_frame"]


def test_each_model_result_lands_in_its_own_part_where_two_models_run_and_one_has_an_extra(planted):
    # The extra's proposals come from the first model's run, beside its own: each slot of a frame's
    # model results holds the part model_names names there, and the union takes the extra last.
    cfg = ProposalConfig(proposer="planted_model+planted_other+planted_frame")
    whole = FrameProposer(cfg, (H, W))
    assert whole.names == ["planted_model", "planted_other", "planted_frame", "onnx_generic"]
    models = whole.propose_images([5], [_frame(5).left])[0]
    assert [set(p.proposer) for p in models] == [{n} for n in whole.model_names]
    p = whole(_frame(5), types.SimpleNamespace(disparity=None, depth=None))
    assert sorted(p.proposer) == ["onnx_generic", "planted_frame", "planted_model", "planted_other"]
