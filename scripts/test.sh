#!/usr/bin/env bash
# Set up (scripts/setup.sh, with the torch extra so the torch proposer's tests run) and run the whole
# test suite. Exits non-zero on any failure.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh test,onnx,torch

export RAY_USAGE_STATS_ENABLED=0
exec .venv/bin/python -m pytest -q "$@"
