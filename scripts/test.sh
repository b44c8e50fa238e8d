#!/usr/bin/env bash
# Set up (scripts/setup.sh) and run the whole test suite. Exits non-zero on any failure.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh test,onnx

export RAY_USAGE_STATS_ENABLED=0
exec .venv/bin/python -m pytest -q "$@"
