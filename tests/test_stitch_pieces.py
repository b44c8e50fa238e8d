"""The stitch's pieces (issue 42): a piece's rows are made into dicts only when asked, and they are
the rows grouping every row by its part tube id would give, in frame order, ties as they came."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from mining.pipeline.stitch import _Pieces


def test_pieces_are_the_rows_grouped_by_tube_in_frame_order_ties_kept():
    rng = np.random.default_rng(3)
    n = 400
    table = pa.table({"tube_id": [f"w{k % 4}/{k}" for k in rng.integers(0, 30, n)],
                      "frame": rng.integers(0, 50, n).tolist(), "window": [f"w{i % 3}" for i in range(n)],
                      "obs_index": [None if i % 17 == 0 else i for i in range(n)],
                      "observed": (rng.random(n) < 0.7).tolist(), "row": list(range(n))})
    want: dict[str, list[dict]] = {}
    for r in table.to_pylist():
        want.setdefault(r["tube_id"], []).append(r)
    for rows in want.values():
        rows.sort(key=lambda r: r["frame"])  # stable: a frame seen twice keeps its rows' order
    pieces = _Pieces(table)
    assert set(pieces.span) == set(want)
    for p, rows in want.items():
        assert pieces.rows(p) == rows
        assert pieces.window[p] == rows[0]["window"]
        assert pieces.keys[p] == {(r["frame"], r["obs_index"]) for r in rows if r["observed"]}
    empty = _Pieces(table.slice(0, 0))
    assert empty.span == {} and empty.keys == {}
