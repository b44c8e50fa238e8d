"""ROS 2 stereo recordings in MCAP files (one file = one sequence, named by its stem).

A sequence needs a left and a right image topic (``sensor_msgs/msg/Image`` or
``sensor_msgs/msg/CompressedImage``) and a ``sensor_msgs/msg/CameraInfo`` topic for each
camera. The images must already be rectified; the calibration comes from the projection
matrices P: fx = P[0], cx = P[2], fy = P[5], cy = P[6] and baseline = (P_l[3] − P_r[3]) / P_r[0]
(= −P_r[3] / P_r[0] when the left camera is the reference, the ROS convention).

Left and right images are paired by their header stamps (nearest neighbour, mutual, within
``max_pair_dt_ns``); frames without a partner are skipped and counted in ``pairing()``.
The frame index is the left message's position in the left topic (ordered by stamp), so a
skipped frame leaves a hole in ``plan.frames`` and a gap in ``plan.gaps``.

Two images on one topic with the same stamp cannot both be paired, and which one a frame
gets would be a guess: by default ``plan`` refuses the file, naming the topic and the
stamp; with ``duplicate_stamps="gap"`` the first message of each stamp (by log time) is
kept and the others are dropped as recording gaps, counted in ``pairing()``.

``plan`` reads the summary, the first CameraInfo of each camera and the first 12 bytes
(CDR encapsulation + stamp) of each image message; it never decodes an image, but it does
decompress every chunk that holds images (~4 ms per 1.4 MB image message). With
``time_source="log"`` it pairs by log time instead and reads only the message index
records, no chunk at all (~40× faster). ``read_frame`` seeks to the chunks that hold the
two messages via the chunk index (log-time filter), not a rescan. Chunk CRCs are checked,
so corrupt bytes are an InputError naming the file (and the frame), never a wrong image.
A file without an intact footer/summary (a recording cut short) is refused at ``plan``.

A corrupt chunk (bad CRC, undecompressable, unparsable) does not fail the recording:
``plan`` reads the file chunk by chunk from the summary's chunk indexes, and a chunk that
cannot be read is recorded (``damaged()``: its byte offset, log-time range and the frames in
it). Its image messages are still known from the message index records written beside the
chunk (log times only: their header stamps are estimated as log time − the topic's median
recording delay), so its frames keep their place in ``plan.frames`` and ``read_frame`` of one
of them raises an InputError naming the chunk's offset and time range: only the windows
holding them fail, the readable frames are mined. They are not ``plan.problems``, which
would refuse the whole ``--frames`` range at planning. A corrupt chunk whose message
indexes are unreadable too leaves its frames unknown: they are a gap, named by ``damaged()``.
"""

from __future__ import annotations

import bisect
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mining.errors import ConfigError, InputError
from mining.files import open_regular
from mining.sources.base import Source
from mining.types import SequencePlan, StereoCalib, StereoFrame

# ours: hardware-triggered stereo stamps agree to well under a millisecond; 5 ms tolerates
# software-triggered pairs while staying far below a frame period (50 ms at 20 Hz).
MAX_PAIR_DT_NS = 5_000_000

# ours: a frame interval longer than this many median intervals is a recording gap.
GAP_FACTOR = 1.5

# ours: intrinsics of the left and right CameraInfo must agree this closely (rectified pair).
RECTIFIED_TOL_PX = 1e-3

IMAGE_TYPES = {
    "sensor_msgs/msg/Image": "raw",
    "sensor_msgs/Image": "raw",
    "sensor_msgs/msg/CompressedImage": "compressed",
    "sensor_msgs/CompressedImage": "compressed",
}
INFO_TYPES = {"sensor_msgs/msg/CameraInfo", "sensor_msgs/CameraInfo"}

# ROS Bayer encoding pattern → OpenCV code. OpenCV names a pattern after the 2nd and 3rd
# pixel of its 2nd row (so GBRG is "GR"); checked by the round-trip tests.
BAYER_TO_RGB = {
    "rggb": cv2.COLOR_BayerBG2RGB,
    "bggr": cv2.COLOR_BayerRG2RGB,
    "gbrg": cv2.COLOR_BayerGR2RGB,
    "grbg": cv2.COLOR_BayerGB2RGB,
}
RAW_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}


