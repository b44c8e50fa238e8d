"""Precomputed proposers (4D-GVT JSON, KITTI detection files), union and the image-only filter,
on the real shared files of KITTI tracking 0005."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from mining.errors import InputError
from mining.eval.recall import kitti_ground_truth, recall_at_n
from mining.formats.coco import CATEGORY_ID_TO_INDEX, CLASS_INDEX, COCO_CATEGORY_IDS, COCO_CLASSES
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.localise.config import ProposalFilterConfig
from mining.masks import mask_iou
from mining.proposals.config import JsonProposalsConfig, KittiDetectionsConfig
from mining.proposals.precomputed import (
    JSON_PROPOSER, KITTI_PROPOSER, JsonProposals, KittiDetections, objectness_from_score, read_proposal_json,
)
from mining.proposals.union import filter_by_box_area_and_count, union
from mining.sources.kitti import KittiTrackingSource
from mining.types import N_CLASSES, UNKNOWN_CLASS, Proposals

W, H = 1242, 375
FRAMES = range(16)


@pytest.fixture(scope="module")
def json_root(shared_data):
    root = shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005"
    assert root.is_dir(), f"expected real data at {root}"
    return root


@pytest.fixture(scope="module")
def top20(json_root):
    reader = JsonProposals(json_root / "top20", image_size=(W, H))
    return [reader(f) for f in FRAMES]


@pytest.fixture(scope="module")
def top500(json_root):
    reader = JsonProposals(json_root / "top500", image_size=(W, H))
    return [reader(f) for f in FRAMES]


@pytest.fixture(scope="module")
def training(kitti_tracking_root):
    return kitti_tracking_root / "training"


@pytest.fixture(scope="module")
def pointrcnn(training):
    calib = KittiTrackingSource(training).kitti_calib("0005")
    return KittiDetections(training / "det_pointrcnn", "0005", calib, (W, H))


@pytest.fixture(scope="module")
def car_gt(training):
    rows = read_kitti_tracking(training / "label_02" / "0005.txt")
    return kitti_ground_truth(rows, FRAMES, {"Car"})


# -- COCO numbering -----------------------------------------------------------------


def test_coco_numbering():
    assert len(COCO_CLASSES) == 80 and len(set(COCO_CLASSES)) == 80
    assert len(set(COCO_CATEGORY_IDS)) == 80 and max(COCO_CATEGORY_IDS) == 90
    assert sorted(set(range(1, 91)) - set(COCO_CATEGORY_IDS)) == [12, 26, 29, 30, 45, 66, 68, 69, 71, 83]
    assert list(COCO_CATEGORY_IDS) == sorted(COCO_CATEGORY_IDS)
    assert CLASS_INDEX["person"] == 0 and CLASS_INDEX["bicycle"] == 1 and CLASS_INDEX["car"] == 2
    assert COCO_CLASSES[CATEGORY_ID_TO_INDEX[90]] == "toothbrush"
    assert COCO_CLASSES[CATEGORY_ID_TO_INDEX[13]] == "stop sign"


# -- 4D-GVT JSON --------------------------------------------------------------------


def test_json_counts_match_the_readme(top20, top500):
    n20 = [len(p) for p in top20]
    assert min(n20) >= 18 and max(n20) <= 26  # README: 18–26 per frame
    assert np.mean(n20) == pytest.approx(20.6, abs=0.05)  # README: mean 20.6
    assert all(len(p) == 500 for p in top500)  # README: exactly 500


@pytest.mark.parametrize("which", ["top20", "top500"])
def test_json_rows_agree_with_the_file(json_root, which, request):
    props = request.getfixturevalue(which)
    for f in (0, 7, 15):
        p = props[f]
        raw = json.loads((json_root / which / f"{f:06d}.json").read_text())
        scores = np.array([r["score"] for r in raw])
        assert p.proposer == [JSON_PROPOSER] * len(raw)
        np.testing.assert_allclose(p.objectness, np.sort(scores)[::-1], rtol=1e-6)
        assert np.all(np.diff(p.objectness) <= 0)
        assert p.posterior.shape == (len(raw), N_CLASSES) and p.posterior.dtype == np.float32
        np.testing.assert_allclose(p.posterior.sum(axis=1), 1.0, atol=1e-5)
        assert (p.posterior >= 0).all()
        # Row by row against the raw element (file order equals score order here).
        assert np.all(np.diff(scores) <= 0)
        for i in (0, len(raw) // 2, len(raw) - 1):
            vals = raw[i]["second_posterior"]["values"]
            total = sum(vals.values())
            for key, v in vals.items():
                col = UNKNOWN_CLASS if key == "0" else int(key) - 1
                assert p.posterior[i, col] == pytest.approx(v / total, rel=1e-5)
            assert int(p.posterior[i, :80].argmax()) + 1 == raw[i]["second_category_id"]
            x, y, w, h = raw[i]["bbox"]
            np.testing.assert_allclose(p.boxes[i], [x, y, x + w, y + h])
            assert p.rles[i]["counts"].decode() == raw[i]["segmentation"]["counts"]


@pytest.mark.parametrize("which", ["top20", "top500"])
def test_json_masks_decode_to_the_frame(which, request):
    props = request.getfixturevalue(which)
    for f in (0, 15):
        p = props[f]
        sel = list(range(min(len(p), 40))) + list(range(max(0, len(p) - 10), len(p)))
        masks = mask_utils.decode([p.rles[i] for i in sel])
        assert masks.shape == (H, W, len(sel))
        assert (masks.reshape(-1, len(sel)).sum(axis=0) > 0).all()
        # The box is the mask's box (README: bbox from the mask).
        mb = mask_utils.toBbox([p.rles[i] for i in sel])
        np.testing.assert_allclose(p.boxes[sel, :2], mb[:, :2], atol=1e-3)
        np.testing.assert_allclose(p.boxes[sel, 2:], mb[:, :2] + mb[:, 2:], atol=1e-3)


def test_json_top_proposal_is_a_car(top20):
    # The four Car tracks dominate 0005; the best proposal of each frame should say car.
    cars = [int(p.posterior[0].argmax()) == CLASS_INDEX["car"] for p in top20]
    assert np.mean(cars) >= 0.9


def test_json_car_recall(top20, top500, car_gt):
    boxes, known = car_gt
    assert sum(len(b) for b in boxes) == 52  # SOURCES.md §1.2
    for props in (top20, top500):
        r = recall_at_n(props, boxes, known)
        rec = [r["known"][n] for n in sorted(r["known"])]
        assert np.all(np.diff(rec) >= 0)  # monotone in N
        assert r["known"][500] >= 0.95  # measured: 1.0 for both
        assert r["known"][1] < r["known"][500]  # one proposal cannot hold 3+ cars
        assert r["known"][1] <= 16 / 52 + 1e-9  # at most one hit per frame at N = 1
        assert r["n_unknown"] == 0 and np.isnan(r["unknown"][20])
    # A stricter overlap separates the two sets: the 500 reach boxes the 20 miss.
    strict20 = recall_at_n(top20, boxes, known, ns=(500,), iou=0.7)["known"][500]
    strict500 = recall_at_n(top500, boxes, known, ns=(500,), iou=0.7)["known"][500]
    assert strict500 >= strict20


def test_json_category_ids_without_posterior(json_root, tmp_path):
    raw = json.loads((json_root / "top20" / "000000.json").read_text())
    for r in raw:
        del r["second_posterior"]
    raw[0]["category_id"] = 3  # COCO id 3 = car
    raw[1]["category_id"] = 13  # COCO id 13 = stop sign (contiguous 11)
    (tmp_path / "000000.json").write_text(json.dumps(raw))
    agnostic = JsonProposals(tmp_path)(0)
    assert agnostic.posterior is None and len(agnostic) == len(raw)
    coco = JsonProposals(tmp_path, JsonProposalsConfig(category_ids="coco"))(0)
    assert coco.posterior[0, CLASS_INDEX["car"]] == pytest.approx(raw[0]["score"], rel=1e-6)
    assert coco.posterior[0, UNKNOWN_CLASS] == pytest.approx(1 - raw[0]["score"], rel=1e-6)
    assert coco.posterior[1, CLASS_INDEX["stop sign"]] == pytest.approx(raw[1]["score"], rel=1e-6)
    np.testing.assert_allclose(coco.posterior.sum(axis=1), 1.0, atol=1e-6)


def _bad_json(json_root, tmp_path, edit) -> str:
    raw = json.loads((json_root / "top20" / "000004.json").read_text())
    text = edit(raw)
    (tmp_path / "000004.json").write_text(text if isinstance(text, str) else json.dumps(text, indent=1))
    with pytest.raises(InputError) as e:
        JsonProposals(tmp_path, image_size=(W, H))(4)
    assert e.value.frame == 4 and e.value.path == str(tmp_path / "000004.json")
    return str(e.value)


def test_json_bad_input(json_root, tmp_path):
    # Malformed JSON: a line cut in half.
    def truncate(raw):
        lines = json.dumps(raw, indent=1).splitlines()
        lines[10] = lines[10][:5]
        return "\n".join(lines)

    assert "line 11" in _bad_json(json_root, tmp_path, truncate)

    def no_score(raw):
        del raw[2]["score"]
        return raw

    assert "element 2" in _bad_json(json_root, tmp_path, no_score)

    def score_too_big(raw):
        raw[1]["score"] = 3.5
        return raw

    assert "score" in _bad_json(json_root, tmp_path, score_too_big)

    def mixed_posterior(raw):
        del raw[3]["second_posterior"]
        return raw

    assert "second_posterior" in _bad_json(json_root, tmp_path, mixed_posterior)

    def wrong_size(raw):
        for r in raw:
            r["segmentation"]["size"] = [370, 1224]
        return raw

    assert "image size" in _bad_json(json_root, tmp_path, wrong_size)

    def bad_index(raw):
        raw[0]["second_posterior"]["values"]["81"] = 0.1
        return raw

    assert "81" in _bad_json(json_root, tmp_path, bad_index)

    (tmp_path / "000005.json").write_text("[]")  # a frame without proposals is valid
    empty = JsonProposals(tmp_path)(5)
    assert len(empty) == 0 and empty.boxes.shape == (0, 4) and empty.posterior.shape == (0, N_CLASSES)

    with pytest.raises(InputError, match="missing") as e:
        JsonProposals(json_root / "top20")(16)
    assert e.value.frame == 16



# -- 4D-GVT JSON: bounded inputs and malformed files -------------------------------


def _many_proposals(json_root, folder, n: int, posterior: bool) -> list[float]:
    """Write ``folder/000000.json``: ``n`` copies of one real proposal of frame 0 (with or
    without its second_posterior), each with its own score; return the scores in file order.
    The scores have three decimals, so ties occur and file order must break them."""
    raw = json.loads((json_root / "top500" / "000000.json").read_text())
    one = next(r for r in raw if len(r["segmentation"]["counts"]) <= 40)
    if not posterior:
        del one["second_posterior"]
    head, tail = json.dumps({**one, "score": 0.123456789}, separators=(",", ":")).split("0.123456789")
    scores = np.random.default_rng(0).integers(0, 1000, n) / 1000
    folder.mkdir(exist_ok=True)
    (folder / "000000.json").write_text("[" + ",\n".join(f"{head}{s!r}{tail}" for s in scores.tolist()) + "]")
    return scores.tolist()


def test_json_file_over_the_size_bound_is_refused(json_root, tmp_path):
    real = (json_root / "top20" / "000003.json").read_text()
    (tmp_path / "000003.json").write_text(real)
    size = len(real.encode())
    assert len(JsonProposals(tmp_path, JsonProposalsConfig(max_file_bytes=size))(3)) > 0
    with pytest.raises(InputError, match="max_file_bytes") as e:
        JsonProposals(tmp_path, JsonProposalsConfig(max_file_bytes=size - 1))(3)
    assert e.value.path == str(tmp_path / "000003.json") and e.value.frame == 3
    # The default bound: a valid list of real proposals padded with whitespace past it.
    limit = JsonProposalsConfig().max_file_bytes
    assert limit > 100 * max(f.stat().st_size for f in json_root.glob("*/*.json"))  # well above real files
    (tmp_path / "000003.json").write_text(real[:-1] + " " * limit + "]")
    with pytest.raises(InputError, match=f"over proposals.json.max_file_bytes = {limit}") as e:
        JsonProposals(tmp_path)(3)
    assert e.value.path == str(tmp_path / "000003.json") and e.value.frame == 3


# 400,000: the reported file's count (~5 s to parse on two loaded cores); 20,000 for the fast tier.
@pytest.mark.parametrize("n", [20_000, pytest.param(400_000, marks=pytest.mark.slow)])
def test_json_many_proposals_keep_the_best_before_any_mask_is_decoded(json_root, tmp_path, monkeypatch, n):
    import mining.proposals.precomputed as precomputed

    scores = _many_proposals(json_root, tmp_path, n, posterior=False)
    assert (tmp_path / "000000.json").stat().st_size < JsonProposalsConfig().max_file_bytes
    checked = []  # each mask whose runs are checked is one about to be decoded

    def counting(sizes, counts):
        checked.extend(counts)
        return real_check(sizes, counts)

    real_check = precomputed.batch_rle_problems
    monkeypatch.setattr(precomputed, "batch_rle_problems", counting)
    monkeypatch.setattr(precomputed.mask_utils, "toBbox", lambda *a: pytest.fail("a mask decoded for its box"))
    k = JsonProposalsConfig().max_proposals
    p = JsonProposals(tmp_path, image_size=(W, H))(0)
    assert len(p) == k == len(checked) and len(p.rles) == len(p.boxes) == k
    # The best by score, ties in file order: what a stable sort of all of them gives first.
    order = np.argsort(-np.asarray(scores), kind="stable")[:k]
    np.testing.assert_array_equal(p.objectness, np.asarray(scores, np.float32)[order])
    # On a real file: the top k of it are the first k of reading it whole.
    full = read_proposal_json(json_root / "top500" / "000009.json", 9)
    top = read_proposal_json(json_root / "top500" / "000009.json", 9, max_proposals=20)
    np.testing.assert_array_equal(top.objectness, full.objectness[:20])
    np.testing.assert_array_equal(top.boxes, full.boxes[:20])
    np.testing.assert_array_equal(top.posterior, full.posterior[:20])
    assert top.rles == full.rles[:20]


@pytest.mark.slow  # writes and reads a 170 MB file
def test_json_reading_400000_proposals_keeps_memory_flat(json_root, tmp_path):
    # The reported case: 400,000 real proposals with their posteriors, ~170 MB. Refused by
    # default; with the size bound raised past it, read in a child process whose peak
    # resident memory is measured (reading it whole took 1.5 GB, the worker after it 19.6 GB).
    import subprocess
    import sys

    from _run import env

    _many_proposals(json_root, tmp_path, 400_000, posterior=True)
    size = (tmp_path / "000000.json").stat().st_size
    with pytest.raises(InputError, match="max_file_bytes"):
        JsonProposals(tmp_path)(0)
    code = (
        "import sys\n"
        "from mining.proposals.config import JsonProposalsConfig\n"
        "from mining.proposals.precomputed import JsonProposals\n"
        f"p = JsonProposals(sys.argv[1], JsonProposalsConfig(max_file_bytes={2 * size}), image_size=({W}, {H}))(0)\n"
        # VmHWM, not ru_maxrss: Linux carries ru_maxrss across exec, so a child forked from a large
        # pytest process reports the parent's peak; VmHWM belongs to the child's own address space.
        "hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\n"
        "print(len(p), int(hwm) // 1024)\n"
    )
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, env=env(),
                         timeout=300)
    assert out.returncode == 0, out.stderr
    n, peak_mib = map(int, out.stdout.split())
    assert n == JsonProposalsConfig().max_proposals
    assert peak_mib < 1024, f"peak RSS {peak_mib} MiB reading a {size >> 20} MiB file"



def _bad_counts(counts):
    def edit(raw):
        raw[0]["segmentation"]["counts"] = counts
        return raw

    return edit


def test_json_malformed_counts_is_one_input_error(json_root, tmp_path):
    # A run past the frame's end (pycocotools' decoders read past the mask for it: the
    # observe step raised IndexError), a number cut off, runs that stop short, non-ASCII.
    past_end = mask_utils.frPyObjects({"size": [H, W], "counts": [1000, 15_255_089]}, H, W)["counts"].decode()
    real = json.loads((json_root / "top20" / "000004.json").read_text())[0]["segmentation"]["counts"]
    for counts in (past_end, real + "e", real[: len(real) // 2], "é" + real):
        text = _bad_json(json_root, tmp_path, _bad_counts(counts))
        assert "element 0: malformed segmentation" in text, text
    assert "runs do not cover exactly 1242x375 pixels" in _bad_json(json_root, tmp_path, _bad_counts(past_end))


def test_json_deep_nesting_and_wrong_shapes_are_input_errors(json_root, tmp_path):
    deep = 100_000  # past Python's recursion limit, for the standard library's parser too
    assert "nested too deeply" in _bad_json(json_root, tmp_path, lambda raw: "[" * deep + "]" * deep)

    def deep_in_an_element(raw):
        return json.dumps(raw)[:-1] + ', {"score": 0.5, "x": ' + "[" * deep + "]" * deep + "}]"

    assert "nested too deeply" in _bad_json(json_root, tmp_path, deep_in_an_element)

    def superscript_index(raw):  # "²".isdigit() holds, int("²") raises
        raw[0]["second_posterior"]["values"]["²"] = 0.1
        return raw

    assert "malformed proposal file (ValueError" in _bad_json(json_root, tmp_path, superscript_index)
    assert "expected a JSON list" in _bad_json(json_root, tmp_path, lambda raw: {"proposals": raw})
    assert "line 1" in _bad_json(json_root, tmp_path, lambda raw: json.dumps(raw) + " []")  # extra data
    assert "bbox" in _bad_json(json_root, tmp_path, lambda raw: [{**raw[0], "bbox": [1, 2, 3]}] + raw[1:])


def test_a_malformed_proposal_file_fails_the_observe_step_naming_file_and_frame(json_root, kitti_tracking_root,
                                                                              tmp_path, capsys):
    from _run import cli

    props = tmp_path / "props"
    props.mkdir()
    for f in range(2):
        raw = json.loads((json_root / "top20" / f"{f:06d}.json").read_text())
        if f == 0:
            raw[0]["segmentation"]["counts"] = mask_utils.frPyObjects(
                {"size": [H, W], "counts": [1000, 15_255_089]}, H, W)["counts"].decode()
        (props / f"{f:06d}.json").write_text(json.dumps(raw))
    rc, out, err = cli(capsys, "track", "images", "--dataset", "kitti", "--root", str(kitti_tracking_root),
                       "--sequence", "0005", "--frames", "0:2", "--out", str(tmp_path / "res"),
                       "--set", 'proposals.proposer="json"', "--set", f'proposals.json.folder="{props}"')
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"file {props / '000000.json'}, frame 0: element 0: malformed segmentation" in err


# -- KITTI detection files ----------------------------------------------------------


def test_pointrcnn_reads_every_line(pointrcnn, training):
    lines = sum(len((training / "det_pointrcnn" / c / "0005.txt").read_text().split()) for c in
                ("Car", "Pedestrian", "Cyclist"))
    assert lines == 2099  # SOURCES.md §1.1
    served = sum(len(pointrcnn(f)) for f in range(297))
    assert lines - 20 <= served <= lines  # only boxes entirely outside the image are dropped
    assert len(pointrcnn(296)) >= 0 and len(pointrcnn(5000)) == 0


def test_pointrcnn_masks_are_the_clipped_boxes(pointrcnn):
    for f in FRAMES:
        p = pointrcnn(f)
        assert len(p) > 0
        assert p.proposer == [KITTI_PROPOSER] * len(p)
        assert (p.boxes[:, :2] >= 0).all() and (p.boxes[:, 2] <= W).all() and (p.boxes[:, 3] <= H).all()
        masks = mask_utils.decode(p.rles)
        assert masks.shape == (H, W, len(p))
        for i in range(len(p)):
            ys, xs = np.nonzero(masks[:, :, i])
            x1, y1, x2, y2 = p.boxes[i]
            # pixel centres inside the box
            assert xs.min() == np.ceil(x1 - 0.5) and xs.max() == np.floor(x2 - 0.5)
            assert ys.min() == np.ceil(y1 - 0.5) and ys.max() == np.floor(y2 - 0.5)
            assert len(xs) == (xs.max() - xs.min() + 1) * (ys.max() - ys.min() + 1)


def test_pointrcnn_3d_centre_projects_into_its_box(pointrcnn, training):
    stereo = KittiTrackingSource(training).calib("0005")  # image_02 camera
    inside, total, err = 0, 0, []
    for f in range(0, 297, 3):
        p = pointrcnn(f)
        if len(p) == 0:
            continue
        assert np.isfinite(p.position).all() and (p.size > 0).all()
        uv = stereo.project(p.position.astype(np.float64))
        b = p.boxes
        inside += int(((uv >= b[:, :2]) & (uv <= b[:, 2:])).all(axis=1).sum())
        total += len(p)
        err += list(np.abs(uv[:, 1] - (b[:, 1] + b[:, 3]) / 2) / (b[:, 3] - b[:, 1]))
    assert total > 500
    assert inside / total >= 0.9  # measured 0.968 (688 detections)
    # The bottom-centre → centre shift matters: the vertical offset is a small part of the box height.
    assert np.median(err) < 0.15  # measured 0.02; without the shift 0.45


def test_pointrcnn_position_is_in_the_image_02_frame(pointrcnn, training):
    # Project the file's own numbers with P2 (rectified camera 0 → image_02 pixels) and compare
    # with our image_02-frame position projected by the image_02 StereoCalib: exact agreement
    # needs both the bottom-to-centre shift and the camera-0 → camera-2 offset.
    kc = KittiTrackingSource(training).kitti_calib("0005")
    stereo = KittiTrackingSource(training).calib("0005")
    table = np.loadtxt(training / "det_pointrcnn" / "Car" / "0005.txt", delimiter=",")
    rows = table[table[:, 0] == 10]
    p = pointrcnn(10)
    raw = pointrcnn.raw_scores(10)
    for r in rows:
        i = int(np.flatnonzero(np.isclose(raw, r[6]))[0])
        centre = r[10:13] - [0, r[7] / 2, 0]
        uvw = kc.P2 @ np.append(centre, 1.0)
        np.testing.assert_allclose(stereo.project(p.position[i : i + 1].astype(np.float64))[0], uvw[:2] / uvw[2],
                                   atol=0.01)
        np.testing.assert_allclose(p.size[i], [r[8], r[7], r[9]], rtol=1e-6)
        np.testing.assert_allclose(p.position[i, 2], centre[2] + kc.t_cam2[2], atol=1e-4)


def test_pointrcnn_objectness_and_posterior(pointrcnn):
    raw, obj = [], []
    for f in range(297):
        p = pointrcnn(f)
        r = pointrcnn.raw_scores(f)
        assert len(r) == len(p)
        assert np.all(np.diff(r) <= 0)  # best first
        if len(p) == 0:
            continue
        assert ((p.objectness > 0) & (p.objectness < 1)).all()
        np.testing.assert_allclose(p.posterior.sum(axis=1), 1.0, atol=1e-6)
        cls = p.posterior[:, :80].argmax(axis=1)
        assert set(cls.tolist()) <= {CLASS_INDEX["person"], CLASS_INDEX["bicycle"], CLASS_INDEX["car"]}
        # the class is the detector's decision (one-hot); whether the detection exists is objectness
        assert (p.posterior[:, :80].max(axis=1) == 1.0).all() and (p.posterior[:, 80] == 0).all()
        raw.append(r)
        obj.append(p.objectness)
    raw, obj = np.concatenate(raw), np.concatenate(obj)
    order = np.argsort(raw, kind="stable")
    assert np.all(np.diff(obj[order]) >= 0)  # monotone in the raw score
    assert raw.min() < KittiDetectionsConfig().score_offset < raw.max()
    assert objectness_from_score(np.array([KittiDetectionsConfig().score_offset]), KittiDetectionsConfig())[0] == 0.5


def test_regionlets_result_format(training):
    calib = KittiTrackingSource(training).kitti_calib("0005")
    reg = KittiDetections(training / "det_02_regionlets", "0005", calib, (W, H))
    assert reg.frames() == list(FRAMES)
    n = sum(len(reg(f)) for f in FRAMES)
    assert 1400 <= n <= 1441  # SOURCES.md §1.5: 1,441 lines
    p = reg(0)
    assert np.isnan(p.position).all() and np.isnan(p.size).all()  # placeholders, no 3D
    raws = np.concatenate([reg.raw_scores(f) for f in FRAMES])
    assert raws.min() == pytest.approx(-9.16, abs=0.01) and raws.max() == pytest.approx(17.60, abs=0.01)


def test_reading_a_long_sequence_is_fast(training):
    calib = KittiTrackingSource(training).kitti_calib("0019")
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        det = KittiDetections(training / "det_pointrcnn", "0019", calib, (1238, 374))
        best = min(best, time.perf_counter() - t)
    assert len(det.frames()) > 1000
    assert best < 0.5  # 13,445 lines; measured ≈ 0.05 s


def test_detections_bad_input(training, tmp_path):
    calib = KittiTrackingSource(training).kitti_calib("0005")
    lines = (training / "det_pointrcnn" / "Car" / "0005.txt").read_text().splitlines()[:10]

    def fails(text: str, name: str = "0005.txt") -> InputError:
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(InputError) as e:
            KittiDetections(path, "0005", calib, (W, H))
        assert e.value.path == str(path)
        return e.value

    short = list(lines)
    short[2] = short[2].rsplit(",", 1)[0]  # 14 columns
    e = fails("\n".join(short))
    assert "line 3" in e.reason and e.frame == int(lines[2].split(",")[0])

    word = list(lines)
    word[4] = word[4].replace(",2,", ",car,", 1)
    e = fails("\n".join(word))
    assert "line 5" in e.reason

    code = list(lines)
    code[6] = code[6].replace(",2,", ",7,", 1)
    assert "line 7" in fails("\n".join(code)).reason

    labels = (training / "label_02" / "0005.txt").read_text().splitlines()[:5]  # 17 columns, no score
    assert "18" in fails("\n".join(labels), "labels.txt").reason

    with pytest.raises(InputError, match="no 0099.txt"):
        KittiDetections(training / "det_pointrcnn", "0099", calib, (W, H))


# -- union and filter ---------------------------------------------------------------


def test_cat_and_take_are_inverse(top20, pointrcnn):
    a, b = top20[3], pointrcnn(3)
    c = Proposals.cat([a, b])
    assert len(c) == len(a) + len(b) and c.proposer == a.proposer + b.proposer
    # The JSON proposer has classes and no 3D, PointRCNN both: missing fields are NaN rows.
    assert np.isnan(c.position[: len(a)]).all() and np.isnan(c.size[: len(a)]).all()
    np.testing.assert_array_equal(c.posterior[: len(a)], a.posterior)
    for part, rows in ((a, np.arange(len(a))), (b, len(a) + np.arange(len(b)))):
        back = c.take(rows)
        assert back.rles == part.rles and back.proposer == part.proposer
        np.testing.assert_array_equal(back.boxes, part.boxes)
        np.testing.assert_array_equal(back.objectness, part.objectness)
    mask = np.zeros(len(c), bool)
    mask[len(a):] = True
    np.testing.assert_array_equal(c.take(mask).position, b.position)
    assert Proposals.cat([a]).posterior.dtype == np.float32 and Proposals.cat([a]).position is None
    with pytest.raises(ValueError):
        Proposals.cat([a, pointrcnn(4)])


def test_union_of_json_and_pointrcnn(top20, pointrcnn):
    thr = 0.5
    merged_any = False
    for f in FRAMES:
        a, b = top20[f], pointrcnn(f)
        u = union([a, b], thr)
        assert len(u) <= len(a) + len(b)
        merged_any |= len(u) < len(a) + len(b)
        assert JSON_PROPOSER in set(u.proposer) <= {JSON_PROPOSER, KITTI_PROPOSER}
        assert np.all(np.diff(u.objectness) <= 0)
        # The other order lets the detector's boxes win, and keeps JSON masks it lacks.
        assert KITTI_PROPOSER in set(union([b, a], thr).proposer)
        np.testing.assert_allclose(u.posterior.sum(axis=1), 1.0, atol=1e-5)
        # Rows keep their proposer's fields: JSON rows have no 3D, PointRCNN rows do.
        is_kitti = np.array(u.proposer) == KITTI_PROPOSER
        assert np.isnan(u.position[~is_kitti]).all() and np.isfinite(u.position[is_kitti]).all()
        # No two kept rows of different proposers are the same object.
        iou = mask_iou(u.rles, u.rles)
        cross = is_kitti[:, None] != is_kitti[None, :]
        assert (iou[cross] <= thr).all()
        # Every dropped row lost to a kept row of the earlier proposer (the first one listed
        # wins duplicates); rows of the first proposer are never dropped.
        kept = {r["counts"] for r in u.rles}
        assert all(r["counts"] in kept for r in a.rles)
        gone = [i for i in range(len(b)) if b.rles[i]["counts"] not in kept]
        if gone:
            iou_g = mask_iou([b.rles[i] for i in gone], [u.rles[j] for j in np.flatnonzero(~is_kitti)])
            assert (iou_g.max(axis=1) > thr).all()
    assert merged_any


def test_union_marks_missing_classes_as_nan(top20, pointrcnn, json_root, tmp_path):
    raw = json.loads((json_root / "top20" / "000002.json").read_text())
    for r in raw:
        del r["second_posterior"]
    (tmp_path / "000002.json").write_text(json.dumps(raw))
    agnostic = read_proposal_json(tmp_path / "000002.json", 2)
    u = union([agnostic, pointrcnn(2)], 0.5)
    rows = np.array(u.proposer) == JSON_PROPOSER
    assert rows.any()
    assert np.isnan(u.posterior[rows]).all()
    assert np.isfinite(u.posterior[~rows]).all()
    with pytest.raises(InputError):
        union([top20[0], pointrcnn(1)], 0.5)


def test_filter_by_box_area_and_count(top500):
    cfg = ProposalFilterConfig()
    for f in (0, 9):
        p = top500[f]
        q = filter_by_box_area_and_count(p, cfg.min_box_area_px, cfg.max_proposals)
        area = lambda b: (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])  # noqa: E731
        assert len(q) == min(cfg.max_proposals, int((area(p.boxes) >= cfg.min_box_area_px).sum()))
        assert (area(q.boxes) >= cfg.min_box_area_px).all()
        assert (area(p.boxes) < cfg.min_box_area_px).any()  # the filter had something to do
        assert np.all(np.diff(q.objectness) <= 0)
        big = p.objectness[area(p.boxes) >= cfg.min_box_area_px]
        np.testing.assert_array_equal(q.objectness, np.sort(big)[::-1][: cfg.max_proposals])
        assert q.posterior.shape == (len(q), N_CLASSES)


def test_union_gives_uncovered_agnostic_rows_unknown_weighted_by_detectability(top20, pointrcnn, json_root, tmp_path):
    """onnx+stereo's rule on real proposals: class-agnostic JSON rows + the PointRCNN classifier."""
    from mining.proposals.config import UnionConfig
    from mining.proposals.union import detectability
    from mining.types import UNKNOWN_CLASS

    raw = json.loads((json_root / "top20" / "000002.json").read_text())
    for r in raw:
        del r["second_posterior"]
    (tmp_path / "000002.json").write_text(json.dumps(raw))
    agnostic = read_proposal_json(tmp_path / "000002.json", 2)
    cfg = UnionConfig()
    det = pointrcnn(2)
    u = union([det, agnostic], 0.5, cfg)
    rows = np.array(u.proposer) == JSON_PROPOSER
    assert rows.any() and (~rows).any()
    # uncovered agnostic rows: all mass on unknown, weight = P(the detector finds an object that tall)
    assert (u.posterior[rows, UNKNOWN_CLASS] == 1).all() and (u.posterior[rows, :UNKNOWN_CLASS] == 0).all()
    h = u.boxes[rows, 3] - u.boxes[rows, 1]
    np.testing.assert_allclose(u.class_weight[rows], detectability(h, cfg), rtol=1e-6)
    # the classifier's own rows keep their posterior at full weight
    np.testing.assert_array_equal(u.class_weight[~rows], 1.0)
    np.testing.assert_allclose(u.posterior[~rows].sum(axis=1), 1.0, atol=1e-6)
    # detectability rises with size, through 1/2 at detect_h50_px
    assert detectability(np.array([cfg.detect_h50_px]), cfg)[0] == pytest.approx(0.5)
    assert np.all(np.diff(detectability(np.array([5.0, 10, 20, 40, 80]), cfg)) > 0)
    # without a classifier in the union nothing is classified
    alone = union([agnostic, agnostic.take(np.arange(0))], 0.5, cfg)
    assert np.isnan(alone.posterior).all() if alone.posterior is not None else True
    assert (alone.class_weights() == 0).all()


