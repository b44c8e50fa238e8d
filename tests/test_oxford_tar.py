"""RobotCar as it is downloaded (issue 42, item 3): tar chunks read in place, on local disk and
from a local S3-compatible server the test starts; a missing or truncated chunk fails only
the frames it holds, named by chunk and offset; ``stride`` skips frames at read time."""

from __future__ import annotations

import tarfile
from pathlib import Path

import numpy as np
import pytest
from _s3 import s3_folder
from conftest import kitti_0005_stereo
from mining.errors import ConfigError, InputError
from mining.sources import open_source
from mining.sources.oxford import OxfordSource
from mining.testing.fixtures import robotcar_as_downloaded, write_robotcar_fixture

N_FRAMES = 6  # KITTI 0005 frames 0-5, chunks of 2: chunk ids 1, 2, 3
TRAV = "2014-12-09-13-21-02"
VO = ("source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw\n"
      "1420070400062500,1420070400000000,1.0,0.0,0.0,0.0,0.0,0.0\n")


@pytest.fixture(scope="module")
def extracted(kitti_tracking_root, tmp_path_factory) -> Path:
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    root = tmp_path_factory.mktemp("extracted")
    trav = write_robotcar_fixture(root, left, right, calib, traversal=TRAV)
    (trav / "vo").mkdir()
    (trav / "vo" / "vo.csv").write_text(VO)
    return root


@pytest.fixture
def chunks(extracted, tmp_path) -> Path:
    return robotcar_as_downloaded(extracted, tmp_path / "chunks", TRAV)


def _same_frames(a: OxfordSource, b: OxfordSource, positions=range(N_FRAMES)) -> None:
    pa_, pb = a.plan(TRAV), b.plan(TRAV)
    assert (pa_.frames, pa_.t_ns, pa_.gaps, pa_.calib) == (pb.frames, pb.t_ns, pb.gaps, pb.calib)
    for pos in positions:
        fa, fb = a.read_frame(pa_, pos), b.read_frame(pb, pos)
        assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)


@pytest.mark.parametrize("small", ["tar", "plain"])
def test_chunks_read_in_place_as_the_extracted_copy(extracted, tmp_path, small):
    root = robotcar_as_downloaded(extracted, tmp_path / "chunks", TRAV, small=small)
    assert not (root / TRAV / "stereo").exists()  # nothing extracted
    assert sorted(p.name for p in root.glob("*_stereo_left_*.tar")) == [f"{TRAV}_stereo_left_0{i}.tar" for i in (1, 2, 3)]
    src = open_source("oxford", str(root))
    assert src.sequences() == [TRAV]
    _same_frames(OxfordSource(extracted), src)
    steps, want = src.vo(TRAV), OxfordSource(extracted).vo(TRAV)
    assert [(s.t_prev_ns, s.t_cur_ns) for s in steps] == [(s.t_prev_ns, s.t_cur_ns) for s in want]
    assert np.allclose(steps[0].T_cur_prev, want[0].T_cur_prev)


def test_a_missing_chunk_fails_only_its_frames(extracted, chunks):
    (chunks / f"{TRAV}_stereo_right_02.tar").unlink()  # the left camera's chunk 2 is there: not a gap
    src = OxfordSource(chunks)
    plan = src.plan(TRAV)
    assert plan.frames == tuple(range(N_FRAMES)) and plan.gaps == ()
    for pos in (2, 3):
        with pytest.raises(InputError) as e:
            src.read_frame(plan, pos)
        msg = str(e.value)
        assert f"frame {pos}: chunk {chunks / f'{TRAV}_stereo_right_02.tar'}: missing" in msg, msg
        assert "\n" not in msg
    _same_frames(OxfordSource(extracted), src, (0, 1, 4, 5))


def test_a_chunk_missing_for_both_cameras_is_a_gap_as_extracted(extracted, chunks):
    for cam in ("left", "right"):
        (chunks / f"{TRAV}_stereo_{cam}_02.tar").unlink()
    plan = OxfordSource(chunks).plan(TRAV)
    assert plan.frames == (0, 1, 4, 5) and plan.gaps == (2,)


def _member(chunk: Path, n: int) -> tarfile.TarInfo:
    with tarfile.open(chunk) as tf:
        return tf.getmembers()[n]