def header_stamp_ns(data: bytes | memoryview) -> int:
    """The ``header.stamp`` of a CDR-encoded message whose first field is a std_msgs/Header."""
    if len(data) < 12:
        raise ValueError("message shorter than a CDR header stamp")
    fmt = "<iI" if data[1] & 1 else ">iI"  # encapsulation id: odd = little endian
    sec, nanosec = struct.unpack_from(fmt, data, 4)
    return sec * 1_000_000_000 + nanosec


@dataclass
class _Index:
    """What plan() learned about one file; read_frame() needs it to find messages."""

    path: Path
    topics: tuple[str, str]
    kinds: tuple[str, str]  # "raw" or "compressed"
    left: list[tuple[int, int]]  # (stamp_ns, log_time) per left message, sorted by stamp
    right: list[tuple[int, int]]
    partner: dict[int, int]  # left position → right position
    calib: StereoCalib
    unpaired_left: int
    unpaired_right: int
    info_topics: tuple[str, str]
    repeated_left: int = 0  # messages dropped because an earlier one has their stamp (duplicate_stamps="gap")
    repeated_right: int = 0
    bad_chunks: list[BadChunk] = field(default_factory=list)
    bad_left: dict[int, int] = field(default_factory=dict)  # left position → bad_chunks number
    bad_right: dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class BadChunk:
    """A chunk that cannot be read: where it is, which log times it holds, and why."""

    offset: int  # byte offset of the chunk record in the file
    start_ns: int  # log time of its first and last message
    end_ns: int
    reason: str
    messages_known: bool = True  # False: its message indexes are unreadable too

    def describe(self) -> str:
        return (
            f"corrupt MCAP chunk at byte offset {self.offset} (log times {self.start_ns}–{self.end_ns} ns) "
            f"cannot be read: {self.reason}"
        )


def _open_error(path: Path, err: Exception) -> InputError:
    return InputError(
        f"not a readable MCAP file, or truncated (no intact footer/summary): {type(err).__name__}: {err}. "
        "A recording cut short can be rebuilt with `mcap recover`",
        path,
    )


