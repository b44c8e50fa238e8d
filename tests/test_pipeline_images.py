"""The full image pipeline (geometry → proposals → localise → tubes → score → select) on real
KITTI 0005 frames, through the `mine` command line, scored by the KITTI MOT protocol."""

from __future__ import annotations

import pytest


from mining.cli import main
from conftest import MODEL


def _run(kitti_tracking_root, tmp_path, capsys, *settings: str) -> dict:
    from mining.eval.kitti_mot import evaluate_kitti_mot

    out = tmp_path / "res"
    args = ["track", "images", "--dataset", "kitti", "--root", str(kitti_tracking_root), "--sequence", "0005",
            "--frames", "0:10", "--out", str(out), "--set", "export.observed_only=false"]
    for s in settings:
        args += ["--set", s]
    assert main(args) == 0
    assert "selected" in capsys.readouterr().out
    gt = tmp_path / "gt.txt"
    rows = [ln for ln in (kitti_tracking_root / "training" / "label_02" / "0005.txt").read_text().splitlines()
            if int(ln.split()[0]) < 10]
    gt.write_text("\n".join(rows) + "\n")
    seqmap = tmp_path / "seqmap"
    seqmap.write_text("0005 empty 000000 000010\n")
    return evaluate_kitti_mot({"0005": gt}, out, ["0005"], ("Car",), seqmap)["Car"]


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_onnx_pipeline_tracks_the_cars(kitti_tracking_root, tmp_path, capsys):
    model = MODEL
    assert model.exists()
    r = _run(kitti_tracking_root, tmp_path, capsys, 'proposals.proposer="onnx"', f'proposals.onnx.model_path="{model}"')
    assert r["HOTA"] > 0.6 and r["MOTA"] > 0.6 and r["IDSW"] == 0


def test_stereo_pipeline_finds_cars_without_classes(kitti_tracking_root, tmp_path, capsys):
    # The weight-free proposer has no classes: its tubes are scored class-agnostically as Car.
    r = _run(kitti_tracking_root, tmp_path, capsys, 'export.unclassified_as="Car"')
    assert r["TP"] > 0 and r["HOTA"] > 0.25
