#!/usr/bin/env bash
# Create .venv (Python >= 3.11) and install Tube Miner into it. Idempotent and quick when
# nothing changed. Usage: scripts/setup.sh [EXTRAS], e.g. scripts/setup.sh test,onnx
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-onnx}"
py="${PYTHON:-}"
if [ -z "$py" ]; then
  for c in python3.11 python3.12 python3.13 python3; do
    if command -v "$c" >/dev/null && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then py="$c"; break; fi
  done
fi
[ -n "$py" ] || { echo "setup: need Python >= 3.11 on PATH" >&2; exit 1; }
[ -x .venv/bin/python ] || "$py" -m venv .venv
stamp=".venv/.installed-$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -c1-16)-${extras//,/_}"
if [ ! -f "$stamp" ]; then
  echo "setup: installing tube-miner[${extras}] into .venv (log: .venv/setup.log)" >&2
  if ! .venv/bin/python -m pip install -e ".[${extras}]" >.venv/setup.log 2>&1; then
    tail -30 .venv/setup.log >&2
    exit 1
  fi
  if [[ ",$extras," == *",test,"* ]]; then
    # TrackEval (MIT, the KITTI/MOT reference evaluator) cross-checks our metrics in the
    # tests. --no-deps: its metadata pulls opencv-python, which clashes with the headless
    # OpenCV we use; the metrics need only numpy and scipy (and its BURST readers tabulate, which
    # the test extra pins).
    .venv/bin/python -m pip install -q --no-deps trackeval==1.3.0 >>.venv/setup.log 2>&1 || { tail -30 .venv/setup.log >&2; exit 1; }
  fi
  touch "$stamp"
fi
if [[ ",$extras," == *",test,"* ]] && ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
  # The browser test of `mine view` (tests/test_view_browser.py) drives Debian's headless Chromium
  # (25 packages, ~120 MB download, ~400 MB on disk). Only as root with apt; elsewhere the test skips
  # outside CI and fails in CI.
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian's chromium for the browser test (log: .venv/apt.log)" >&2
    if ! { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
             chromium fonts-dejavu-core; } >.venv/apt.log 2>&1; then
      tail -20 .venv/apt.log >&2
      echo "setup: chromium did not install; the browser test cannot run" >&2
    fi
  else
    echo "setup: no chromium (install Debian's chromium as root for the browser test)" >&2
  fi
fi
export RAY_USAGE_STATS_ENABLED=0
