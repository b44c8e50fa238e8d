"""The video and MOTS exports read back by the field's reference evaluator, TrackEval 1.3.0:
its own dataset classes (KittiMOTS, YouTubeVIS, TAO, BURST, BURST_OW), their config dicts
pointing at the export's files laid out as each expects. Each export's results file scored
against its own dataset file is perfect: HOTA 1 for every class that has tubes, and for the
class average (an empty category listed would pull that to 2/3, the reported bug). A damaged
copy of the results scores below 1, so the check can fail.

The catalogue is the real KITTI 0005 one (tests/_catalog_data.py) with its three selected
tubes made known (car), unknown and unclassified in turn, so every kind of category is read,
and a copy of them as a second sequence (``OTHER``), so ids must stay apart across videos.
"""

from __future__ import annotations

import json
import os
import shutil
import types
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from _catalog_data import DATASET, SEQUENCE
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.export import burst
from mining.export.run import run_export
from mining.formats.coco import COCO_CLASSES
from mining.formats.lvis import COCO_IN_LVIS, TAO_MAX_ID

trackeval = pytest.importorskip("trackeval")

OTHER = "0006"  # the second sequence: the same tubes again (KITTI-MOTS wants numeric sequence names)
EVAL_CONFIG = {"USE_PARALLEL": False, "PRINT_RESULTS": False, "PRINT_CONFIG": False, "TIME_PROGRESS": False,
               "OUTPUT_SUMMARY": False, "OUTPUT_DETAILED": False, "PLOT_CURVES": False, "DISPLAY_LESS_PROGRESS": True,
               "LOG_ON_ERROR": None}


@pytest.fixture(scope="module")
def kinds(catalogue, tmp_path_factory) -> Path:
    """A copy of the catalogue whose selected tubes are known (car), unknown and unclassified in
    turn, and the same tubes again as sequence OTHER."""
    out, tables = catalogue
    rows = tables["tubes"].to_pylist()
    selected = [r for r in rows if r["selected"]]
    assert len(selected) == 3
    for i, r in enumerate(selected):
        r["known"] = (True, False, None)[i]
        r["call"] = ("known", "unknown", "unclassified")[i]
        r["category"] = ("car", "unknown", None)[i]
    cat = tmp_path_factory.mktemp("kinds") / "cat"
    store = Store(cat)
    frames = tables["tube_frames"].to_pylist()
    for seq in (SEQUENCE, OTHER):
        def moved(r: dict) -> dict:
            return dict(r, sequence=seq, tube_id=r["tube_id"].replace(f"/{SEQUENCE}/", f"/{seq}/"))
        write_sequence(store, "tubes", DATASET, seq, pa.Table.from_pylist([moved(r) for r in rows],
                                                                          schema=SCHEMAS["tubes"]))
        write_sequence(store, "tube_frames", DATASET, seq, pa.Table.from_pylist([moved(r) for r in frames],
                                                                                schema=SCHEMAS["tube_frames"]))
    store.write_bytes("job.json", Store(out).read_bytes("job.json"))
    return cat


def _export(cat: Path, fmt: str, dest: Path, **kw) -> Path:
    assert run_export(str(cat), "selected", fmt, str(dest), **kw) == 0
    return dest


def _place(src: Path, folder: Path) -> Path:
    """``src`` copied into ``folder`` (made), the layout an evaluator reads; the copy."""
    folder.mkdir(parents=True, exist_ok=True)
    return Path(shutil.copy(src, folder))


def _evaluate(dataset_class, config: dict, work: Path) -> dict:
    """TrackEval's HOTA of tracker ``ours``: class → HOTA (averaged over its α thresholds, as
    TrackEval reports it), combined over the sequences."""
    dataset = dataset_class({**config, "PRINT_CONFIG": False, "TRACKERS_TO_EVAL": ["ours"],
                             "OUTPUT_FOLDER": str(work / "eval")})
    out, messages = trackeval.Evaluator(EVAL_CONFIG).evaluate([dataset], [trackeval.metrics.HOTA()])
    name = dataset.get_name()
    assert messages[name]["ours"] == "Success", messages
    return {cls: float(np.mean(m["HOTA"]["HOTA"])) for cls, m in out[name]["ours"]["COMBINED_SEQ"].items()}


def _perfect(hota: dict, classes: set[str]) -> None:
    per_class = {c: v for c, v in hota.items() if not c.startswith("cls_comb")}
    assert set(per_class) == classes, per_class
    for cls, v in hota.items():
        assert v == pytest.approx(1.0, abs=1e-9), (cls, hota)


