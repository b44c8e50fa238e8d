"""A dataset root on local disk or any pyarrow filesystem URI, and tar archives read in place.

RobotCar is downloaded as tar chunks; extracting an hour of driving doubles the disk it
takes and, on an object store, means copying it first. So a chunk is read where it lies:
its headers are scanned once (``index_chunk``: one small read per member, no image data
read) into member name → (offset, size), and a frame's bytes are then one ranged read.

Only uncompressed tar is read this way (a compressed stream has no offsets to seek to),
which is how RobotCar ships its chunks. An index says where the archive stops being a
tar (``ChunkIndex.cut``): a chunk whose download stopped half-way still serves the members
before the cut, and the frames after it fail alone, named by chunk and offset.

Local files are opened through ``mining.files`` (regular files only: a FIFO never hangs a
reader); a URI (``s3://bucket/robotcar?endpoint_override=…``) through ``pyarrow.fs``.
"""

from __future__ import annotations

import io
import os
import posixpath
import tarfile
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow.fs as pafs

from mining.files import open_regular, read_bytes

# POSIX tar: every header and every member's data is padded to 512-byte blocks; the archive
# ends with (at least) one block of zeros.
TAR_BLOCK = 512
# ours: bytes read at a header (a pax header, its records and the member's header fit in it many
# times over); on an object store one request costs about the same for 512 bytes or 16 KiB.
HEADER_READ = 16 * 1024


class Root:
    """A folder to read data from: a local path, or a pyarrow filesystem URI (as ``--out``)."""

    def __init__(self, root: str | Path, sub: str = ""):
        text = str(root)
        self.text, self.sub = text, sub
        self.local = "://" not in text
        if self.local:
            self.fs, self.base, self._prefix = None, str(Path(text) / sub) if sub else str(Path(text)), ""
        else:
            self.fs, base = pafs.FileSystem.from_uri(text)
            self.base = posixpath.join(base.rstrip("/"), sub) if sub else base.rstrip("/")
            self._prefix = text.split("://", 1)[0] + "://"  # shown as the user wrote it, without the query

    def __getstate__(self) -> dict:
        return {"text": self.text, "sub": self.sub}  # a filesystem handle does not travel; the URI does

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["text"], state["sub"])

    def full(self, rel: str) -> str:
        """The path of ``rel`` for ``open``/``os`` calls (local) or ``self.fs`` (a URI)."""
        return str(Path(self.base) / rel) if self.local else posixpath.join(self.base, rel) if rel else self.base

    def show(self, rel: str = "") -> str:
        """How ``rel`` is named in messages: the local path, or the URI's scheme and path."""
        return self.full(rel) if self.local else self._prefix + self.full(rel)

    def child(self, rel: str) -> Root:
        """The folder ``rel`` below this one, as a Root."""
        return Root(self.text, posixpath.join(self.sub, rel) if self.sub else rel)

    def names(self, rel: str = "") -> set[str] | None:
        """The entries of folder ``rel``; None when it is not a folder (an empty set on an object
        store, where a folder is only a prefix)."""
        if self.local:
            try:
                with os.scandir(self.full(rel)) as it:
                    return {e.name for e in it}
            except (NotADirectoryError, FileNotFoundError):
                return None
        infos = self.fs.get_file_info(pafs.FileSelector(self.full(rel), allow_not_found=True))
        return {posixpath.basename(i.path) for i in infos}

    def is_file(self, rel: str) -> bool:
        if self.local:
            return os.path.isfile(self.full(rel))
        return self.fs.get_file_info(self.full(rel)).type == pafs.FileType.File

    def is_dir(self, rel: str) -> bool:
        if self.local:
            return os.path.isdir(self.full(rel))
        return self.fs.get_file_info(self.full(rel)).type == pafs.FileType.Directory

    def read(self, rel: str, frame: int | None = None) -> bytes:
        """The whole of file ``rel`` (a regular file, where local); FileNotFoundError when absent."""
        if self.local:
            return read_bytes(self.full(rel), frame)
        if self.fs.get_file_info(self.full(rel)).type != pafs.FileType.File:
            raise FileNotFoundError(self.show(rel))
        with self.fs.open_input_file(self.full(rel)) as f:
            return f.readall()

    def open(self, rel: str) -> RandomFile:
        """``rel`` for ranged reads (a regular file, where local); FileNotFoundError when absent."""
        if self.local:
            f = open_regular(self.full(rel))
            st = os.fstat(f.fileno())
            return RandomFile(f, st.st_size, st.st_mtime_ns)
        info = self.fs.get_file_info(self.full(rel))
        if info.type != pafs.FileType.File:
            raise FileNotFoundError(self.show(rel))
        mtime = info.mtime_ns if info.mtime_ns is not None else 0
        return RandomFile(self.fs.open_input_file(self.full(rel)), info.size, mtime)


