"""A tagging session in a real headless Chromium over the small synthetic job's catalogue: tubes chosen
and labelled with the keyboard alone, the tag as a gallery filter, the filter's export command
exporting exactly the tagged tubes, and every tag still there after a compaction.

Screenshots go to the test's tmp folder, or to $TUBE_MINER_VIEW_SHOTS when set (to look at).
"""

from __future__ import annotations

import json
import shlex

import pytest

from _cdp import Browser
from _jobs import copy_of
from conftest import serving
from mining import cli
from mining.catalog import labels
from mining.catalog.store import Store
from mining.catalog.views import connect
from test_view_browser import _looks_like_a_page, _shots

TAG = "roadside thing"
READY = "document.body.dataset.state === 'ready'"
CARDS = "[...document.querySelectorAll('.card')].map(c => c.dataset.tube)"


@pytest.mark.slow  # Chromium: over ~2.5 s
def test_tag_tubes_with_keys_filter_by_the_tag_and_export_them(base_catalogue, chromium, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "c")
    shots = _shots(tmp_path)
    with serving(out, tmp_path / "cache", author="ann") as (base, _):
        with Browser(chromium, width=1400, height=1000) as b:
            b.goto(f"{base}/?set=all&sort=tube_id&order=asc")
            b.wait_for(READY)
            shown = b.evaluate(CARDS)
            n = min(10, len(shown))
            assert n >= 5, "the catalogue has too few tubes for a tagging session"
            b.key("ArrowRight", key_code=39)  # focus the first card
            for _ in range(n):
                b.key("x", key_code=88)  # select it
                b.key("ArrowRight", key_code=39)
            assert b.evaluate("document.getElementById('picked').textContent") == f"{n} picked"
            b.key("t", key_code=84)  # into the tag field
            assert b.evaluate("document.activeElement.id") == "tag"
            b.send("Input.insertText", {"text": TAG}, session=True)
            b.key("Enter", key_code=13)
            b.wait_for("document.body.dataset.labelled === '1'")
            assert b.evaluate("document.getElementById('tag').value") == ""  # it kept the text once
            b.key("o", key_code=79)  # the verdict for the same selection
            b.wait_for("document.body.dataset.labelled === '2'")
            b.key("t", key_code=84)  # a second tag: its own, not joined onto the first
            b.send("Input.insertText", {"text": "post"}, session=True)
            b.key("Enter", key_code=13)
            b.wait_for("document.body.dataset.labelled === '3'")
            assert b.evaluate("document.body.dataset.labelError || ''") == ""
            chips = b.evaluate("[...document.querySelectorAll('.cell.picked .labels')]"
                               ".map(l => [...l.querySelectorAll('.tag')].map(t => t.textContent).sort())")
            assert chips == [sorted([TAG, "post"])] * n
            b.evaluate("window.scrollTo(0, 0)")
            _looks_like_a_page(b.screenshot(shots / "gallery-tagged.png"), 1400, 1000)
            # The tag is a filter: exactly the tagged tubes, and the export line says so.
            b.goto(f"{base}/?set=all&tag={TAG.replace(' ', '+')}")
            b.wait_for(READY)
            assert sorted(b.evaluate(CARDS)) == sorted(shown[:n])
            command = b.evaluate("document.getElementById('export').textContent")
            assert "list_contains(tags, 'roadside thing')" in command
            # The verdict facet counts them.
            assert b.evaluate("document.querySelector('span.n[data-verdict=object]').textContent") == f"({n})"
    # The gallery's export command, run as the user would paste it (with another destination).
    args = shlex.split(command)[1:]
    args[-1] = str(tmp_path / "export")
    args[args.index("crops")] = "kitti"
    assert cli.main(args) == 0
    sidecar = json.loads((tmp_path / "export" / "tube_labels.json").read_text())
    assert sorted(t["tube_id"] for t in sidecar["tubes"]) == sorted(shown[:n])
    assert {(t["verdict"], tuple(sorted(t["tags"])), t["labelled_by"]) for t in sidecar["tubes"]} == {
        ("object", tuple(sorted([TAG, "post"])), "ann")}
    # A compaction keeps every tag.
    store = Store(out)
    assert labels.compact(store)[0] == 3
    con = connect(out)
    try:
        tagged = con.execute("SELECT tube_id FROM tube_labels WHERE list_contains(tags, ?)", [TAG]).fetchall()
    finally:
        con.close()
    assert sorted(r[0] for r in tagged) == sorted(shown[:n])