def _drop_half(masks: list, empty) -> list:
    """A track's per-frame masks with every other present one replaced by ``empty``."""
    present = [k for k, m in enumerate(masks) if m]
    return [empty if k in present[::2] else m for k, m in enumerate(masks)]


# -- the facts the TAO and BURST categories rest on --------------------------------------


def test_the_lvis_table_is_taos_category_list():
    """Every synset and TAO id of mining/formats/lvis.py as TAO's list (TrackEval's copy) has
    them, and the TAO ids are exactly BURST-OW's 78 "known" (COCO) ids."""
    from trackeval.datasets.burst_helpers.burst_ow_base import BURST_OW_Base

    path = Path(trackeval.__file__).parent / "datasets" / "burst_helpers" / "tao_categories.json"
    tao = {c["id"]: c for c in json.loads(path.read_text())}
    assert max(tao) == TAO_MAX_ID == len(tao)
    assert tuple(COCO_IN_LVIS) == COCO_CLASSES
    for cls, (syn, cid, name) in COCO_IN_LVIS.items():
        if cid is None:
            assert syn not in {c["synset"] for c in tao.values()}, cls
        else:
            assert (tao[cid]["synset"], tao[cid]["name"]) == (syn, name), cls
    split = types.SimpleNamespace()
    BURST_OW_Base._split_known_unknown_distractor(split)
    assert {cid for _, cid, _ in COCO_IN_LVIS.values() if cid is not None} == split.knowns
    # our own BURST ids are "unknown" to BURST-OW, never known or distractors
    own = {*burst.OWN_IDS.values(), burst.OUTSIDE_TAO_BASE + 58, burst.OUTSIDE_TAO_BASE + 79}
    assert own <= split.unknowns and not own & set(tao)


# -- KITTI-MOTS ---------------------------------------------------------------------------


@pytest.mark.parametrize("unknown_class", [None, 3])
def test_kitti_mots_scores_itself_perfectly(kinds, tmp_path, unknown_class):
    """The KITTI-MOTS txt as TrackEval's KittiMOTS ground truth and tracker: car HOTA 1. The
    unknown and unclassified tubes are class 10 (ignore regions to it), or with
    ``--unknown-class 3`` class 3, which it reads and leaves out of car."""
    dest = _export(kinds, "kitti-mots", tmp_path / "mots", unknown_class=unknown_class)
    lengths = {}
    for seq in (SEQUENCE, OTHER):
        txt = dest / f"{seq}.txt"
        lines = txt.read_text().splitlines()
        assert {ln.split()[2] for ln in lines} == ({"1", "10"} if unknown_class is None else {"1", "3"})
        _place(txt, tmp_path / "gt" / "label_02")
        _place(txt, tmp_path / "trackers" / "ours" / "data")
        lengths[seq] = max(int(ln.split()[0]) for ln in lines) + 1
    config = {"GT_FOLDER": str(tmp_path / "gt"), "TRACKERS_FOLDER": str(tmp_path / "trackers"),
              "CLASSES_TO_EVAL": ["car"], "SEQ_INFO": lengths}
    _perfect(_evaluate(trackeval.datasets.KittiMOTS, config, tmp_path), {"car"})
    # a tracker that misses every other car frame is not perfect
    cars = [ln for ln in lines if ln.split()[2] == "1"]
    (tmp_path / "trackers" / "ours" / "data" / txt.name).write_text(
        "".join(ln + "\n" for ln in lines if ln not in cars[::2]))
    assert _evaluate(trackeval.datasets.KittiMOTS, config, tmp_path)["car"] < 0.9


# -- YouTube-VIS --------------------------------------------------------------------------


def test_youtube_vis_scores_itself_perfectly(kinds, tmp_path):
    dest = _export(kinds, "youtube-vis", tmp_path / "vis")
    _place(dest / "instances.json", tmp_path / "gt" / "youtube_vis_mined")
    results = _place(dest / "results" / "results.json", tmp_path / "trk" / "youtube_vis_mined" / "ours" / "data")
    config = {"GT_FOLDER": f"{tmp_path / 'gt'}{os.sep}", "TRACKERS_FOLDER": f"{tmp_path / 'trk'}{os.sep}",
              "SPLIT_TO_EVAL": "mined"}
    _perfect(_evaluate(trackeval.datasets.YouTubeVIS, config, tmp_path), {"car", "unknown", "unclassified"})
    tracks = json.loads(results.read_text())
    car = next(t for t in tracks if t["category_id"] == 3)
    car["segmentations"] = _drop_half(car["segmentations"], None)
    results.write_text(json.dumps(tracks))
    assert _evaluate(trackeval.datasets.YouTubeVIS, config, tmp_path)["car"] < 0.9


