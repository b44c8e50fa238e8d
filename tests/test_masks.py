"""RLE helpers against pycocotools on random and real-shaped masks."""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from mining.boxes import box_iou, size_similarity
from mining.masks import (areas, batch_mask_pixels, batch_mask_runs, batch_rle_problems, box_rle, crop_rle, grid_run_pixels,
                          mask_iou, mask_pixels, rle_box, rle_counts, rle_problem)


def _random_masks(rng, n, h=60, w=80):
    out = []
    for _ in range(n):
        m = np.zeros((h, w), bool)
        for _ in range(rng.integers(1, 4)):
            y, x = rng.integers(0, h), rng.integers(0, w)
            m[y : y + rng.integers(1, 30), x : x + rng.integers(1, 40)] = True
        m &= rng.random((h, w)) > 0.1 * rng.integers(0, 2)
        out.append(m)
    out.append(np.zeros((h, w), bool))
    out.append(np.ones((h, w), bool))
    return out


def test_counts_and_pixels_match_pycocotools():
    rng = np.random.default_rng(0)
    for m in _random_masks(rng, 200):
        rle = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
        counts = rle_counts(rle)
        assert counts.sum() == m.size
        rows, cols = mask_pixels(rle)
        back = np.zeros_like(m)
        back[rows, cols] = True
        np.testing.assert_array_equal(back, m)


def test_crop_rle_round_trip():
    rng = np.random.default_rng(1)
    for m in _random_masks(rng, 100):
        ys, xs = np.nonzero(m)
        if ys.size == 0:
            continue
        y0, x0 = ys.min(), xs.min()
        rle = crop_rle(m[y0 : ys.max() + 1, x0 : xs.max() + 1], x0, y0, *m.shape)
        np.testing.assert_array_equal(mask_utils.decode(rle).astype(bool), m)


def test_box_helpers():
    rle = box_rle(np.array([10.2, 5.0, 20.0, 15.5]), 40, 50)
    assert mask_utils.area(rle) == 10 * 11
    np.testing.assert_allclose(rle_box(rle), [10, 5, 20, 16])
    a = np.array([[0, 0, 10, 10]])
    b = np.array([[5, 0, 15, 10], [0, 0, 10, 10], [20, 20, 30, 30]])
    np.testing.assert_allclose(box_iou(a, b), [[1 / 3, 1.0, 0.0]])
    np.testing.assert_allclose(size_similarity(a, np.array([[0, 0, 5, 10]])), [[0.5]])


def test_batched_iou_and_chunked_area():
    rng = np.random.default_rng(2)
    ms = _random_masks(rng, 300)
    rles = [mask_utils.encode(np.asfortranarray(m.astype(np.uint8))) for m in ms]
    np.testing.assert_array_equal(areas(rles), [m.sum() for m in ms])
    iou = mask_iou(rles[:5], rles[5:9])
    for i in range(5):
        for j in range(4):
            a, b = ms[i], ms[5 + j]
            union = (a | b).sum()
            assert iou[i, j] == pytest.approx((a & b).sum() / union if union else 0.0)


def test_batch_decoding_matches_per_mask():
    rng = np.random.default_rng(3)
    ms = _random_masks(rng, 120)
    rles = [mask_utils.encode(np.asfortranarray(m.astype(np.uint8))) for m in ms]
    seg, rows, cols = batch_mask_pixels(rles)
    for i, rle in enumerate(rles):
        r, c = mask_pixels(rle)
        np.testing.assert_array_equal(rows[seg == i], r)
        np.testing.assert_array_equal(cols[seg == i], c)
    assert batch_mask_pixels([])[0].size == 0


