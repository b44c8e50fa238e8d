#!/usr/bin/env bash
# A screenshot of `mine view` on KITTI tracking 0005, frames 0–15, mined with the onnx+stereo proposer.
#
# Usage: bash scripts/view_screenshot.sh [OUT.png] [--catalogue DIR] [MINE SUBMIT ARGS...]
#   OUT.png          where the picture goes (default docs/img/view_kitti0005.png)
#   --catalogue DIR  mine into DIR and keep it (default: a fresh temporary folder, removed at the end);
#                    a finished job in DIR is resumed, i.e. not mined again
#   anything else goes to `mine submit`, e.g. --set tubes.association='"innovation"' --workers 1
# e.g. bash scripts/view_screenshot.sh /tmp/shot.png --set tubes.association='"innovation"'
#
# It runs `mine submit --config jobs/kitti.toml --sequences 0005 --frames 0:16` with
# proposals.proposer="onnx+stereo" and the int8 YOLOv8n-seg model (KITTI_ROOT and MODEL override
# ../shared/data/kitti_tracking and ../shared/models/yolov8n-seg_int8.onnx), serves the catalogue
# with `mine view` on 127.0.0.1 and a free port, and photographs the gallery of the selected tubes of
# kitti/0005 (each card: the tube's best view with its mask outlined, its class, score and frames) in
# headless Chromium at 1600×900 (scripts/view_screenshot.py; Debian's chromium must be on PATH).
# Needs .venv with the onnx extra (scripts/setup.sh onnx). The server stops when the script ends.
set -euo pipefail

here="$(pwd)"
repo="$(cd "$(dirname "$0")/.." && pwd)"
abs() { case "$1" in /*) printf '%s\n' "$1" ;; *) printf '%s\n' "$here/$1" ;; esac; }

png="$repo/docs/img/view_kitti0005.png"
catalogue=""
submit_args=()
if [ $# -gt 0 ] && [[ "$1" != -* ]]; then png="$(abs "$1")"; shift; fi
while [ $# -gt 0 ]; do
  case "$1" in
    --catalogue) catalogue="$(abs "${2:?--catalogue needs a folder}")"; shift 2 ;;
    -h|--help) awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"; exit 0 ;;
    *) submit_args+=("$1"); shift ;;
  esac
done

cd "$repo"
[ -x .venv/bin/mine ] || { echo "view_screenshot: no .venv/bin/mine: run scripts/setup.sh onnx" >&2; exit 1; }
command -v chromium >/dev/null || command -v chromium-browser >/dev/null \
  || { echo "view_screenshot: no chromium on PATH (Debian: apt-get install chromium)" >&2; exit 1; }

tmp="$(mktemp -d -t tube-miner-view-shot.XXXXXX)"
server=""
stop() {
  if [ -n "$server" ] && kill -0 "$server" 2>/dev/null; then
    kill "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
  fi
  rm -rf "$tmp"
}
trap stop EXIT
trap 'exit 130' INT TERM
[ -n "$catalogue" ] || catalogue="$tmp/catalog"

export RAY_USAGE_STATS_ENABLED=0
start=$SECONDS
echo "view_screenshot: mining KITTI 0005 frames 0:16 (onnx+stereo) into $catalogue" >&2
.venv/bin/mine submit --config jobs/kitti.toml --root "${KITTI_ROOT:-../shared/data/kitti_tracking}" \
  --sequences 0005 --frames 0:16 \
  --set proposals.proposer='"onnx+stereo"' \
  --set proposals.onnx.model_path="\"${MODEL:-../shared/models/yolov8n-seg_int8.onnx}\"" \
  --out "$catalogue" --no-progress "${submit_args[@]}"
mined=$SECONDS

# A free port (--port 0), read back from the line the server prints when it listens.
.venv/bin/mine view --out "$catalogue" --host 127.0.0.1 --port 0 --cache "$tmp/cache" >"$tmp/view.log" 2>&1 &
server=$!
url=""
for _ in $(seq 300); do
  url="$(grep -o 'serving http://127\.0\.0\.1:[0-9]*/' "$tmp/view.log" | head -1 | cut -d' ' -f2 || true)"
  [ -n "$url" ] && break
  kill -0 "$server" 2>/dev/null || { cat "$tmp/view.log" >&2; echo "view_screenshot: mine view stopped" >&2; exit 1; }
  sleep 0.2
done
[ -n "$url" ] || { cat "$tmp/view.log" >&2; echo "view_screenshot: mine view did not start in 60 s" >&2; exit 1; }
grep -v '^mine view: .*serving' "$tmp/view.log" >&2 || true
echo "view_screenshot: $(head -1 "$tmp/view.log")" >&2

# The gallery of kitti/0005's selected tubes (known and unknown), best score first.
.venv/bin/python scripts/view_screenshot.py "${url}?seq=kitti%2F0005" "$png" --width 1600 --height 900
echo "view_screenshot: mined in $((mined - start)) s, photographed in $((SECONDS - mined)) s: $png" >&2
