"""What lies near the ego at a time, found without a Python pass over the whole world: an hour's
sequence holds tens of thousands of objects and millions of roadside faces, and a frame of it
should cost what a frame of a short one does (issue 42). The faces and objects found, and their
order, are exactly those of a pass over everything."""

from __future__ import annotations

from typing import Any

import numpy as np

MESHES_CACHED = 512  # ours: objects whose mesh is kept (the least recently drawn lose theirs; rebuilt exactly)
SLIDING = ("static", "lane")  # motions whose arc position is s0 + v·t (v unused for static): tested in bulk


class Nearby:
    """An index of a scene's static faces (by their arc key) and of its objects' cheap range test."""

    def __init__(self, static_keys: np.ndarray, objects: list[Any]):
        self.n_static, self.n_objects = len(static_keys), len(objects)
        self.order = np.argsort(static_keys, kind="stable")
        self.sorted_keys = static_keys[self.order]
        self.objects = objects
        kinds = [o.motion.kind for o in objects]
        self.sliding = np.array([k in SLIDING for k in kinds], bool)
        self.s0 = np.array([o.motion.s0 if k in SLIDING else 0.0 for o, k in zip(objects, kinds)], float)
        self.v = np.array([o.motion.v if k == "lane" else 0.0 for o, k in zip(objects, kinds)], float)

    def fits(self, static_keys: np.ndarray, objects: list[Any]) -> bool:
        """Still the index of this world (the world is only ever added to while it is built)."""
        return objects is self.objects and len(static_keys) == self.n_static and len(objects) == self.n_objects

    def static(self, lo: float, hi: float) -> np.ndarray:
        """Indices of the static faces with ``lo < key < hi``, in their stored order."""
        a = np.searchsorted(self.sorted_keys, lo, side="right")
        b = np.searchsorted(self.sorted_keys, hi, side="left")
        return np.sort(self.order[a:b])

    def candidates(self, t: float, lo: float, hi: float) -> list[Any]:
        """The objects that pass the cheap test at ``t`` (sliding ones with ``lo < s0 + v·t < hi``;
        every other kind), in the world's order: each still gets the exact state test."""
        s = self.s0 + self.v * t
        keep = ~self.sliding | ((s > lo) & (s < hi))
        return [self.objects[i] for i in np.flatnonzero(keep)]


def keep_mesh(meshed: dict[int, Any], o: Any) -> None:
    """``o`` was drawn now (its mesh built): it goes last in ``meshed``; beyond ``MESHES_CACHED`` the
    least recently drawn lose their meshes, so a long sequence keeps those near the ego, not all it
    passed (a mesh is a pure function of its object: one dropped is built again the same)."""
    meshed.pop(id(o), None)
    meshed[id(o)] = o
    while len(meshed) > MESHES_CACHED:
        meshed.pop(next(iter(meshed))).faces = None