class McapSource(Source):
    """Stereo pairs from ROS 2 MCAP files under ``root`` (a folder of .mcap files or one file)."""

    dataset = "mcap"

    def __init__(
        self,
        root: str | Path,
        left_topic: str | None = None,
        right_topic: str | None = None,
        left_info: str | None = None,
        right_info: str | None = None,
        max_pair_dt_ns: int = MAX_PAIR_DT_NS,
        time_source: str = "header",
        duplicate_stamps: str = "error",
    ):
        if time_source not in ("header", "log"):
            raise ConfigError(f"time_source must be 'header' or 'log', got {time_source!r}")
        if duplicate_stamps not in ("error", "gap"):
            raise ConfigError(f"duplicate_stamps must be 'error' or 'gap', got {duplicate_stamps!r}")
        self.duplicate_stamps = duplicate_stamps
        self.root = Path(root)
        self.left_topic, self.right_topic = left_topic, right_topic
        self.left_info, self.right_info = left_info, right_info
        self.max_pair_dt_ns = int(max_pair_dt_ns)
        self.time_source = time_source
        self._index: dict[str, _Index] = {}

    # -- files ---------------------------------------------------------------------------

    def sequences(self) -> list[str]:
        if self.root.is_file():
            return [self.root.stem]
        if not self.root.is_dir():
            raise InputError("MCAP root not found", self.root)
        return sorted(p.stem for p in self.root.glob("*.mcap"))

    def _path(self, sequence: str) -> Path:
        path = self.root if self.root.is_file() else self.root / f"{sequence}.mcap"
        if path.stem != sequence or not path.is_file():
            raise InputError(f"no MCAP file for sequence {sequence!r}", path)
        return path

    @staticmethod
    def _reader(f: Any, path: Path) -> tuple[Any, Any, Any]:
        """Reader, summary and a CDR decoder factory (its cache is per file: schema ids are)."""
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        try:
            reader = make_reader(f, validate_crcs=True)  # chunk CRCs catch corrupt bytes
            summary = reader.get_summary()
        except Exception as err:  # the mcap library raises assorted types on bad bytes
            raise _open_error(path, err) from None
        if summary is None:
            raise InputError("MCAP file has no summary section; re-index it with `mcap recover`", path)
        return reader, summary, DecoderFactory()

    # -- planning ------------------------------------------------------------------------

    def _choose(self, path: Path, summary: Any) -> tuple[tuple[str, str], tuple[str, str], tuple[str, str]]:
        channels = {ch.topic: summary.schemas[ch.schema_id].name if ch.schema_id else "" for ch in summary.channels.values()}
        images = sorted(t for t, s in channels.items() if s in IMAGE_TYPES)
        infos = sorted(t for t, s in channels.items() if s in INFO_TYPES)

        def pick(explicit: str | None, pool: list[str], side: str, what: str, near: str | None = None) -> str:
            if explicit is not None:
                if explicit not in pool:
                    raise InputError(f"{what} topic {explicit!r} not found; {what} topics here: {pool}", path)
                return explicit
            hits = [t for t in pool if side in t.lower()]
            if near is not None and len(hits) > 1:  # the CameraInfo beside the image topic
                common = [len(_common_prefix(t, near)) for t in hits]
                hits = [t for t, c in zip(hits, common) if c == max(common)]
            if len(hits) != 1:
                found = hits or pool
                if not found:
                    raise InputError(f"no {what} topic in the file (topics: {sorted(channels)})", path)
                raise InputError(
                    f"cannot tell the {side} {what} topic among {found}; pass {side}_"
                    f"{'topic' if what == 'image' else 'info'}=... explicitly",
                    path,
                )
            return hits[0]

        lt = pick(self.left_topic, images, "left", "image")
        rt = pick(self.right_topic, images, "right", "image")
        li = pick(self.left_info, infos, "left", "CameraInfo", near=lt)
        ri = pick(self.right_info, infos, "right", "CameraInfo", near=rt)
        kinds = (IMAGE_TYPES[channels[lt]], IMAGE_TYPES[channels[rt]])
        return (lt, rt), (li, ri), kinds

    def _build_index(self, sequence: str) -> _Index:
        path = self._path(sequence)
        with open_regular(path) as f:
            _, summary, factory = self._reader(f, path)
            (lt, rt), (lit, rit), kinds = self._choose(path, summary)
            try:
                stamps = _log_times_from_index(f, summary, [lt, rt]) if self.time_source == "log" else None
                scan = _scan(f, summary, [lt, rt, lit, rit] if stamps is None else [lit, rit], [lit, rit], factory)
            except InputError:
                raise
            except Exception as err:
                raise InputError(f"cannot read messages (corrupt chunk?): {type(err).__name__}: {err}", path) from None
        infos = scan.infos
        if stamps is None:
            try:
                stamps = {
                    t: [(m.log_time if self.time_source == "log" else header_stamp_ns(m.data), m.log_time)
                        for m in scan.messages.get(t, [])]
                    for t in (lt, rt)
                }
            except ValueError as err:
                raise InputError(f"cannot read an image message's header stamp: {err}", path) from None
        for topic in (lit, rit):
            if topic not in infos:
                more = "".join(f"; {b.describe()}" for b in scan.bad)
                raise InputError(f"CameraInfo topic {topic} has no readable messages{more}", path)
        for topic in (lt, rt):
            if not stamps[topic] and not scan.bad_logs.get(topic):
                raise InputError(f"image topic {topic} has no messages", path)
            if self.time_source == "header" and stamps[topic] and all(s == 0 for s, _ in stamps[topic]):
                raise InputError(f"image topic {topic} has zero header stamps; use time_source='log'", path)
        calib = _calib_from_infos(infos[lit], infos[rit], path, lit, rit)
        # Messages of unreadable chunks: log times from their message indexes, stamps estimated.
        delays = [lg - st for t in (lt, rt) for st, lg in stamps[t]]
        sides = {}
        for topic in (lt, rt):
            own = [lg - st for st, lg in stamps[topic]]
            delay = int(np.median(own if own else delays)) if (own or delays) else 0
            entries = [(st, lg, -1) for st, lg in stamps[topic]]
            entries += [(lg - delay, lg, k) for lg, k in scan.bad_logs.get(topic, [])]
            entries.sort()
            sides[topic] = ([(st, lg) for st, lg, _ in entries], {i: k for i, (_, _, k) in enumerate(entries) if k >= 0})
        (left, bad_left), (right, bad_right) = sides[lt], sides[rt]
        repeats = {
            topic: [k for k in _repeated(msgs) if k not in bad and k - 1 not in bad]
            for topic, msgs, bad in ((lt, left, bad_left), (rt, right, bad_right))
        }
        for topic, msgs in ((lt, left), (rt, right)):
            if repeats[topic] and self.duplicate_stamps == "error":
                k = repeats[topic][0]
                by_log = self.time_source == "header" and msgs[k - 1][1] != msgs[k][1]
                raise InputError(
                    f"image topic {topic}: {len(repeats[topic])} message(s) repeat the stamp of an earlier one "
                    f"(first: stamp {msgs[k][0]} ns, log times {msgs[k - 1][1]} and {msgs[k][1]}); pairing would "
                    "drop frames silently. Pass duplicate_stamps='gap' to keep the first of each stamp and drop "
                    f"the repeats as recording gaps{', or time_source=log (their log times differ)' if by_log else ''}",
                    path,
                )
        partner = _pair(left, right, self.max_pair_dt_ns, set(repeats[lt]), set(repeats[rt]))
        for i in bad_left:  # an unreadable left image is a frame that fails, never a silent drop
            partner.setdefault(i, -1)
        return _Index(
            path, (lt, rt), kinds, left, right, partner, calib,
            unpaired_left=len(left) - len(partner), unpaired_right=len(right) - len(set(partner.values()) - {-1}),
            info_topics=(lit, rit), repeated_left=len(repeats[lt]), repeated_right=len(repeats[rt]),
            bad_chunks=scan.bad, bad_left=bad_left, bad_right=bad_right,
        )  # fmt: skip

    def survey(self, sequence: str) -> SequencePlan:
        idx = self._build_index(sequence)
        frames = tuple(sorted(idx.partner))
        if not frames:
            raise InputError(
                f"no left/right pair within {self.max_pair_dt_ns} ns on {idx.topics[0]} and {idx.topics[1]}", idx.path
            )
        t_ns = tuple(idx.left[i][0] for i in frames)
        dt = np.diff(np.asarray(t_ns, dtype=np.int64))
        median = float(np.median(dt)) if len(dt) else 0.0
        gaps = tuple(
            i for i in range(1, len(frames)) if frames[i] != frames[i - 1] + 1 or dt[i - 1] > GAP_FACTOR * median
        )
        self._index[sequence] = idx
        return SequencePlan(self.dataset, sequence, idx.calib, frames, t_ns, gaps)

    def damaged(self, sequence: str) -> list[dict[str, Any]]:
        """The chunks ``plan`` found unreadable: byte offset, log-time range, reason, and the
        frames (left positions) whose left or right image lies in each; [] for an intact file."""
        if sequence not in self._index:
            self.plan(sequence)
        idx = self._index[sequence]
        out = []
        for k, b in enumerate(idx.bad_chunks):
            frames = sorted(
                i for i, j in idx.partner.items() if idx.bad_left.get(i) == k or idx.bad_right.get(j) == k
            )
            out.append({"offset": b.offset, "start_ns": b.start_ns, "end_ns": b.end_ns, "reason": b.reason,
                        "messages_known": b.messages_known, "frames": frames, "message": b.describe()})
        return out

    def pairing(self, sequence: str) -> dict[str, Any]:
        """Topics used and how many images found no partner."""
        if sequence not in self._index:
            self.plan(sequence)
        idx = self._index[sequence]
        return {
            "left_topic": idx.topics[0],
            "right_topic": idx.topics[1],
            "left_info": idx.info_topics[0],
            "right_info": idx.info_topics[1],
            "pairs": len(idx.partner),
            "unpaired_left": idx.unpaired_left,
            "unpaired_right": idx.unpaired_right,
            "repeated_left": idx.repeated_left,
            "repeated_right": idx.repeated_right,
            "corrupt_chunks": len(idx.bad_chunks),
        }

    # -- reading -------------------------------------------------------------------------

    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        idx = self._index.get(plan.sequence)
        if idx is None:
            self.plan(plan.sequence)
            idx = self._index[plan.sequence]
        frame = plan.frames[position]
        if frame not in idx.partner:
            raise InputError("frame is not a stereo pair in this file (plan from another file?)", idx.path, frame)
        for pos, bad, side in ((frame, idx.bad_left, "left"), (idx.partner[frame], idx.bad_right, "right")):
            if pos in bad:
                raise InputError(f"{idx.bad_chunks[bad[pos]].describe()}; it holds this frame's {side} image",
                                 idx.path, frame)
        wanted = {idx.topics[0]: idx.left[frame], idx.topics[1]: idx.right[idx.partner[frame]]}
        found: dict[str, np.ndarray] = {}
        try:
            with open_regular(idx.path, frame) as f:
                _, summary, factory = self._reader(f, idx.path)
                ids = {ch.id: ch for ch in summary.channels.values() if ch.topic in wanted}
                logs = {log for _, log in wanted.values()}
                chunks = [c for c in summary.chunk_indexes
                          if any(c.message_start_time <= t <= c.message_end_time for t in logs)
                          and (not c.message_index_offsets or set(c.message_index_offsets) & set(ids))]
                for chunk in sorted(chunks, key=lambda c: (c.message_start_time, c.chunk_start_offset)):
                    try:
                        messages = _chunk_messages(f, chunk, ids)
                    except Exception as err:
                        raise InputError(f"{_bad_chunk(chunk, err).describe()}; it holds this frame's images",
                                         idx.path, frame) from None
                    for message in messages:
                        channel = ids[message.channel_id]
                        stamp_log = wanted[channel.topic]
                        if channel.topic in found or message.log_time != stamp_log[1]:
                            continue
                        stamp = message.log_time if self.time_source == "log" else header_stamp_ns(message.data)
                        if stamp != stamp_log[0]:
                            continue
                        schema = summary.schemas.get(channel.schema_id)
                        msg = factory.decoder_for(channel.message_encoding, schema)(message.data)
                        kind = idx.kinds[0 if channel.topic == idx.topics[0] else 1]
                        found[channel.topic] = decode_image(msg, kind, idx.path, frame, channel.topic)
        except InputError as err:
            if err.frame is None:
                raise InputError(err.reason, err.path, frame) from None
            raise
        except Exception as err:
            raise InputError(f"cannot read the image messages (corrupt or truncated data): {type(err).__name__}: {err}", idx.path, frame) from None
        for topic in wanted:
            if topic not in found:
                raise InputError(f"image message on {topic} not found where the plan put it", idx.path, frame)
        left, right = found[idx.topics[0]], found[idx.topics[1]]
        for topic, img in ((idx.topics[0], left), (idx.topics[1], right)):
            if img.shape[:2] != (plan.calib.height, plan.calib.width):
                raise InputError(
                    f"{topic} image is {img.shape[1]}x{img.shape[0]} but CameraInfo says "
                    f"{plan.calib.width}x{plan.calib.height}",
                    idx.path,
                    frame,
                )
        return StereoFrame(self.dataset, plan.sequence, frame, plan.t_ns[position], left, right, plan.calib)