def test_grid_pixels_from_runs_match_the_filtered_pixels():
    """``grid_run_pixels`` keeps what ``batch_mask_pixels`` filtered to rows and columns on each
    mask's grid step keeps, in the same order (runs that cross columns included)."""
    rng = np.random.default_rng(4)
    ms = _random_masks(rng, 120)
    rles = [mask_utils.encode(np.asfortranarray(m.astype(np.uint8))) for m in ms]
    seg, rows, cols = batch_mask_pixels(rles)
    heights = np.full(len(rles), 60, np.int64)
    for step in (np.ones(len(rles), np.int64), rng.integers(1, 5, len(rles))):
        g = step[seg]
        sel = (rows % g == 0) & (cols % g == 0)
        got = grid_run_pixels(*batch_mask_runs(rles), heights, step)
        for a, b in zip(got, (seg[sel], rows[sel], cols[sel])):
            np.testing.assert_array_equal(a, b)
    assert batch_mask_runs([])[0].size == 0


def test_crop_rle_is_canonical_when_the_mask_holds_the_last_pixel():
    """A mask reaching the frame's bottom-right pixel ends on a run of ones: COCO's encoding writes
    no empty run after it (a FastSAM mask over the frame's corner found this)."""
    from mining.masks import crop_rle

    for crop, x0, y0 in ((np.ones((3, 4), bool), 6, 7), (np.ones((10, 10), bool), 0, 0),
                         (np.eye(3, dtype=bool)[::-1], 7, 7)):
        full = np.zeros((10, 10), np.uint8)
        full[y0:y0 + crop.shape[0], x0:x0 + crop.shape[1]] = crop
        assert crop_rle(crop, x0, y0, 10, 10)["counts"] == mask_utils.encode(np.asfortranarray(full))["counts"]


def _damaged(counts: str, rng) -> list[str]:
    """Ways a compressed counts string breaks: cut, a character changed, doubled, grown, emptied."""
    cut = counts[: rng.integers(0, len(counts))] if len(counts) > 1 else ""
    k = int(rng.integers(0, len(counts)))
    changed = counts[:k] + chr(int(rng.integers(33, 127))) + counts[k + 1:]
    return [cut, changed, counts + counts, counts + "1", "", counts[:-1] + "o", "0" * 5, "\x7f", "é" + counts]


def test_batch_rle_problems_says_what_rle_problem_says_of_each():
    rng = np.random.default_rng(3)
    sizes, counts = [], []
    for m in _random_masks(rng, 60):
        c = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))["counts"].decode()
        for s in [c, *_damaged(c, rng)]:
            sizes.append(m.shape)
            counts.append(s)
    sizes += [(0, 80), (60, -1), (60, 80), (60, 80), (2**40, 2**40)]
    counts += ["PP", "PP", None, b"PP", "0"]
    expected = [rle_problem(h, w, c) for (h, w), c in zip(sizes, counts)]
    assert sum(p is None for p in expected) >= 60 and sum(p is not None for p in expected) >= 300  # both kinds
    order = rng.permutation(len(counts))  # good and bad interleaved: no string's runs may leak into the next
    got = batch_rle_problems([sizes[i] for i in order], [counts[i] for i in order])
    assert got == [expected[i] for i in order]
    assert batch_rle_problems([], []) == []


def test_box_rle_equals_the_rle_of_the_filled_box():
    # box_rle writes one run per column; the truth is crop_rle of the box filled with ones.
    rng = np.random.default_rng(3)
    H, W = 37, 53
    boxes = [[0, 0, W, H], [0, 0, 1, 1], [W - 1, H - 1, W, H], [3, 0, 9, H], [0, 5, W, 9], [-4, -2.5, 7.2, H + 3],
             [10, 10, 10, 20], [5, 30, 6, 31]]
    for _ in range(300):
        (xa, xb), (ya, yb) = np.sort(rng.uniform(-5, W + 5, 2)), np.sort(rng.uniform(-5, H + 5, 2))
        boxes.append([xa, ya, xb, yb])
    for b in np.array(boxes, float):
        x1, y1 = max(0, int(np.floor(b[0]))), max(0, int(np.floor(b[1])))
        x2, y2 = min(W, int(np.ceil(b[2]))), min(H, int(np.ceil(b[3])))
        filled = np.zeros((H, W), bool)
        if x2 > x1 and y2 > y1:
            filled[y1:y2, x1:x2] = True
        got = box_rle(b, H, W)
        assert got == crop_rle(filled, 0, 0, H, W), b
        np.testing.assert_array_equal(mask_utils.decode(got).astype(bool), filled)