@dataclass
class RandomFile:
    """An open file, its size and modification time, read by ranges."""

    handle: object  # a local binary file (``open_regular``) or a pyarrow RandomAccessFile
    size: int
    mtime_ns: int

    def read_at(self, offset: int, n: int) -> bytes:
        """At most ``n`` bytes from ``offset`` (fewer only at the end of the file)."""
        h = self.handle
        if hasattr(h, "read_at"):
            return h.read_at(n, offset)
        return os.pread(h.fileno(), n, offset)

    def close(self) -> None:
        self.handle.close()

    def __enter__(self) -> RandomFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Ranged(io.RawIOBase):
    """A RandomFile as the seekable stream ``tarfile`` reads headers from. On an object store
    every read is a request, so a header is read with what follows it (``HEADER_READ``: a pax
    header, its data and the member's own header come in one), and the images between the
    headers are never read."""

    def __init__(self, f: RandomFile):
        self.f, self.pos = f, 0
        self.buf_at, self.buf = 0, b""

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self.pos = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.f.size}[whence] + offset
        return self.pos

    def readinto(self, b) -> int:
        n = len(b)
        if n == 1 and self.pos < self.f.size:
            # tarfile reads the byte before each header only to learn whether the previous member's
            # data ends inside the file; the size says so without a request (the value is unused).
            b[0] = 0
            self.pos += 1
            return 1
        if not (self.buf_at <= self.pos and self.pos + n <= self.buf_at + len(self.buf)):
            self.buf_at = self.pos
            self.buf = self.f.read_at(self.pos, max(n, HEADER_READ)) if self.pos < self.f.size else b""
        data = self.buf[self.pos - self.buf_at: self.pos - self.buf_at + n]
        b[: len(data)] = data
        self.pos += len(data)
        return len(data)


@dataclass(frozen=True, slots=True)
class Member:
    """One regular file in a tar chunk: where its header and its data start, its size."""

    header: int
    offset: int
    size: int


@dataclass
class ChunkIndex:
    """What a tar chunk holds, from its headers; ``cut`` is None for an archive that ends as a
    tar should, else the offset where it stops being one (a truncated or damaged download)."""

    name: str
    size: int
    members: dict[str, Member] = field(default_factory=dict)
    cut: int | None = None
    damage: str = "truncated"  # what happened at ``cut``, for messages

    def truncated(self, m: Member) -> bool:
        """Whether member ``m``'s data runs past the end of the chunk."""
        return m.offset + m.size > self.size


def index_chunk(f: RandomFile, name: str) -> ChunkIndex:
    """The index of the tar archive ``f`` (file name ``name``); one that is no tar from its first
    header (an empty or cut download, another format) is an index of nothing, cut at 0."""
    idx = ChunkIndex(name, f.size)
    try:
        tf = tarfile.TarFile(fileobj=_Ranged(f))  # plain tar, read: no compression to detect
    except tarfile.TarError as e:  # an empty or cut first header, or no tar at all: no member is readable
        idx.cut = 0
        if f.size >= TAR_BLOCK:
            idx.damage = f"not an uncompressed tar archive ({e})"
        return idx
    ti = tf.firstmember
    while ti is not None:
        if ti.isreg():
            idx.members[ti.name] = Member(ti.offset, ti.offset_data, ti.size)
        try:
            ti = tf.next()
        except tarfile.ReadError:  # the data of the last member runs past the end: cut inside it
            idx.cut = ti.offset
            return idx
    end = tf.offset  # tarfile stops at the end-of-archive block, or silently where the headers stop making sense
    if f.read_at(end, TAR_BLOCK) != bytes(TAR_BLOCK):
        idx.cut = min(end, f.size)
    return idx


# Per process: a chunk is indexed once per (where, size, modification time), however many
# sources and windows read it.
_INDEXES: dict[tuple[str, int, int], ChunkIndex] = {}


def chunk_index(root: Root, rel: str) -> ChunkIndex:
    """The (cached) index of tar chunk ``rel`` under ``root``; FileNotFoundError when absent."""
    with root.open(rel) as f:
        key = (root.show(rel), f.size, f.mtime_ns)
        if key not in _INDEXES:
            _INDEXES[key] = index_chunk(f, posixpath.basename(rel))
    return _INDEXES[key]


def indexes_under(root: Root) -> dict[tuple[str, int, int], ChunkIndex]:
    """The indexes this process made of chunks under ``root`` (to hand to other processes)."""
    prefix = root.show()
    return {k: v for k, v in _INDEXES.items() if k[0].startswith(prefix)}


def adopt_indexes(indexes: dict[tuple[str, int, int], ChunkIndex]) -> None:
    """Indexes another process made (``indexes_under``); each is used only while its chunk's
    size and modification time are still those it was made from (its key)."""
    _INDEXES.update(indexes)


def read_member(root: Root, rel: str, member: Member) -> bytes:
    """The data of ``member`` of chunk ``rel``: one ranged read."""
    with root.open(rel) as f:
        return f.read_at(member.offset, member.size)