def test_union_keeps_the_mask_that_agrees_with_the_objects_depth():
    """Renderer truth: a learned mask bleeding onto the background loses to the exact one."""
    import cv2
    from pycocotools import mask as mask_utils

    from mining.proposals.config import UnionConfig
    from mining.proposals.union import depth_agreement
    from mining.sources import open_source
    from mining.types import Proposals

    src = open_source("synthetic", None, n_frames=5)
    plan = src.plan("0000")
    frame = src.read_frame(plan, 2)
    truth = frame.truth
    medium = [o for o in truth.objects if o.known and 2_000 < o.mask.sum() < 40_000]
    assert medium, "the synthetic frame has a mid-sized known object"
    obj = max(medium, key=lambda o: o.mask.sum())
    bf = plan.calib.fx * plan.calib.baseline_m
    disparity = (bf / truth.depth).astype(np.float32)
    exact = obj.mask.astype(np.uint8)
    k = max(9, int(np.sqrt(exact.sum()) / 1.5))
    bleed = cv2.dilate(exact, np.ones((k, k), np.uint8))  # spills onto whatever lies behind
    assert bleed.sum() > 1.5 * exact.sum()
    rle = lambda m: mask_utils.encode(np.asfortranarray(m))  # noqa: E731
    a, b = depth_agreement(rle(bleed), rle(exact), disparity, UnionConfig(), bf)
    assert b > a + UnionConfig().better_mask_margin
    box = lambda m: np.array(mask_utils.toBbox(rle(m)), np.float32) @ np.array([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)  # noqa: E731  xywh → x1y1x2y2
    post = np.zeros((1, 81), np.float32)
    post[0, 2] = 1
    learned = Proposals(frame.index, [rle(bleed)], box(bleed)[None], np.array([0.9], np.float32), post, ["onnx"])
    stereo = Proposals(frame.index, [rle(exact)], box(exact)[None], np.array([0.5], np.float32), None, ["stereo"])
    on = UnionConfig(better_mask=True)  # off by default (mine bench classify); the rule itself is tested here
    u = union([learned, stereo], 0.3, on, disparity, truth.depth)
    assert len(u) == 1 and u.proposer == ["onnx"] and u.posterior[0, 2] == 1  # the learned row's class stands...
    assert mask_utils.iou([u.rles[0]], [rle(exact)], [0])[0, 0] == pytest.approx(1.0)  # ...with the better mask
    # and the other way round: an exact learned mask is kept over a stereo mask that bled
    learned2 = Proposals(frame.index, [rle(exact)], box(exact)[None], np.array([0.9], np.float32), post, ["onnx"])
    stereo2 = Proposals(frame.index, [rle(bleed)], box(bleed)[None], np.array([0.5], np.float32), None, ["stereo"])
    u2 = union([learned2, stereo2], 0.3, on, disparity, truth.depth)
    assert mask_utils.iou([u2.rles[0]], [rle(exact)], [0])[0, 0] == pytest.approx(1.0)
