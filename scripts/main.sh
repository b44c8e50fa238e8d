#!/usr/bin/env bash
# Set up and run the main job on the embedded default: mine the synthetic dataset
# (jobs/synthetic.toml: sequence 0000, 500 frames) on a local Ray into ./out/catalog,
# then query the catalogue. Override the folder with OUT=...; extra arguments go to
# `mine submit` (e.g. --workers 2). Running it again resumes (a finished job does nothing).
# The default's proposer (stereo) names no class: submit's summary ends with the settings that would.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh onnx,video

export RAY_USAGE_STATS_ENABLED=0
out="${OUT:-out}/catalog"
.venv/bin/mine submit --config jobs/synthetic.toml --out "$out" "$@"
.venv/bin/mine query --out "$out" \
  "SELECT category, known, count(*) AS tubes, round(avg(n_frames), 1) AS mean_frames, round(max(score), 1) AS best_score
   FROM selected_tubes GROUP BY ALL ORDER BY tubes DESC"
