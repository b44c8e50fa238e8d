"""The one painter of tubes on images: colours, mask fill, outline, labels.

`mine render` (``mining/export/render.py``) and the viewer's pictures (``mining/view/images.py``)
draw with these, so a tube looks the same in both: its mask filled semi-transparently
(``FILL_ALPHA``), the mask's outer outline ``OUTLINE_PX`` wide (anti-aliased), and in a
render a label on a box of the tube's colour above its box. Colours are tuples in the
image's own channel order (render draws on BGR frames, the viewer on RGB ones): the
functions never swap channels. numpy and OpenCV only.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# ours: opacity of a mask's fill. Render and the viewer had their own (0.45 and 0.35); render's
# is kept, so the rendered videos stay as they were, and the viewer's frames fill a little stronger.
FILL_ALPHA = 0.45
OUTLINE_PX = 2  # ours: width of a mask's outline
FONT = cv2.FONT_HERSHEY_SIMPLEX
FONT_SCALE = 0.5  # ours: label text size (≈ 11 px high)
GOLDEN_HUE_STEP = 0.618034  # ours: hue step between tubes (the golden ratio's fraction spreads any count)
# Colours (RGB) by the tube's call (``mining.types.CALLS``; the viewer's, its CSS says the same); a predicted
# frame is white.
CALL_COLOURS = {"known": (70, 220, 90), "unknown": (255, 150, 20), "clutter": (190, 130, 255),
                "unclassified": (40, 190, 255)}
PREDICTED_COLOUR = (255, 255, 255)


def tube_colours(tube_ids: list[str]) -> dict[str, tuple[int, int, int]]:
    """A BGR colour per tube: saturated hues a golden-ratio step apart in the order of the
    sorted ids, so neighbouring tubes differ and a tube keeps its colour in every frame (and
    in every render of the same tubes, whatever the frame range)."""
    out = {}
    for k, tid in enumerate(sorted(set(tube_ids))):
        hue = round((k * GOLDEN_HUE_STEP) % 1.0 * 180) % 180
        b, g, r = cv2.cvtColor(np.array([[[hue, 220, 255]]], np.uint8), cv2.COLOR_HSV2BGR)[0, 0]
        out[tid] = (int(b), int(g), int(r))
    return out


def fill_mask(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], alpha: float = FILL_ALPHA) -> None:
    """Blend ``colour`` into ``img`` (in place) where ``mask`` is set, at opacity ``alpha``."""
    m = mask.astype(bool)
    img[m] = ((1 - alpha) * img[m] + alpha * np.array(colour, np.float32)).astype(np.uint8)


def outline_mask(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], width: int = OUTLINE_PX) -> None:
    """Draw the outer outline of ``mask`` on ``img`` (in place)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, colour, width, cv2.LINE_AA)


def draw_mask(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], fill: bool = True) -> np.ndarray:
    """A copy of ``img`` with ``mask`` outlined (and filled, with ``fill``)."""
    out = img.copy()
    if fill and mask.any():
        fill_mask(out, mask, colour)
    outline_mask(out, mask, colour)
    return out


@dataclass
class Drawn:
    """One tube in one frame, ready to draw."""

    tube_id: str
    label: str
    colour: tuple[int, int, int]
    mask: np.ndarray  # (H, W) uint8 0/1
    bbox: tuple[float, float, float, float]  # x1, y1, x2, y2
    observed: bool


def draw_tubes(img: np.ndarray, items: list[Drawn], fill: bool = True) -> np.ndarray:
    """``img`` with each item's mask filled (observed frames, when ``fill``), outlined
    and labelled; a new image. Fills first, then outlines, then labels: no fill covers an
    outline and no outline a label."""
    out = img.copy()
    if fill:
        for it in items:
            if it.observed:
                fill_mask(out, it.mask, it.colour)
    for it in items:
        outline_mask(out, it.mask, it.colour)
    placed: list[tuple[int, int, int, int]] = []
    for it in items:
        label(out, it.label if it.observed else it.label + " (predicted)", it.bbox, it.colour, placed)
    return out


def overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Whether rectangles ``a`` and ``b`` (x1, y1, x2, y2) overlap."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def label(img: np.ndarray, text: str, bbox, colour: tuple[int, int, int],
          placed: list[tuple[int, int, int, int]] | None = None) -> None:
    """``text`` on a box of ``colour`` just above ``bbox`` (inside the image); where that box
    would cover a label already ``placed`` (x1, y1, x2, y2), the first free place stepping up,
    then down, by a label's height (labels of neighbouring tubes stay readable)."""
    (tw, th), base = cv2.getTextSize(text, FONT, FONT_SCALE, 1)
    h, w = img.shape[:2]
    x = int(np.clip(bbox[0], 0, max(0, w - tw - 4)))
    y = int(bbox[1]) - 3
    if y - th - base < 0:
        y = min(h - base - 1, int(bbox[1]) + th + 3)
    step = th + base + 1

    def box(yy: int) -> tuple[int, int, int, int]:
        return x, yy - th - base, x + tw + 4, yy + base - 1

    if placed is not None:
        tries = [y] + [y + k * d * step for k in range(1, 8) for d in (-1, 1)]
        tries = [t for t in tries if t - th - base >= 0 and t + base - 1 < h]
        y = next((t for t in tries if not any(overlaps(box(t), b) for b in placed)), y)
        placed.append(box(y))
    x1, y1, x2, y2 = box(y)
    cv2.rectangle(img, (x1, y1), (x2, y2), colour, cv2.FILLED)
    ink = (0, 0, 0) if sum(colour) > 382 else (255, 255, 255)
    cv2.putText(img, text, (x + 2, y - 1), FONT, FONT_SCALE, ink, 1, cv2.LINE_AA)


def caption(img: np.ndarray, text: str) -> None:
    """White ``text`` on black in the image's top-left corner (in place)."""
    (tw, th), base = cv2.getTextSize(text, FONT, FONT_SCALE, 1)
    cv2.rectangle(img, (0, 0), (tw + 8, th + base + 6), (0, 0, 0), cv2.FILLED)
    cv2.putText(img, text, (4, th + 3), FONT, FONT_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
