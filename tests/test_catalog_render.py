"""`mine render`: videos of a real catalogue (KITTI 0005 frames 0–15) read back with OpenCV."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
from pycocotools import mask as mask_utils
from conftest import REPO

from _catalog_data import N_FRAMES, SEQUENCE
from _run import cli, clean_error
from mining.errors import MiningError
from mining.export.render import run_render

W, H = 1242, 375
VIDEO_H = H + 1  # 4:2:0 video needs even sides: one black row below KITTI's 375


def _frames(path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened(), path
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        out.append(img)
    cap.release()
    return out


def _source(kitti_tracking_root, frame: int) -> np.ndarray:
    return cv2.imread(str(kitti_tracking_root / "training" / "image_02" / SEQUENCE / f"{frame:06d}.png"))


def _mask(tube_frames, tube_ids, frame: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    for f in tube_frames.to_pylist():
        if f["frame"] == frame and f["tube_id"] in tube_ids:
            m |= mask_utils.decode({"size": [f["rle_h"], f["rle_w"]], "counts": f["rle_counts"].encode()}).astype(bool)
    return m


def _selected(tables) -> list[str]:
    return sorted(t["tube_id"] for t in tables["tubes"].to_pylist() if t["selected"])


@pytest.fixture(scope="module")
def mp4(catalogue, tmp_path_factory):
    out, _ = catalogue
    dest = tmp_path_factory.mktemp("render") / "0005.mp4"
    assert run_render(str(out), SEQUENCE, str(dest)) == 0
    return dest


def test_every_mined_frame_at_the_source_size(mp4):
    frames = _frames(mp4)
    assert len(frames) == N_FRAMES
    assert {f.shape for f in frames} == {(VIDEO_H, W, 3)}
    cap = cv2.VideoCapture(str(mp4))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == N_FRAMES


def test_masks_are_drawn_and_the_rest_is_the_source(mp4, catalogue, kitti_tracking_root):
    """Inside the selected tubes' masks the pixels change; far from every mask they are the
    source's (up to the codec's loss), away from the caption in the top-left corner."""
    _, tables = catalogue
    frame = 8
    got = _frames(mp4)[frame][:H].astype(np.int32)
    src = _source(kitti_tracking_root, frame).astype(np.int32)
    inside = _mask(tables["tube_frames"], set(_selected(tables)), frame)
    all_tubes = {t["tube_id"] for t in tables["tubes"].to_pylist()}
    near = cv2.dilate(_mask(tables["tube_frames"], all_tubes, frame).astype(np.uint8), np.ones((61, 61), np.uint8))
    far = near == 0
    far[:40, :500] = False  # the caption
    diff = np.abs(got - src).mean(axis=2)
    assert inside.sum() > 500 and far.sum() > W * H // 2
    assert diff[inside].mean() > 25, "the masks are filled"
    assert diff[far].mean() < 10, "pixels far from every mask are the source's"


def test_where_draws_only_the_tubes_it_matches(mp4, catalogue, tmp_path, kitti_tracking_root):
    """The other selected tubes' masks, filled in the full render, keep the source's pixels."""
    out, tables = catalogue
    one, *others = _selected(tables)
    dest = tmp_path / "one.mp4"
    assert run_render(str(out), SEQUENCE, str(dest), where=f"tube_id = '{one}'", frames=(0, 2)) == 0
    src = _source(kitti_tracking_root, 0).astype(np.int32)
    diff = np.abs(_frames(dest)[0][:H].astype(np.int32) - src).mean(axis=2)
    full = np.abs(_frames(mp4)[0][:H].astype(np.int32) - src).mean(axis=2)
    mine = _mask(tables["tube_frames"], {one}, 0)
    theirs = _mask(tables["tube_frames"], set(others), 0)
    theirs &= cv2.dilate(mine.astype(np.uint8), np.ones((41, 41), np.uint8)) == 0  # their fill, not one's outline
    assert mine.sum() > 100 and theirs.sum() > 100
    assert np.median(diff[mine]) > 25
    assert np.median(full[theirs]) > 25 and np.median(diff[theirs]) < 12


def test_depth_doubles_the_width(catalogue, tmp_path):
    out, _ = catalogue
    dest = tmp_path / "depth.mp4"
    assert run_render(str(out), SEQUENCE, str(dest), depth=True, frames=(3, 5)) == 0
    frames = _frames(dest)
    assert len(frames) == 2 and frames[0].shape == (VIDEO_H, 2 * W, 3)
    panel = frames[0][:H, W:]
    assert (panel.std(axis=(0, 1)) > 20).all(), "a colour-mapped depth image, not a blank panel"


def _codec(path) -> str:
    cap = cv2.VideoCapture(str(path))
    try:
        return int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode()
    finally:
        cap.release()


def test_mp4_is_h264(mp4):
    """With the `video` extra (PyAV, which the test set-up installs) MP4 is H.264, the codec every
    browser plays (tests/test_view_browser.py plays it in Chromium)."""
    assert _codec(mp4) in {"h264", "avc1"}


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_without_pyav_mp4_is_mpeg4_part2_and_says_so(catalogue, tmp_path):
    """A machine without PyAV still gets an MP4, MPEG-4 Part 2, and is told that browsers will not play it."""
    out, _ = catalogue
    dest = tmp_path / "no-pyav.mp4"
    code = ("import sys; sys.modules['av'] = None; from mining.cli import main; "  # `import av` fails, as without it
            f"sys.exit(main(['render', '--out', {str(out)!r}, '--sequence', {SEQUENCE!r}, '--frames', '0:2', {str(dest)!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    assert _codec(dest) in {"mp4v", "FMP4"} and len(_frames(dest)) == 2  # FFmpeg reads MPEG-4 Part 2 back as FMP4
    assert "browsers do not" in done.stdout and "tube-miner[video]" in done.stdout


def test_webm_is_vp8(catalogue, tmp_path):
    """WebM is written as VP8, which browsers play."""
    out, _ = catalogue
    dest = tmp_path / "v.webm"
    assert run_render(str(out), SEQUENCE, str(dest), frames=(0, 3)) == 0
    assert _codec(dest) == "VP80" and len(_frames(dest)) == 3


def test_nothing_matched_writes_nothing(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest = tmp_path / "none.mp4"
    from mining.cli import main

    assert main(["render", "--out", str(out), "--sequence", SEQUENCE, "--where", "n_frames > 10000", str(dest)]) == 1
    assert capsys.readouterr().err == (f"mine render: no selected tube of sequence {SEQUENCE!r} matches "
                                       "--where 'n_frames > 10000'; nothing written\n")
    assert not dest.exists() and not list(tmp_path.iterdir())


def test_unknown_sequence_and_container_are_refused(catalogue, tmp_path, capsys):
    out, _ = catalogue
    with pytest.raises(MiningError, match="'9999'"):
        run_render(str(out), "9999", str(tmp_path / "a.mp4"))
    with pytest.raises(MiningError, match=r"\.webm"):
        run_render(str(out), SEQUENCE, str(tmp_path / "a.avi"))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("fps", ["nan", "0", "-5", "inf", "1e308", "0.0"])
def test_fps_must_be_a_positive_finite_rate(catalogue, tmp_path, capsys, fps):
    """Issue 28, case 10: ``--fps nan`` ended in a traceback and ``--fps 0`` silently became 10 fps."""
    out, _ = catalogue
    dest = tmp_path / "v.webm"
    rc, o, e = cli(capsys, "render", "--out", str(out), "--sequence", SEQUENCE, "--frames", "0:2", "--fps", fps, str(dest))
    assert rc == 2 and "--fps" in clean_error(e) and len(e.strip().splitlines()) == 1 and not o, (rc, o, e)
    assert not list(tmp_path.iterdir())
    for value in (float(fps), float("nan")):  # the function refuses them too (never "0 means the default")
        with pytest.raises(MiningError, match="--fps"):
            run_render(str(out), SEQUENCE, str(dest), fps=value, frames=(0, 2))
    assert not list(tmp_path.iterdir())


def test_cli_render(catalogue, tmp_path):
    from mining.cli import main

    out, _ = catalogue
    dest = tmp_path / "cli.webm"
    assert main(["render", "--out", str(out), "--sequence", SEQUENCE, "--frames", "0:2", "--fps", "5", str(dest)]) == 0
    cap = cv2.VideoCapture(str(dest))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2 and cap.get(cv2.CAP_PROP_FPS) == 5


def test_labels_of_neighbouring_tubes_do_not_cover_each_other():
    """Two tubes with the same box get their labels one above the other, both inside the image."""
    from mining.draw import Drawn, draw_tubes, label, overlaps

    img = np.zeros((200, 300, 3), np.uint8)
    placed: list = []
    for _ in range(3):
        label(img, "12.3 unclassified", (40, 100, 120, 160), (0, 200, 0), placed)
    assert len(placed) == 3 and not any(overlaps(a, b) for i, a in enumerate(placed) for b in placed[i + 1:])
    assert all(0 <= y1 and y2 < 200 for _, y1, _, y2 in placed)
    mask = np.zeros((200, 300), np.uint8)
    mask[100:160, 40:120] = 1
    items = [Drawn(f"t{k}", f"{k}.0 car", (0, 0, 255) if k else (255, 0, 0), mask, (40, 100, 120, 160), True)
             for k in range(2)]
    out = draw_tubes(np.zeros((200, 300, 3), np.uint8), items)
    above = out[:100, 40:200]
    assert ((above == (255, 0, 0)).all(axis=2).any() and (above == (0, 0, 255)).all(axis=2).any()), \
        "both labels' boxes are visible above the mask"


def test_render_labels_keep_the_id_apart_from_the_probability():
    from mining.export.render import short_id, tube_caption

    # 3.9 and 3.90 are different tubes; neither id reads as a number.
    assert short_id("kitti/0005/0000003.009") == "#3:9" and short_id("kitti/0005/0000003.090") == "#3:90"
    assert short_id("kitti/0005/0000012.003-1") == "#12:3-1"  # a second tube from one observation
    assert tube_caption({"tube_id": "kitti/0005/0000090.001", "known": True, "category": "car",
                         "category_prob": 0.372}) == "#90:1 car 0.37"
    assert tube_caption({"tube_id": "kitti/0005/0000004.001", "known": False, "category": "unknown",
                         "category_prob": 0.91}) == "#4:1 unknown 0.91"
    assert tube_caption({"tube_id": "kitti/0005/0000004.001", "known": None, "category": None,
                         "category_prob": None}) == "#4:1 unclassified"


def test_a_sequence_with_no_selected_tube_renders_its_frames_and_says_so(catalogue, kitti_tracking_root, tmp_path, capsys):
    """It was refused ("no selected tube … nothing written"): a video of the frames shows what was
    missed, which is what one renders such a sequence for."""
    import pyarrow as pa

    from _catalog_data import DATASET
    from mining.catalog.schema import SCHEMAS
    from mining.catalog.store import Store, write_sequence
    from mining.cli import main

    out, tables = catalogue
    cat = tmp_path / "none-selected"
    rows = [dict(r, selected=False) for r in tables["tubes"].to_pylist()]
    write_sequence(Store(cat), "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=SCHEMAS["tubes"]))
    write_sequence(Store(cat), "tube_frames", DATASET, SEQUENCE, tables["tube_frames"])
    Store(cat).write_bytes("job.json", (out / "job.json").read_bytes())
    dest = tmp_path / "frames.mp4"
    assert main(["render", "--out", str(cat), "--sequence", SEQUENCE, "--frames", "0:3", str(dest)]) == 0
    said = capsys.readouterr().out
    assert f"sequence {SEQUENCE!r} has no selected tube: the video shows its frames alone" in said, said
    assert "3 frames, 0 tubes" in said
    got = _frames(dest)
    assert len(got) == 3
    # The frame as the source has it, under the caption band: no tube drawn.
    src = _source(kitti_tracking_root, 1)
    assert np.abs(got[1][H // 2:H].astype(int) - src[H // 2:].astype(int)).mean() < 8
