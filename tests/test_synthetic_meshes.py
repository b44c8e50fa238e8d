"""The synthetic world keeps the meshes of the objects near the ego only (issue 42: no state kept
past its window), and a mesh dropped and rebuilt draws the same frame bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from mining.sources.synthetic import SyntheticSource
from mining.sources.synthetic import nearby


@pytest.mark.slow  # over ~2.5 s: renders frames of a long world
def test_meshes_kept_are_bounded_and_a_rebuilt_mesh_draws_the_same_frame(monkeypatch):
    src = SyntheticSource(n_frames=400, width=160, height=48)
    plan = src.plan("0000")
    first = src.read_frame(plan, 5)
    sc = src.scene("0000")
    meshed_first = [o for o in sc.objects if o.faces is not None]
    monkeypatch.setattr(nearby, "MESHES_CACHED", 4)  # small, so a few hundred frames evict
    for i in range(10, 400, 10):
        src.read_frame(plan, i)
    assert len(sc.meshed) <= 4 and sum(o.faces is not None for o in sc.objects) <= 4
    assert any(o.faces is None for o in meshed_first)  # the first frame's objects lost their meshes…
    again = src.read_frame(plan, 5)  # …and get them back, the same
    assert np.array_equal(first.left, again.left) and np.array_equal(first.right, again.right)
    assert np.array_equal(first.truth.depth, again.truth.depth, equal_nan=True)
