"""RobotCar as it is downloaded: a traversal's tar chunks beside each other, read in place.

Layout under the root (a local folder or a pyarrow filesystem URI)::

    <traversal>_stereo_<camera>_<NN>.tar   members <traversal>/stereo/<camera>/<µs>.png, one time range each
    <traversal>_<name>.tar                 small archives: <traversal>/stereo.timestamps, <traversal>/vo/vo.csv
    <traversal>/stereo.timestamps          … or those as plain files (a plain file wins)
    <traversal>/vo/vo.csv

The RobotCar download names chunk NN after the chunk id that ``stereo.timestamps`` gives its
frames (``_01`` holds the frames of chunk 1). A frame is looked up in that chunk first; should
the numbering disagree, in every chunk of its camera.

What is not there: a chunk absent for both cameras was not downloaded, a gap (as in the
extracted layout). A chunk present for one camera and absent for the other is *missing*; a
chunk whose archive stops part-way is *truncated*. Their frames stay in the plan and fail
when read, one line naming the chunk (and the offset where it stops): the windows holding
them fail, the others are mined.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from mining.errors import InputError
from mining.sources.tarchunks import ChunkIndex, Member, Root, chunk_index, read_member

# RobotCar download names: <traversal>_stereo_<camera>_<NN>.tar (cameras as the stereo/ folders).
CHUNK = re.compile(r"(?P<traversal>.+)_stereo_(?P<camera>left|centre|right)_(?P<number>\d+)\.tar")
# Another sensor's numbered chunk (mono, lidar, radar): large, never scanned for the small files.
NUMBERED = re.compile(r".+_\d+\.tar")


def chunk_traversals(names: set[str], cameras: tuple[str, ...]) -> set[str]:
    """The traversals that have a stereo chunk of one of ``cameras`` among the file ``names``."""
    return {m["traversal"] for n in names if (m := CHUNK.fullmatch(n)) and m["camera"] in cameras}


@dataclass
class Located:
    """Where one image lies: the chunk (relative to the root), its index and the member."""

    chunk: str
    index: ChunkIndex
    member: Member


@dataclass
class TarTraversal:
    """One traversal's chunks of the cameras of a stereo pair, indexed when first needed."""

    root: Root
    traversal: str
    cameras: tuple[str, ...]
    chunks: dict[str, dict[int, str]] = field(default_factory=dict)  # camera → chunk number → file name
    small: list[str] = field(default_factory=list)  # other archives of the traversal that may hold the small files

    @classmethod
    def find(cls, root: Root, traversal: str, cameras: tuple[str, ...], names: set[str]) -> TarTraversal:
        """The chunks of ``traversal`` among the root's file ``names``."""
        t = cls(root, traversal, cameras, {c: {} for c in cameras})
        for n in sorted(names):
            if (m := CHUNK.fullmatch(n)) and m["traversal"] == traversal:
                if m["camera"] in cameras:
                    t.chunks[m["camera"]][int(m["number"])] = n
            elif n.startswith(traversal + "_") and n.endswith(".tar") and not NUMBERED.fullmatch(n):
                t.small.append(n)
        return t

    @property
    def has_chunks(self) -> bool:
        return any(self.chunks.values())

    def member_name(self, camera: str, t_us: int) -> str:
        return f"{self.traversal}/stereo/{camera}/{t_us}.png"

    def chunk_file(self, camera: str, number: int) -> str:
        """The file name chunk ``number`` of ``camera`` has (or would have, as downloaded)."""
        return self.chunks[camera].get(number, f"{self.traversal}_stereo_{camera}_{number:02d}.tar")

    def present(self, camera: str) -> dict[str, Located]:
        """Every image of ``camera`` in its chunks (those cut short by a truncation included)."""
        out: dict[str, Located] = {}
        for rel in self.chunks[camera].values():
            idx = chunk_index(self.root, rel)
            prefix = f"{self.traversal}/stereo/{camera}/"
            out.update({n: Located(rel, idx, m) for n, m in idx.members.items() if n.startswith(prefix)})
        return out

    def locate(self, camera: str, t_us: int, chunk: int, frame: int) -> Located:
        """Where frame ``frame``'s image of ``camera`` lies (chunk id ``chunk`` by the timestamps);
        InputError naming the chunk, and the offset where it stops, when it cannot be read."""
        name = self.member_name(camera, t_us)
        rel = self.chunk_file(camera, chunk)
        shown = self.root.show(rel)
        idx = chunk_index(self.root, rel) if rel in self.chunks[camera].values() else None
        found = Located(rel, idx, idx.members[name]) if idx is not None and name in idx.members else None
        if found is None:  # a numbering that disagrees with the timestamps: every chunk of the camera
            found = self.present(camera).get(name)
        if found is not None:
            if found.index.truncated(found.member):
                m = found.member
                raise InputError(f"chunk {self.root.show(found.chunk)}, offset {m.header}: truncated: {name} needs "
                                 f"{m.size} bytes from offset {m.offset}, the chunk ends at {found.index.size}",
                                 None, frame)
            return found
        if idx is None:
            raise InputError(f"chunk {shown}: missing (stereo.timestamps puts this frame in chunk {chunk}, and "
                             f"{'the other camera has' if self._other_has(camera, chunk) else 'the traversal has'} it)",
                             None, frame)
        if idx.cut is not None:
            raise InputError(f"chunk {shown}, offset {idx.cut}: {idx.damage}: the archive stops there, before {name}",
                             None, frame)
        raise InputError(f"chunk {shown}: holds no {name} (stereo.timestamps puts this frame in chunk {chunk})",
                         None, frame)

    def _other_has(self, camera: str, chunk: int) -> bool:
        return any(chunk in numbers for c, numbers in self.chunks.items() if c != camera)

    def read(self, found: Located) -> bytes:
        return read_member(self.root, found.chunk, found.member)

    def small_file(self, rel: str) -> tuple[bytes, str] | None:
        """``<traversal>/<rel>`` (``stereo.timestamps``, ``vo/vo.csv``) and how to name it, from the
        traversal's small archives, else its stereo chunks; None when none holds it."""
        name = f"{self.traversal}/{rel}"
        stereo = [r for c in self.cameras for r in self.chunks[c].values()]
        for archive in (*self.small, *stereo):
            idx = chunk_index(self.root, archive)
            if (m := idx.members.get(name)) is not None and not idx.truncated(m):
                return read_member(self.root, archive, m), f"{self.root.show(archive)} (member {name})"
        return None
