"""`mine view` in a real headless Chromium (Debian's, installed by scripts/setup.sh test), over
the real KITTI 0005 catalogue: the gallery shows the selected tubes, a filter narrows them to
what DuckDB counts, a tube page shows its frames and steps through them with the arrow keys.

Screenshots go to the test's tmp folder, or to $TUBE_MINER_VIEW_SHOTS when set (to look at).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from _cdp import Browser
from conftest import count_tubes, serving
from mining.view.images import best_frame

# The natural widths of the images in view (a lazy image out of view, e.g. far along the tube page's
# strip, is not fetched), once each has loaded or failed.
ALL_IMAGES_LOADED = """(() => {
  const inView = i => {
    const r = i.getBoundingClientRect(), s = i.closest('#strip');
    const c = s ? s.getBoundingClientRect() : { left: 0, right: innerWidth };
    return r.top < innerHeight && r.left < Math.min(innerWidth, c.right) && r.right > Math.max(0, c.left);
  };
  const shown = [...document.images].filter(i => i.loading !== 'lazy' || inView(i));
  return Promise.all(shown.map(i => i.complete ? 0 : new Promise(r => { i.onload = i.onerror = r; })))
    .then(() => shown.map(i => i.naturalWidth));
})()"""


def _shots(tmp_path: Path) -> Path:
    folder = Path(os.environ.get("TUBE_MINER_VIEW_SHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _looks_like_a_page(path: Path, width: int, height: int) -> None:
    image = cv2.imread(str(path))
    assert image is not None and image.shape[:2] == (height, width)
    assert image.std() > 20, "a blank screenshot"


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_gallery_filter_and_tube_page_in_chromium(catalogue, chromium, tmp_path):
    out, tables = catalogue
    n_selected = count_tubes(out, "selected")
    # a bound at the selected tubes' median score, on whatever scale the unary has (calibrated: a log-odds)
    scores = sorted(t["score"] for t in tables["tubes"].to_pylist() if t["selected"])
    bound = f"{np.floor(scores[len(scores) // 2] * 100) / 100:.2f}"
    n_narrowed = count_tubes(out, f"selected AND score >= {bound}")
    n_all = count_tubes(out, "true")
    assert 0 < n_narrowed < n_selected < n_all
    shots = _shots(tmp_path)
    with serving(out, tmp_path / "cache") as (base, _):
        with Browser(chromium, width=1400, height=900) as b:
            # The gallery: one card per selected tube, every thumbnail a real picture.
            b.goto(f"{base}/")
            b.wait_for("document.body.dataset.state === 'ready'")
            assert b.evaluate("document.querySelectorAll('.card').length") == n_selected
            assert b.evaluate("document.getElementById('count').textContent") == str(n_selected)
            assert b.evaluate(ALL_IMAGES_LOADED) == [240] * n_selected
            assert b.evaluate("document.getElementById('banner').hidden")
            b.screenshot(shots / "gallery.png")
            # A filter typed into the form narrows the gallery to DuckDB's count, and the URL keeps it.
            b.evaluate(f"(() => {{ const i = document.getElementById('min_score'); i.value = '{bound}';"
                       " i.dispatchEvent(new Event('change', { bubbles: true })); })()")
            b.wait_for(f"document.body.dataset.state === 'ready' && document.body.dataset.total === '{n_narrowed}'")
            assert b.evaluate("document.querySelectorAll('.card').length") == n_narrowed
            assert f"min_score={bound}" in b.evaluate("location.search")
            assert f"score >= {bound}" in b.evaluate("document.getElementById('export').textContent")
            # The toggle for all candidates, the score bound cleared.
            b.evaluate("(() => { const i = document.getElementById('min_score'); i.value = '';"
                       " document.querySelector('input[name=set][value=all]').checked = true;"
                       " i.dispatchEvent(new Event('change', { bubbles: true })); })()")
            b.wait_for(f"document.body.dataset.state === 'ready' && document.body.dataset.total === '{n_all}'")
            assert b.evaluate("document.querySelectorAll('.card').length") == n_all
            # A tube page, reached by clicking the best card: its frames load, the arrow keys step.
            best = max(tables["tubes"].to_pylist(), key=lambda t: t["score"])
            b.evaluate(f"document.querySelector('.card[data-tube=\"{best['tube_id']}\"]').click()")
            b.wait_for("location.pathname === '/tube' && document.body.dataset.state === 'ready'")
            b.wait_for("document.getElementById('frame').complete && document.getElementById('frame').naturalWidth > 0")
            assert b.evaluate("document.getElementById('frame').naturalWidth") == 1242
            assert b.evaluate("document.querySelectorAll('#strip img').length") == best["n_frames"]
            widths = b.evaluate(ALL_IMAGES_LOADED)
            assert widths[0] == 1242 and 200 in widths[1:] and 0 not in widths
            # It opens on the frame its card showed (the largest whole view), not on the first.
            rows = sorted((f for f in tables["tube_frames"].to_pylist() if f["tube_id"] == best["tube_id"]),
                          key=lambda f: f["frame"])
            shown = best_frame(rows)["frame"]
            k = [f["frame"] for f in rows].index(shown)
            assert b.evaluate("document.getElementById('frame-label').textContent").startswith(
                f"frame {shown} ({k + 1} of {best['n_frames']})")
            b.key("ArrowRight", key_code=39)
            b.key("ArrowRight", key_code=39)
            b.key("ArrowLeft", key_code=37)
            nxt = rows[(k + 1) % len(rows)]["frame"]
            assert b.evaluate("document.getElementById('frame-label').textContent").startswith(
                f"frame {nxt} ({(k + 1) % len(rows) + 1} of")
            # Follow the object (a small one opens followed): the frame scaled onto its box, or whole.
            x1, y1, x2, y2 = rows[k]["bbox"]
            small = (x2 - x1) * (y2 - y1) < 0.01 * rows[k]["rle_w"] * rows[k]["rle_h"]
            zooms = [float(b.evaluate("document.body.dataset.zoom"))]
            b.key("f", key_code=70)
            zooms.append(float(b.evaluate("document.body.dataset.zoom")))
            assert (zooms[0] > 1.5 and zooms[1] == 1) if small else (zooms[0] == 1 and zooms[1] > 1.5), zooms
            b.screenshot(shots / "tube-follow.png")
            b.wait_for("document.getElementById('frame').complete")
            assert b.evaluate("document.querySelectorAll('#track polyline').length") == 2  # tube and camera
            assert best["tube_id"] in b.evaluate("document.getElementById('export').textContent")
            b.screenshot(shots / "tube.png")
            # Play runs through the frames by itself.
            b.evaluate("document.getElementById('play').click()")
            b.wait_for("!document.getElementById('frame-label').textContent.startsWith('frame 1 ')", timeout=10)
            b.evaluate("document.getElementById('play').click()")
            # An unknown tube says so.
            b.goto(f"{base}/tube?id=kitti/0005/nothing")
            b.wait_for("document.body.dataset.state === 'error'")
            assert "no tube" in b.evaluate("document.getElementById('banner').textContent")
    _looks_like_a_page(shots / "gallery.png", 1400, 900)
    _looks_like_a_page(shots / "tube.png", 1400, 900)


# Each card's tube id → [badge text, badge classes, the number beside it].
CARDS = """Object.fromEntries([...document.querySelectorAll('.card')].map(c => [c.dataset.tube,
  [c.querySelector('.badge').textContent, c.querySelector('.badge').className, c.querySelector('.prob-text').textContent]]))"""
CLUTTER_RGB = "rgb(190, 130, 255)"  # app.css --clutter, draw.py CALL_COLOURS["clutter"]


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_the_calls_in_chromium(every_call, chromium, tmp_path):
    """Badges, counts, the call filter and the legend of the gallery, and a clutter and an
    unclassified tube's page, over a catalogue with every call (rows from before the call column too)."""
    out, calls = every_call
    clutter = next(t for t, c in calls.items() if c == "clutter")
    shots = _shots(tmp_path)
    with serving(out, tmp_path / "cache") as (base, _):
        with Browser(chromium, width=1400, height=900) as b:
            b.goto(f"{base}/?set=all")
            b.wait_for("document.body.dataset.state === 'ready'")
            cards = b.evaluate(CARDS)
            assert set(cards) == set(calls)
            for tube_id, call in calls.items():
                text, classes, _ = cards[tube_id]
                assert text == ("car" if call == "known" else call) and f"c-{call}" in classes.split(), tube_id
            assert cards[clutter][2] == "P(object) 0.31"
            assert cards["kitti/0005/0000000.001"][2] == "P(unknown) 0.80"
            assert cards["kitti/0005/0000005.003"][2] == ""  # unclassified: no probability
            assert cards["kitti/0005/0000000.000"][2] == "P(car) 1.00"
            assert b.evaluate(f"getComputedStyle(document.querySelector('.card[data-tube=\"{clutter}\"] .badge'))"
                              ".backgroundColor") == CLUTTER_RGB
            counts = b.evaluate("Object.fromEntries([...document.querySelectorAll('span.n[data-call]')]"
                                ".map(s => [s.dataset.call, s.textContent]))")
            assert counts == {c: f"({list(calls.values()).count(c)})" for c in ("known", "unknown", "clutter", "unclassified")}
            legend = " ".join(b.evaluate("document.getElementById('legend').textContent").split())
            assert ("clutter unknown to the classifier, but its object evidence says not an object: P(object) below "
                    "the gate; kept out of the unknown set") in legend
            assert "unclassified no classifier looked" in legend
            assert b.evaluate(ALL_IMAGES_LOADED) == [240] * len(calls)
            b.screenshot(shots / "gallery-calls.png")
            # The call checkboxes filter: clutter and unclassified, the address keeps them.
            for call in ("clutter", "unclassified"):
                b.evaluate(f"document.querySelector('input[name=call][value={call}]').click()")
            want = sorted(t for t, c in calls.items() if c in ("clutter", "unclassified"))
            b.wait_for(f"document.body.dataset.state === 'ready' && document.body.dataset.total === '{len(want)}'")
            assert sorted(b.evaluate(CARDS)) == want
            assert b.evaluate("location.search") == "?set=all&call=clutter&call=unclassified"
            assert "IN ('clutter', 'unclassified')" in b.evaluate("document.getElementById('export').textContent")
            # The clutter tube's page: its badge, the call and P(object) in its table, the rule with the numbers.
            b.evaluate(f"document.querySelector('.card[data-tube=\"{clutter}\"]').click()")
            b.wait_for("location.pathname === '/tube' && document.body.dataset.state === 'ready'")
            assert b.evaluate("document.getElementById('badge').textContent") == "clutter"
            rule = b.evaluate("document.getElementById('class-rule').textContent")
            assert "P(object) 0.31 < 0.50 (score.unknown_min_object): clutter" in rule, rule
            assert "ln P(car) − ln P(unknown) = ln 0.060 − ln 0.900 = -2.71 ≤ 0.00" in rule
            table = b.evaluate("Object.fromEntries([...document.querySelectorAll('#class tr')]"
                               ".map(r => [r.cells[0].textContent, r.cells[1].textContent]))")
            assert table["call"] == "clutter" and table["P(object)"] == "0.310" and table["P(unknown)"] == "0.900"
            assert b.evaluate("getComputedStyle(document.querySelector('#track polyline.tube')).stroke") == CLUTTER_RGB
            assert b.evaluate("getComputedStyle(document.querySelector('.swatch.tube')).backgroundColor") == CLUTTER_RGB
            b.wait_for("document.getElementById('frame').complete && document.getElementById('frame').naturalWidth > 0")
            b.screenshot(shots / "tube-clutter.png")
            # An unclassified tube's page says no classifier looked; an old row says its call was read from known.
            b.goto(f"{base}/tube?id=kitti/0005/0000005.003")
            b.wait_for("document.body.dataset.state === 'ready'")
            assert b.evaluate("document.getElementById('badge').textContent").startswith("unclassified")
            assert b.evaluate("document.getElementById('class-rule').textContent") == (
                "Unclassified: no classifier looked at this tube (classified frames 0).")
            b.goto(f"{base}/tube?id=kitti/0005/0000000.101")
            b.wait_for("document.body.dataset.state === 'ready'")
            assert b.evaluate("document.getElementById('badge').textContent") == "unknown"
            assert "written before the call column" in b.evaluate("document.querySelector('#class tr td').textContent")
    _looks_like_a_page(shots / "gallery-calls.png", 1400, 900)
    _looks_like_a_page(shots / "tube-clutter.png", 1400, 900)


