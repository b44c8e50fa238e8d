#!/usr/bin/env bash
# Set up and run the main job on the embedded default: the synthetic dataset, on this
# machine. Results go to ./out/ (override with OUT=...).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh onnx

export RAY_USAGE_STATS_ENABLED=0
out="${OUT:-out}"
exec .venv/bin/mine inspect geometry --dataset synthetic --sequence 0000 --frames 0:20 --out "$out/geometry" "$@"
