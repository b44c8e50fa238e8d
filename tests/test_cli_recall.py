"""`mine eval recall` on real KITTI frames and on the real RobotCar labels."""

from __future__ import annotations

import json

import numpy as np
from pycocotools import mask as mask_utils

from mining.cli import main
from mining.formats.oxford_labels import read_oxford_labels


def test_recall_kitti_stereo(kitti_tracking_root, capsys):
    assert main(["eval", "recall", "--dataset", "kitti", "--root", str(kitti_tracking_root),
                 "--sequence", "0005", "--frames", "0:4"]) == 0
    out = capsys.readouterr().out
    known = [ln for ln in out.splitlines() if ln.strip().startswith("known")][0].split()
    assert int(known[1]) == 12  # 12 labelled cars in frames 0–3
    recall = [float(x) for x in known[2:]]
    assert recall == sorted(recall) and recall[-1] > 0.5


def test_recall_oxford_labels(oxford_data, tmp_path, capsys):
    labels = read_oxford_labels(oxford_data / "labels_4dgvt")
    # Proposals that are the labelled boxes themselves, minus every 'other' object in
    # alternate frames: known recall is 1, unknown recall is what was kept.
    kept_unknown = total_unknown = 0
    for k, lf in enumerate(labels):
        rel = lf.path.relative_to(lf.path.parents[1])
        items = []
        for box, known in zip(lf.boxes, lf.known):
            total_unknown += not known
            if not known and k % 2:
                continue
            kept_unknown += not known
            x1, y1, x2, y2 = box
            rle = mask_utils.frPyObjects(np.array([[x1, y1, x2 - x1 + 1, y2 - y1 + 1]], np.float64), 960, 1280)[0]
            items.append({"segmentation": {"size": rle["size"], "counts": rle["counts"].decode()},
                          "score": 0.9, "category_id": 1, "bbox": [float(x1), float(y1), float(x2 - x1), float(y2 - y1)]})
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(json.dumps(items))
    assert main(["eval", "recall", "--oxford-labels", str(oxford_data / "labels_4dgvt"),
                 "--proposals-json", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = {ln.split()[0]: ln.split()[1:] for ln in out.splitlines()[2:]}
    assert int(rows["known"][0]) == 1081 and int(rows["unknown"][0]) == 413
    assert float(rows["known"][-1]) == 1.0
    assert np.isclose(float(rows["unknown"][-1]), kept_unknown / total_unknown, atol=2e-3)