# -- TAO ----------------------------------------------------------------------------------


def test_tao_scores_itself_perfectly(kinds, tmp_path):
    dest = _export(kinds, "tao", tmp_path / "tao")
    doc = json.loads((dest / "tao.json").read_text())
    assert {c["name"]: c["synset"] for c in doc["categories"]} == {
        "car": "car.n.01", "unknown": "tube_miner.unknown", "unclassified": "tube_miner.unclassified"}
    _place(dest / "tao.json", tmp_path / "gt")
    results = _place(dest / "results" / "results.json", tmp_path / "trk" / "ours" / "data")
    config = {"GT_FOLDER": str(tmp_path / "gt"), "TRACKERS_FOLDER": str(tmp_path / "trk")}
    _perfect(_evaluate(trackeval.datasets.TAO, config, tmp_path), {"car", "unknown", "unclassified"})
    dets = json.loads(results.read_text())
    car = [d for d in dets if d["category_id"] == 3]
    results.write_text(json.dumps([d for d in dets if d not in car[::2]]))
    assert _evaluate(trackeval.datasets.TAO, config, tmp_path)["car"] < 0.9


# -- BURST --------------------------------------------------------------------------------


def _burst_folders(dest: Path, work: Path) -> tuple[dict, Path]:
    _place(dest / "burst.json", work / "gt")
    results = _place(dest / "results" / "results.json", work / "trk" / "ours" / "data")
    return {"GT_FOLDER": str(work / "gt"), "TRACKERS_FOLDER": str(work / "trk")}, results


def test_burst_scores_itself_perfectly(kinds, tmp_path):
    """Class-guided BURST reads TAO's categories: the car tube is TAO's car_(automobile); the
    unknown and unclassified tubes have ids outside TAO's, which it does not score."""
    dest = _export(kinds, "burst", tmp_path / "burst")
    doc = json.loads((dest / "burst.json").read_text())
    assert doc["split"] == "val" and [s["seq_name"] for s in doc["sequences"]] == [SEQUENCE, OTHER]
    for seq in doc["sequences"]:
        assert seq["track_category_ids"] == {"1": 211, "2": burst.UNKNOWN_ID, "3": burst.UNCLASSIFIED_ID}
    assert {c["id"]: c["synset"] for c in doc["categories"]}[211] == "car.n.01"
    config, results = _burst_folders(dest, tmp_path)
    _perfect(_evaluate(trackeval.datasets.BURST, config, tmp_path), {"car_(automobile)"})
    pred = json.loads(results.read_text())
    car = next(k for k, c in pred["sequences"][0]["track_category_ids"].items() if c == 211)
    segs = pred["sequences"][0]["segmentations"]
    for k in [k for k, s in enumerate(segs) if car in s][::2]:
        del segs[k][car]
    results.write_text(json.dumps(pred))
    assert _evaluate(trackeval.datasets.BURST, config, tmp_path)["car_(automobile)"] < 0.9


def test_burst_open_world_scores_every_tube_perfectly(kinds, tmp_path):
    """BURST-OW is class-agnostic: all three tubes, known, unknown and unclassified, are its "object"s."""
    dest = _export(kinds, "burst", tmp_path / "burst")
    config, _ = _burst_folders(dest, tmp_path)
    _perfect(_evaluate(trackeval.datasets.BURST_OW, config, tmp_path), {"object"})


def test_a_catalogue_of_cars_averages_over_car_alone(catalogue, tmp_path):
    """The reported bug: the old instances.json listed "unknown" and "unclassified" with no tube
    in them, and TrackEval's class average counted them as failed classes (HOTA 2/3 and less).
    Only the categories used are listed now."""
    out, _ = catalogue
    dest = _export(out, "youtube-vis", tmp_path / "vis")
    _place(dest / "instances.json", tmp_path / "gt" / "youtube_vis_cars")
    _place(dest / "results" / "results.json", tmp_path / "trk" / "youtube_vis_cars" / "ours" / "data")
    config = {"GT_FOLDER": f"{tmp_path / 'gt'}{os.sep}", "TRACKERS_FOLDER": f"{tmp_path / 'trk'}{os.sep}",
              "SPLIT_TO_EVAL": "cars"}
    _perfect(_evaluate(trackeval.datasets.YouTubeVIS, config, tmp_path), {"car"})