def test_a_truncated_chunk_fails_the_frames_past_the_cut(extracted, chunks):
    chunk = chunks / f"{TRAV}_stereo_left_02.tar"
    second = _member(chunk, 1)  # frame 3's image
    data = chunk.read_bytes()
    chunk.write_bytes(data[: second.offset_data + second.size // 2])  # the download stopped in frame 3's image
    src = OxfordSource(chunks)
    plan = src.plan(TRAV)
    assert plan.frames == tuple(range(N_FRAMES))
    with pytest.raises(InputError) as e:
        src.read_frame(plan, 3)
    msg = str(e.value)
    assert msg.startswith(f"frame 3: chunk {chunk}, offset {second.offset}: truncated"), msg
    _same_frames(OxfordSource(extracted), src, (0, 1, 2, 4, 5))  # frame 2, before the cut, reads

    chunk.write_bytes(data[: second.offset])  # cut between the two members: no header for frame 3 at all
    src = OxfordSource(chunks)
    plan = src.plan(TRAV)
    with pytest.raises(InputError, match=f"frame 3: chunk {chunk}, offset {second.offset}: truncated"):
        src.read_frame(plan, 3)
    src.read_frame(plan, 2)

    for cut in (0, 100):  # an empty download; one cut inside its first header
        chunk.write_bytes(data[:cut])
        src = OxfordSource(chunks)
        plan = src.plan(TRAV)
        for pos in (2, 3):
            with pytest.raises(InputError, match=f"frame {pos}: chunk {chunk}, offset 0: truncated"):
                src.read_frame(plan, pos)
        _same_frames(OxfordSource(extracted), src, (0, 1, 4, 5))


def test_a_chunk_that_is_no_tar_fails_its_frames_naming_why(extracted, chunks):
    chunk = chunks / f"{TRAV}_stereo_right_01.tar"
    chunk.write_bytes(b"\x1f\x8b" + bytes(4096))  # compressed, or anything else: no tar header to read
    src = OxfordSource(chunks)
    plan = src.plan(TRAV)
    with pytest.raises(InputError, match=f"frame 1: chunk {chunk}, offset 0: not an uncompressed tar archive"):
        src.read_frame(plan, 1)
    _same_frames(OxfordSource(extracted), src, (2, 3, 4, 5))


def test_stride_skips_frames_and_says_so(extracted, chunks):
    for root in (extracted, chunks):
        src = open_source("oxford", str(root), stride=2)
        plan = src.plan(TRAV)
        assert plan.frames == (0, 2, 4) and plan.gaps == ()
        assert plan.note == "stride 2: 1 of every 2 frames skipped (3 of 6)"
        assert src.read_frame(plan, 1).index == 2
    full = OxfordSource(extracted)
    assert np.array_equal(src.read_frame(plan, 2).left, full.read_frame(full.plan(TRAV), 4).left)
    plan = open_source("oxford", str(chunks), rate_hz=5.0).plan(TRAV)  # 16 Hz / 5 Hz: the nearest stride is 3
    assert plan.frames == (0, 3) and plan.note == "rate 5 Hz of 16 Hz: stride 3: 2 of every 3 frames skipped (4 of 6)"
    for bad in ({"rate_hz": 0.0}, {"rate_hz": 4.0, "stride": 2}, {"stride": 0}):
        with pytest.raises(ConfigError):
            open_source("oxford", str(chunks), **bad)


@pytest.fixture
def s3_root(chunks, monkeypatch):
    with s3_folder(chunks, monkeypatch) as uri:
        yield uri


def test_chunks_on_an_object_store_read_as_the_extracted_copy(extracted, s3_root):
    src = open_source("oxford", s3_root)
    assert src.sequences() == [TRAV]
    _same_frames(OxfordSource(extracted), src, (0, 3, 5))
    assert len(src.vo(TRAV)) == 1
    import pickle  # a worker gets the source by pickle: the URI travels, not the connection

    clone = pickle.loads(pickle.dumps(src))
    plan = clone.plan(TRAV)
    assert clone.read_frame(plan, 4).index == 4


def test_workers_adopt_the_planners_chunk_indexes(chunks, monkeypatch):
    """The job carries the planning source's indexes (Source.shared_state): a worker's source
    reads frames without scanning a chunk again, and scans one that changed since."""
    import pickle

    from mining.sources import tarchunks

    planner = OxfordSource(chunks)
    plan = planner.plan(TRAV)
    state = pickle.loads(pickle.dumps(planner.shared_state()))  # as it travels to a worker
    assert len(state) == 7  # 3 chunks of each camera and the timestamps' archive
    monkeypatch.setattr(tarchunks, "_INDEXES", {})  # a worker's process
    worker = pickle.loads(pickle.dumps(planner))
    worker.adopt_state(state)
    scans = []
    real = tarchunks.index_chunk
    monkeypatch.setattr(tarchunks, "index_chunk", lambda f, name: scans.append(name) or real(f, name))
    for pos in range(N_FRAMES):
        worker.read_frame(plan, pos)
    assert scans == []
    changed = chunks / f"{TRAV}_stereo_left_03.tar"
    changed.write_bytes(changed.read_bytes()[:1024])  # a chunk replaced since planning: its index is made anew
    with pytest.raises(InputError, match="truncated"):
        worker.read_frame(plan, 5)
    assert scans == [changed.name]


def test_an_extracted_traversal_on_an_object_store_reads_too(extracted, monkeypatch):
    with s3_folder(extracted, monkeypatch) as uri:
        src = open_source("oxford", uri)
        assert src.sequences() == [TRAV]
        _same_frames(OxfordSource(extracted), src, (0, 5))
