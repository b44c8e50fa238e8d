"""Screenshot of `mine view`'s gallery in headless Chromium, for scripts/view_screenshot.sh.

    .venv/bin/python scripts/view_screenshot.py URL OUT.png [--width 1600] [--height 900]

Waits until the server at URL answers, opens URL (the gallery's filter is in its query, e.g.
``/?seq=kitti/0005``), waits until the gallery is drawn and every thumbnail in view has loaded,
prints the tubes the gallery lists (id, class label, score, frames; ``*`` = in the screenshot),
and writes a plain PNG of the viewport, made smaller (compression, then scale) if it is over
``--max-bytes``. Chromium is driven through the DevTools protocol helper of the browser tests
(tests/_cdp.py).
"""

from __future__ import annotations

import argparse
import base64
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from _cdp import Browser, CDPError, find_chromium  # noqa: E402

# Every <img> in the viewport, once each has loaded or failed: their natural widths (0 = failed).
IMAGES_IN_VIEW = """(() => {
  const shown = [...document.images].filter(i => {
    const r = i.getBoundingClientRect();
    return r.bottom > 0 && r.top < innerHeight && r.right > 0 && r.left < innerWidth;
  });
  return Promise.all(shown.map(i => i.complete ? 0 : new Promise(r => { i.onload = i.onerror = r; })))
    .then(() => shown.map(i => i.naturalWidth));
})()"""

# What the gallery lists: one row per card, and whether the card is (at least half) in view.
CARDS = """[...document.querySelectorAll('.card')].map(c => {
  const r = c.getBoundingClientRect();
  return { id: c.dataset.tube, label: c.querySelector('.badge').textContent,
           prob: c.querySelector('.card-head .muted').textContent,
           score: c.querySelector('.score').textContent,
           facts: [...c.querySelectorAll('.card-facts')].map(f => f.textContent).join(' | '),
           shown: r.top + r.height / 2 < innerHeight };
})"""


def wait_answering(url: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                if r.status == 200:
                    return
        except (urllib.error.URLError, OSError) as e:
            if time.monotonic() > deadline:
                sys.exit(f"view_screenshot: {url} did not answer in {timeout:.0f} s ({e})")
        time.sleep(0.2)


def small_png(png: bytes, max_bytes: int) -> tuple[bytes, float]:
    """``png`` (re-encoded at the highest compression, then scaled down in 5 % steps) under ``max_bytes``."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    scale, out = 1.0, png
    while len(out) > max_bytes and scale > 0.3:
        shown = image if scale == 1.0 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".png", shown, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        assert ok
        out = buf.tobytes()
        if len(out) > max_bytes:
            scale = round(scale - 0.05, 2)
    return out, scale


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("url")
    ap.add_argument("out", type=Path)
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--timeout", type=float, default=300, help="seconds for the thumbnails to be drawn")
    ap.add_argument("--max-bytes", type=int, default=400_000)
    args = ap.parse_args()
    if not find_chromium():
        sys.exit("view_screenshot: no chromium on PATH (Debian: apt-get install chromium)")
    wait_answering(args.url, 60)
    t0 = time.monotonic()
    with Browser(width=args.width, height=args.height, timeout=args.timeout) as b:
        b.goto(args.url)
        b.wait_for("['ready', 'error'].includes(document.body.dataset.state)", timeout=120)
        if b.evaluate("document.body.dataset.state") == "error":
            sys.exit("view_screenshot: the gallery says: " + b.evaluate("document.getElementById('banner').textContent"))
        widths = b.evaluate(IMAGES_IN_VIEW, timeout=args.timeout)
        if 0 in widths:
            print(f"view_screenshot: {widths.count(0)} of {len(widths)} pictures in view did not load", file=sys.stderr)
        banner = b.evaluate("document.getElementById('banner').hidden ? '' : document.getElementById('banner').textContent")
        if banner:
            print(f"view_screenshot: the gallery's banner says: {banner}", file=sys.stderr)
        print("view_screenshot:", b.evaluate("document.getElementById('catalogue').textContent"), "·",
              b.evaluate("document.getElementById('totals').textContent"), "·",
              b.evaluate("document.getElementById('count').textContent"), "tubes in this view",
              f"(drawn in {time.monotonic() - t0:.1f} s)")
        for c in b.evaluate(CARDS):
            print(f"  {'*' if c['shown'] else ' '} {c['id']}  {c['label']} {c['prob']}  score {c['score']}  {c['facts']}")
        png = b.send("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
    data, scale = small_png(base64.b64decode(png), args.max_bytes)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(data)
    print(f"view_screenshot: wrote {args.out} ({len(data) // 1000} kB"
          + (f", scaled to {scale:.0%}" if scale < 1 else "") + "; * = in the picture)")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except CDPError as e:
        sys.exit(f"view_screenshot: {e}")