def test_burst_carries_the_frame_rate_and_its_image_layout(catalogue, tmp_path):
    """BURST's ``fps`` is the mined frames' rate: KITTI's 10 Hz from the catalogue's timestamps
    (the copy without a frames table has none, and leaves it out). ``--images`` puts each frame
    where BURST's paths point: ``frames/<split>/<dataset>/<seq_name>/<image path>``."""
    from mining.catalog.views import connect

    out, _ = catalogue
    con = connect(out)
    t_ns = [t for (t,) in con.execute("SELECT t_ns FROM frames ORDER BY frame").fetchall()]
    con.close()
    assert len(t_ns) == 16 and round(1e9 / np.median(np.diff(t_ns))) == 10
    dest = _export(out, "burst", tmp_path / "b", images=True)
    doc = json.loads((dest / "burst.json").read_text())
    assert [s["fps"] for s in doc["sequences"]] == [10]
    seq = doc["sequences"][0]
    folder = dest / "frames" / doc["split"] / seq["dataset"] / seq["seq_name"]
    assert sorted(p.name for p in folder.iterdir()) == seq["annotated_image_paths"] == [f"{k:06d}.jpg" for k in range(16)]


# -- a user's tag as the category -----------------------------------------------------------


TAG = "construction barrier"  # the README's example: no COCO class


@pytest.fixture(scope="module")
def tagged(kinds, tmp_path_factory) -> Path:
    """A copy of ``kinds`` whose unknown tubes the user tagged TAG (in both sequences)."""
    from mining.catalog import labels
    from mining.catalog.views import connect
    cat = tmp_path_factory.mktemp("tagged") / "cat"
    shutil.copytree(kinds, cat)
    con = connect(cat)
    try:
        ids = con.execute("SELECT dataset, sequence, tube_id FROM tubes WHERE selected AND call = 'unknown'").fetchall()
    finally:
        con.close()
    assert len(ids) == 2
    labels.append(Store(cat), labels.events([tuple(r) for r in ids], "tag", TAG))
    return cat


@pytest.mark.parametrize("fmt", ["youtube-vis", "tao", "burst"])
def test_a_tag_that_is_no_coco_class_is_a_category_of_its_own_the_reader_scores(tagged, tmp_path, fmt):
    """The README's workflow, label then export with ``--category-from tag``: a tag that is not a
    COCO class became a category of its own (it was refused, "not a COCO class"), listed by name,
    and the format's reader scores it: YouTube-VIS and TAO as a class of its own, BURST-OW as one
    of its "unknown" objects (class-guided BURST takes TAO's list, which cannot hold it)."""
    dest = _export(tagged, fmt, tmp_path / fmt, category_from="tag")
    if fmt == "youtube-vis":
        cats = json.loads((dest / "instances.json").read_text())["categories"]
        assert {"id": 2000, "name": TAG, "supercategory": "tag"} in cats
        _place(dest / "instances.json", tmp_path / "gt" / "youtube_vis_tagged")
        _place(dest / "results" / "results.json", tmp_path / "trk" / "youtube_vis_tagged" / "ours" / "data")
        config = {"GT_FOLDER": f"{tmp_path / 'gt'}{os.sep}", "TRACKERS_FOLDER": f"{tmp_path / 'trk'}{os.sep}",
                  "SPLIT_TO_EVAL": "tagged"}
        _perfect(_evaluate(trackeval.datasets.YouTubeVIS, config, tmp_path), {"car", TAG, "unclassified"})
    elif fmt == "tao":
        cats = json.loads((dest / "tao.json").read_text())["categories"]
        assert {"id": 2000, "name": TAG, "synset": f"tube_miner.tag:{TAG}"} in cats
        _place(dest / "tao.json", tmp_path / "gt")
        _place(dest / "results" / "results.json", tmp_path / "trk" / "ours" / "data")
        config = {"GT_FOLDER": str(tmp_path / "gt"), "TRACKERS_FOLDER": str(tmp_path / "trk")}
        _perfect(_evaluate(trackeval.datasets.TAO, config, tmp_path), {"car", TAG, "unclassified"})
    else:
        doc = json.loads((dest / "burst.json").read_text())
        assert {"id": burst.TAG_BASE, "name": TAG, "synset": f"tube_miner.tag:{TAG}"} in doc["categories"]
        assert all(s["track_category_ids"]["2"] == burst.TAG_BASE for s in doc["sequences"])
        config, _ = _burst_folders(dest, tmp_path)
        _perfect(_evaluate(trackeval.datasets.BURST_OW, config, tmp_path), {"object"})