# Loads video `src` into a <video>, waits for its first frame (or an error), and reports its size,
# duration, error code and the mean of the first frame's pixels as the browser decoded them.
PLAY_VIDEO = """(src => new Promise(done => {
  const v = document.createElement('video');
  v.muted = true; v.preload = 'auto';
  const report = () => {
    let mean = null;
    if (v.readyState >= 2) {
      const c = document.createElement('canvas'); c.width = v.videoWidth; c.height = v.videoHeight;
      const g = c.getContext('2d'); g.drawImage(v, 0, 0);
      const px = g.getImageData(0, 0, c.width, c.height).data; let s = 0, n = 0;
      for (let i = 0; i < px.length; i += 4) { s += px[i] + px[i + 1] + px[i + 2]; n += 3; }
      mean = s / n;
    }
    done({ width: v.videoWidth, height: v.videoHeight, duration: v.duration, error: v.error && v.error.code, mean });
  };
  v.onloadeddata = report; v.onerror = report;
  v.src = src; document.body.appendChild(v);
}))"""


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_rendered_mp4_plays_in_chromium(catalogue, chromium, tmp_path):
    """`mine render`'s MP4 (H.264) plays in Chromium and shows the picture OpenCV reads back; an
    MPEG-4 Part 2 MP4 (what OpenCV alone writes) does not play: the check can fail."""
    import functools
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    import numpy as np

    from _catalog_data import SEQUENCE
    from mining.export.render import run_render

    out, _ = catalogue
    assert run_render(str(out), SEQUENCE, str(tmp_path / "h264.mp4"), frames=(0, 6), fps=10) == 0
    ok, first = cv2.VideoCapture(str(tmp_path / "h264.mp4")).read()
    assert ok
    control = cv2.VideoWriter(str(tmp_path / "mp4v.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10, first.shape[1::-1])
    for _ in range(6):
        control.write(first)
    control.release()
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(tmp_path))
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        with Browser(chromium, width=800, height=600) as b:
            b.goto(f"{base}/")
            played = b.evaluate(f"{PLAY_VIDEO}('{base}/h264.mp4')", timeout=30)
            refused = b.evaluate(f"{PLAY_VIDEO}('{base}/mp4v.mp4')", timeout=30)
    finally:
        server.shutdown()
        server.server_close()
    assert played["error"] is None and (played["width"], played["height"]) == (1242, 376)
    assert abs(played["duration"] - 0.6) < 0.05
    assert abs(played["mean"] - float(np.mean(first))) < 3, "the browser shows the picture OpenCV reads"
    assert refused["error"] == 4 and refused["mean"] is None  # MEDIA_ERR_SRC_NOT_SUPPORTED