@dataclass
class _Scan:
    infos: dict[str, Any]  # topic → first decoded message (CameraInfo)
    messages: dict[str, list[Any]]  # topic → Message records of the readable chunks
    bad: list[BadChunk]
    bad_logs: dict[str, list[tuple[int, int]]]  # topic → (log time, bad chunk number) per unreadable message


def _chunk_messages(f: Any, chunk: Any, ids: dict[int, Any]) -> list[Any]:
    """The Message records of channels ``ids`` in one chunk, CRC checked; raises on bad bytes."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    f.seek(chunk.chunk_start_offset)
    opcode = f.read(1)
    if opcode != b"\x06":
        raise ValueError(f"expected a chunk record, found opcode {opcode.hex() or 'EOF'}")
    f.seek(8, 1)  # record length
    record = Chunk.read(ReadDataStream(f))
    return [r for r in breakup_chunk(record, validate_crc=True) if isinstance(r, Message) and r.channel_id in ids]


def _bad_chunk(chunk: Any, err: Exception, messages_known: bool = True) -> BadChunk:
    reason = f"{type(err).__name__}: {err}"
    return BadChunk(chunk.chunk_start_offset, chunk.message_start_time, chunk.message_end_time, reason, messages_known)


def _scan(f: Any, summary: Any, topics: list[str], info_topics: list[str], factory: Any) -> _Scan:
    """Read the chunks holding ``topics`` one by one (all of them, or only until every info
    topic has a message when ``topics`` are the info topics); a chunk that cannot be read is
    recorded, with the log times of its messages from its message indexes where they can be read."""
    ids = {ch.id: ch for ch in summary.channels.values() if ch.topic in topics}
    infos_only = set(topics) <= set(info_topics)
    out = _Scan({}, {t: [] for t in topics}, [], {t: [] for t in topics})
    for chunk in sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset)):
        if infos_only and len(out.infos) == len(info_topics):
            break
        if chunk.message_index_offsets and not set(chunk.message_index_offsets) & set(ids):
            continue
        try:
            messages = _chunk_messages(f, chunk, ids)
        except Exception as err:  # the mcap library, zstd and lz4 raise assorted types on bad bytes
            try:
                logs = _chunk_log_times(f, chunk, {i: ch.topic for i, ch in ids.items()})
            except Exception:
                logs = None
            k = len(out.bad)
            out.bad.append(_bad_chunk(chunk, err, logs is not None))
            for topic, times in (logs or {}).items():
                out.bad_logs[topic].extend((t, k) for t in times)
            continue
        for message in sorted(messages, key=lambda m: m.log_time):
            channel = ids[message.channel_id]
            if channel.topic in info_topics:
                if channel.topic not in out.infos:
                    schema = summary.schemas.get(channel.schema_id)
                    out.infos[channel.topic] = factory.decoder_for(channel.message_encoding, schema)(message.data)
            else:
                out.messages[channel.topic].append(message)
    return out


def _message_index(f: Any, offset: int) -> Any:
    """The message index record at byte ``offset`` of ``f`` (ValueError if another record is there)."""
    from mcap.records import MessageIndex
    from mcap.stream_reader import StreamReader

    f.seek(offset)
    record = next(StreamReader(f, skip_magic=True).records)
    if not isinstance(record, MessageIndex):
        raise ValueError(f"expected a message index at byte {offset}, found {type(record).__name__}")
    return record


def _chunk_log_times(f: Any, chunk: Any, ids: dict[int, str]) -> dict[str, list[int]] | None:
    """Log times per topic of one chunk's messages from its message index records; None
    when the chunk has none."""
    if not chunk.message_index_offsets:
        return None
    out: dict[str, list[int]] = {}
    for channel_id, offset in chunk.message_index_offsets.items():
        if channel_id in ids:
            out.setdefault(ids[channel_id], []).extend(t for t, _ in _message_index(f, offset).records)
    return out


def _log_times_from_index(f: Any, summary: Any, topics: list[str]) -> dict[str, list[tuple[int, int]]] | None:
    """(log_time, log_time) per message of each topic from the message index records alone,
    without decompressing a chunk; None when the file has no message indexes."""
    ids = {ch.id: ch.topic for ch in summary.channels.values() if ch.topic in topics}
    out: dict[str, list[tuple[int, int]]] = {t: [] for t in topics}
    for chunk in summary.chunk_indexes:
        if not chunk.message_index_offsets:
            return None
        for channel_id, offset in chunk.message_index_offsets.items():
            if channel_id in ids:
                out[ids[channel_id]].extend((t, t) for t, _ in _message_index(f, offset).records)
    return out


def _common_prefix(a: str, b: str) -> str:
    n = 0
    while n < min(len(a), len(b)) and a[n] == b[n]:
        n += 1
    return a[:n]


def _repeated(msgs: list[tuple[int, int]]) -> list[int]:
    """Positions (in stamp order) of messages whose stamp an earlier message already has."""
    return [k for k in range(1, len(msgs)) if msgs[k][0] == msgs[k - 1][0]]


def _pair(left: list[tuple[int, int]], right: list[tuple[int, int]], tol: int,
          skip_left: set[int] = frozenset(), skip_right: set[int] = frozenset()) -> dict[int, int]:
    """Mutual nearest neighbours by stamp within ``tol``: left position → right position;
    the ``skip_*`` positions (repeated stamps) take part in no pair."""
    keep_r = [j for j in range(len(right)) if j not in skip_right]
    keep_l = [i for i in range(len(left)) if i not in skip_left]
    if not keep_l or not keep_r:
        return {}
    pairs = _pair_unique([left[i] for i in keep_l], [right[j] for j in keep_r], tol)
    return {keep_l[i]: keep_r[j] for i, j in pairs.items()}


def _pair_unique(left: list[tuple[int, int]], right: list[tuple[int, int]], tol: int) -> dict[int, int]:
    ls = [s for s, _ in left]
    rs = [s for s, _ in right]

    def nearest(stamps: list[int], t: int) -> int:
        j = bisect.bisect_left(stamps, t)
        cands = [k for k in (j - 1, j) if 0 <= k < len(stamps)]
        return min(cands, key=lambda k: abs(stamps[k] - t))

    out = {}
    for i, t in enumerate(ls):
        j = nearest(rs, t)
        if abs(rs[j] - t) <= tol and nearest(ls, rs[j]) == i:
            out[i] = j
    return out


def _calib_from_infos(left: Any, right: Any, path: Path, left_topic: str, right_topic: str) -> StereoCalib:
    Pl = np.asarray(left.p, dtype=np.float64)
    Pr = np.asarray(right.p, dtype=np.float64)
    for P, topic in ((Pl, left_topic), (Pr, right_topic)):
        if P.shape != (12,) or not P[0] > 0 or not P[5] > 0:
            raise InputError(f"CameraInfo on {topic} has no projection matrix P (uncalibrated camera?)", path)
    kl, kr = Pl[[0, 5, 2, 6]], Pr[[0, 5, 2, 6]]
    if np.abs(kl - kr).max() > RECTIFIED_TOL_PX:
        raise InputError(f"CameraInfo P of {left_topic} and {right_topic} differ in fx, fy, cx, cy: not rectified", path)
    if (left.width, left.height) != (right.width, right.height):
        raise InputError(f"CameraInfo sizes differ: {left_topic} vs {right_topic}", path)
    baseline = (Pl[3] - Pr[3]) / Pr[0]
    if not baseline > 0:
        raise InputError(f"CameraInfo P[3] of {right_topic} gives baseline {baseline:.4f} m; expected −fx·baseline < 0", path)
    return StereoCalib(float(Pl[0]), float(Pl[5]), float(Pl[2]), float(Pl[6]), float(baseline), int(left.width), int(left.height))


def decode_image(msg: Any, kind: str, path: Path, frame: int, topic: str) -> np.ndarray:
    """A decoded sensor_msgs Image / CompressedImage → RGB uint8 (H, W, 3)."""
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if kind == "compressed":
        if "compresseddepth" in msg.format.lower():
            raise InputError(f"{topic}: compressedDepth images are not colour images", path, frame)
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None  # an empty buffer raises cv2.error
        if img is None:
            raise InputError(f"{topic}: cannot decode CompressedImage ({msg.format!r})", path, frame)
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    enc = msg.encoding.lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    bayer = enc[len("bayer_") : -1] if enc.startswith("bayer_") and enc.endswith("8") else None
    c = 1 if bayer in BAYER_TO_RGB else RAW_CHANNELS.get(enc)
    if c is None:
        raise InputError(f"{topic}: image encoding {msg.encoding!r} not supported (8-bit colour, mono or Bayer)", path, frame)
    if step < w * c or len(buf) < step * h:
        raise InputError(f"{topic}: image data holds {len(buf)} bytes, too few for {w}x{h} {enc} step {step}", path, frame)
    img = buf[: step * h].reshape(h, step)[:, : w * c].reshape(h, w, c)
    if bayer is not None:
        return cv2.cvtColor(img[..., 0], BAYER_TO_RGB[bayer])
    if enc in ("rgb8", "rgba8"):
        return np.ascontiguousarray(img[..., :3])
    if enc in ("bgr8", "bgra8"):
        return np.ascontiguousarray(img[..., 2::-1])
    return cv2.cvtColor(img[..., 0], cv2.COLOR_GRAY2RGB)
