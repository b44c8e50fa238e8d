#!/usr/bin/env bash
# Set up and run the main job on the embedded default: mine the synthetic dataset
# (jobs/synthetic.toml: sequence 0000, 500 frames) on a local Ray into ./out/catalog,
# then query the catalogue. Override the folder with OUT=...; extra arguments go to
# `mine submit` (e.g. --workers 2). Running it again resumes (a finished job does nothing).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh onnx,video

export RAY_USAGE_STATS_ENABLED=0
out="${OUT:-out}/catalog"
.venv/bin/mine submit --config jobs/synthetic.toml --out "$out" "$@"
.venv/bin/mine query --out "$out" \
  "SELECT category, known, count(*) AS tubes, round(avg(n_frames), 1) AS mean_frames, round(max(score), 1) AS best_score
   FROM selected_tubes GROUP BY ALL ORDER BY tubes DESC"
# The embedded default's proposer (stereo) has no classes: every tube is unclassified. Say what a
# classified catalogue adds, and the command that makes one.
if [ "$(.venv/bin/mine query --out "$out" --format csv "SELECT count(*) FROM tubes WHERE known IS NOT NULL" | tail -1)" = "0" ]; then
  cat <<'HINT'

Every tube above is unclassified: the stereo proposer finds objects without naming them. With a
COCO instance-segmentation model (a YOLOv8-seg ONNX file you provide; its weights are AGPL-3.0, not
bundled) each tube is also called known (one of the 80 classes, e.g. car) or unknown (an object none
of them describes: the discovery set), and `mine view` filters and labels them:

  OUT=out/classified scripts/main.sh --set proposals.proposer=onnx+stereo \
      --set proposals.onnx.model_path=/path/to/yolov8n-seg.onnx
  .venv/bin/mine view --out out/classified/catalog
HINT
fi
