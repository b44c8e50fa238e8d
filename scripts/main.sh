#!/usr/bin/env bash
# Set up and run the main job on the embedded default: the synthetic dataset, on this
# machine. Results go to ./out/ (override with OUT=...).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh onnx 2>&1 | grep -v "is ignored: it is neither" || true
test -x .venv/bin/python || { echo "main: set-up failed" >&2; exit 1; }
export RAY_USAGE_STATS_ENABLED=0
out="${OUT:-out}"
exec .venv/bin/mine inspect geometry --dataset synthetic --sequence 0000 --frames 0:20 --out "$out/geometry" "$@"
