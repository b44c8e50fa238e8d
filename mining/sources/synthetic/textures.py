"""Procedural textures of the synthetic world, packed into one mip-mapped atlas.

Every material is a small image ("tile") generated from seeded value noise and simple
patterns (bricks, windows, slabs, lane markings). Tiles repeat (wrap) in both axes, so a
face samples ``mod(s, w)``; each tile is stored with a wrapped border so bilinear lookups
across the seam are right at every mip level. Levels are box-filtered per tile, so a far
surface shows a blurred texture instead of aliasing noise (which would differ between the
left and right views and break stereo matching the way no real image does).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

NLEV = 4  # ours: mip levels (1, 1/2, 1/4, 1/8)
PAD_COARSE = 2  # ours: wrapped border at the coarsest level, texels
PAD = PAD_COARSE * 2 ** (NLEV - 1)  # border at level 0, texels
ATLAS_W = 2048  # ours: atlas width at level 0, texels


@dataclass(frozen=True)
class Tile:
    """Where a material lies in the atlas (level-0 texels) and how large it is in metres."""

    x0: int
    y0: int
    w: int
    h: int
    metres_w: float  # physical extent of one repeat; 0 = stretched over the whole face
    metres_h: float


@dataclass
class Atlas:
    levels: list[np.ndarray]  # uint8 (H/2^L, W/2^L, 3)
    tiles: dict[str, Tile]
    packed: np.ndarray | None = None  # all levels side by side; level L starts at x = 2·ATLAS_W·(1 − 2^−L)
    cache: dict = field(default_factory=dict)  # meshes built once per atlas (their rows hold its tile places)


# --------------------------------------------------------------------------- noise


def value_noise(rng: np.random.Generator, h: int, w: int, cells: tuple[int, int]) -> np.ndarray:
    """Periodic smooth noise in [0, 1]: a random grid of ``cells``, wrapped and resized cubically."""
    cy, cx = max(1, cells[0]), max(1, cells[1])
    g = rng.random((cy, cx), dtype=np.float32)
    g = np.pad(g, 2, mode="wrap")
    big = cv2.resize(g, ((cx + 4) * w // cx, (cy + 4) * h // cy), interpolation=cv2.INTER_CUBIC)
    oy, ox = 2 * h // cy, 2 * w // cx
    return big[oy : oy + h, ox : ox + w]


def fbm(rng: np.random.Generator, h: int, w: int, cells: int, octaves: int = 5, gain: float = 0.5) -> np.ndarray:
    """Multi-octave value noise, zero mean, roughly unit range. ``cells`` is the coarsest grid along w."""
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    cx = cells
    for _ in range(octaves):
        cy = max(1, round(cx * h / w))
        if cx > w or cy > h:
            break
        out += amp * (value_noise(rng, h, w, (cy, cx)) - 0.5)
        total += amp
        amp *= gain
        cx *= 2
    return out / total * 2.0


def speckle(rng: np.random.Generator, h: int, w: int, density: float) -> np.ndarray:
    """Sparse ±1 single-texel dots (asphalt grain, gravel), zero elsewhere."""
    r = rng.random((h, w), dtype=np.float32)
    s = rng.random((h, w), dtype=np.float32) * 2 - 1
    return np.where(r < density, s, 0).astype(np.float32)


def _rgb(grey: np.ndarray, colour: tuple[float, float, float]) -> np.ndarray:
    return grey[..., None] * np.asarray(colour, np.float32)[None, None, :]


# --------------------------------------------------------------------------- materials
# Each generator returns an (h, w, 3) float32 image in [0, 1]; texture row 0 is the top of
# a vertical face (texture v grows downwards like camera y).


def asphalt(rng, h, w) -> np.ndarray:
    g = 0.34 + 0.07 * fbm(rng, h, w, 4, 6) + 0.08 * fbm(rng, h, w, 96, 3) + 0.16 * speckle(rng, h, w, 0.15)
    g -= 0.05 * np.clip(fbm(rng, h, w, 3, 3) - 0.3, 0, 1)  # patches and stains
    return _rgb(g, (1.0, 1.0, 1.03))


def road(rng, h, w, lanes_per_dir: int, lane_m: float, parking_m: float, period_m: float) -> np.ndarray:
    """Asphalt with lane markings; x runs along the road (one dash period), y across it."""
    img = asphalt(rng, h, w)
    width_m = 2 * (lanes_per_dir * lane_m + parking_m)
    ty = (np.arange(h) + 0.5) / h * width_m - width_m / 2  # lateral offset, metres (+ = right)
    sx = (np.arange(w) + 0.5) / w * period_m
    dash = sx < period_m / 3.0  # ours: dash a third of the period (German urban 3 m / 6 m)
    paint = np.zeros((h, w), np.float32)

    def line(offset_m: float, half_w: float, dashed: bool):
        rows = np.abs(ty - offset_m) < half_w
        paint[rows] = np.where(dash, 1.0, 0.0)[None, :] if dashed else 1.0

    if lanes_per_dir == 1:
        line(0.0, 0.06, True)
    else:  # double solid centre line
        line(-0.12, 0.05, False)
        line(0.12, 0.05, False)
    for j in range(1, lanes_per_dir):
        line(j * lane_m, 0.06, True)
        line(-j * lane_m, 0.06, True)
    line(lanes_per_dir * lane_m, 0.08, False)
    line(-lanes_per_dir * lane_m, 0.08, False)
    wear = np.clip(0.75 + 0.5 * fbm(rng, h, w, 8, 4), 0.3, 1.0)
    paint *= wear
    return img * (1 - paint[..., None]) + 0.82 * paint[..., None]


def grass(rng, h, w) -> np.ndarray:
    g = 0.55 + 0.35 * fbm(rng, h, w, 6, 6) + 0.15 * speckle(rng, h, w, 0.3)
    dirt = np.clip(fbm(rng, h, w, 3, 3) * 2, 0, 1)[..., None]
    green = _rgb(g, (0.36, 0.45, 0.20))
    brown = _rgb(g, (0.45, 0.40, 0.30))
    return green * (1 - dirt) + brown * dirt


def slabs(rng, h, w, n_x: int, n_y: int, colour=(0.62, 0.60, 0.57)) -> np.ndarray:
    """Paving slabs: per-slab brightness, joints, fine grain."""
    per = 1.0 + 0.10 * (rng.random((n_y, n_x), dtype=np.float32) - 0.5) * 2
    g = cv2.resize(per, (w, h), interpolation=cv2.INTER_NEAREST)
    g = g * (0.9 + 0.12 * fbm(rng, h, w, 16, 4)) + 0.08 * speckle(rng, h, w, 0.1)
    jy = (np.arange(h) % (h // n_y)) < 2
    jx = (np.arange(w) % (w // n_x)) < 2
    g[jy, :] *= 0.7
    g[:, jx] *= 0.7
    return _rgb(g, colour)


def concrete(rng, h, w) -> np.ndarray:
    g = 0.68 + 0.10 * fbm(rng, h, w, 4, 6) + 0.05 * speckle(rng, h, w, 0.2)
    stain = np.clip(fbm(rng, h, w, 3, 4), 0, 1)
    g -= 0.15 * stain * np.linspace(0.3, 1.0, h, dtype=np.float32)[:, None]  # run-off towards the ground
    return _rgb(g, (0.95, 0.94, 0.92))


def bricks(rng, h, w, brick_w: int, brick_h: int, colour=(0.62, 0.33, 0.25)) -> np.ndarray:
    ny, nx = h // brick_h, w // brick_w
    per = 0.85 + 0.3 * rng.random((ny, nx * 2), dtype=np.float32)
    img = np.zeros((h, w), np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    row = yy // brick_h
    shift = (row % 2) * (brick_w // 2)
    col = ((xx + shift) // brick_w) % nx
    img = per[row % ny, col]
    mortar = ((yy % brick_h) < 1) | (((xx + shift) % brick_w) < 1)
    img = img * (0.92 + 0.10 * fbm(rng, h, w, 8, 4))
    out = _rgb(img, colour)
    out[mortar] = (0.72, 0.70, 0.66)
    return out


def window_bay(rng, wall: np.ndarray, win: tuple[int, int, int, int], frame_colour=(0.85, 0.85, 0.82)) -> np.ndarray:
    """Paste one window (x, y, w, h texels) with a frame, sill, glass reflections on a wall tile."""
    out = wall.copy()
    x, y, ww, hh = win
    f = max(2, ww // 16)
    out[y - f : y + hh + f, x - f : x + ww + f] = frame_colour
    gh, gw = hh, ww
    glass = 0.12 + 0.18 * np.linspace(1, 0, gh, dtype=np.float32)[:, None] + 0.12 * fbm(rng, gh, gw, 2, 3)
    glass = _rgb(np.clip(glass, 0.02, 1), (0.75, 0.85, 1.0))
    glass[:, gw // 2 - f // 2 : gw // 2 + f // 2 + 1] = frame_colour  # mullion
    out[y : y + hh, x : x + ww] = glass
    out[y + hh + f : y + hh + 2 * f, x - 2 * f : x + ww + 2 * f] = (0.55, 0.55, 0.55)  # sill
    return out


def planks(rng, h, w, n: int, colour=(0.55, 0.40, 0.26), vertical: bool = True) -> np.ndarray:
    base = (0.8 + 0.25 * rng.random(n, dtype=np.float32)).repeat(int(np.ceil((w if vertical else h) / n)))
    grain = fbm(rng, h, w, 2, 4) if vertical else fbm(rng, h, w, 24, 4)
    streak = value_noise(rng, h, w, (max(1, h // 4), max(1, w // 64))) if vertical else value_noise(rng, h, w, (max(1, h // 64), max(1, w // 4)))
    if vertical:
        g = base[None, :w] * (0.85 + 0.15 * grain + 0.15 * (streak - 0.5))
        gap = (np.arange(w) % int(np.ceil(w / n))) < 2
        g[:, gap] *= 0.35
    else:
        g = base[:h, None] * (0.85 + 0.15 * grain + 0.15 * (streak - 0.5))
        gap = (np.arange(h) % int(np.ceil(h / n))) < 2
        g[gap, :] *= 0.35
    return _rgb(g, colour)


def foliage(rng, h, w) -> np.ndarray:
    g = 0.5 + 0.55 * fbm(rng, h, w, 8, 5) + 0.25 * speckle(rng, h, w, 0.35)
    holes = fbm(rng, h, w, 16, 3) < -0.35
    g = np.where(holes, 0.15, g)
    return _rgb(np.clip(g, 0.05, 1.2), (0.30, 0.42, 0.17))


def bark(rng, h, w) -> np.ndarray:
    streak = value_noise(rng, h, w, (4, 12))
    g = 0.45 + 0.25 * (streak - 0.5) + 0.15 * fbm(rng, h, w, 8, 4)
    return _rgb(g, (0.45, 0.36, 0.28))


def paint(rng, h, w) -> np.ndarray:
    g = 0.86 + 0.04 * fbm(rng, h, w, 3, 5) + 0.015 * fbm(rng, h, w, 32, 2)
    return _rgb(g, (1, 1, 1))


def body_side(rng, h, w, part: str = "upper") -> np.ndarray:
    """A car's body side, stretched along the car: the ``upper`` part (waist line to the shoulder:
    sky-lit, a crease under the shoulder, door handles) or the ``lower`` part (waist to sill:
    shading down as the panel turns away from the sky, a black plastic sill); door seams at
    the same places on both."""
    img = paint(rng, h, w)
    y = (np.arange(h, dtype=np.float32) + 0.5) / h
    if part == "upper":
        shade = 1.08 - 0.12 * y
        shade[y < 0.12] *= 1.06
        shade[(y > 0.12) & (y < 0.2)] *= 0.8  # the crease under the shoulder
    else:
        shade = 0.98 - 0.3 * y ** 1.5
    img *= shade[:, None, None]
    for fx in (0.26, 0.53, 0.78):  # door seams: front wing | front door | rear door | rear quarter
        y1 = h if part == "upper" else int(0.8 * h)
        img[:y1, int(fx * w) : int(fx * w) + 2] *= 0.45
    if part == "upper":
        for fx in (0.46, 0.72):  # handles: a dark recess under a bright edge
            x0, x1 = int(fx * w), int(fx * w) + max(3, w // 22)
            img[int(0.4 * h) : int(0.48 * h), x0:x1] *= 1.25
            img[int(0.48 * h) : int(0.6 * h), x0:x1] *= 0.35
    else:
        img[int(0.8 * h) :, :] = 0.16  # sill: black plastic (the tint barely shows)
    return img


def rear_panel(rng, h, w) -> np.ndarray:
    """A car's rear below the lamps, stretched (painted): a crease under the lamps, the recess
    the plate sits in, the bumper's top seam with its reflectors, shading towards the bottom."""
    img = paint(rng, h, w)
    y = (np.arange(h, dtype=np.float32) + 0.5) / h
    img *= (1.04 - 0.22 * y)[:, None, None]
    img[int(0.08 * h) : int(0.12 * h)] *= 1.2
    img[int(0.12 * h) : int(0.17 * h)] *= 0.7
    img[int(0.3 * h) : int(0.62 * h), int(0.3 * w) : int(0.7 * w)] *= 0.8
    img[int(0.62 * h) : int(0.66 * h)] *= 0.45
    for x0 in (0.04, 0.9):
        img[int(0.72 * h) : int(0.8 * h), int(x0 * w) : int((x0 + 0.06) * w)] = (0.6, 0.05, 0.04)
    return img


def glass(rng, h, w, frame: float = 0.06) -> np.ndarray:
    """Tinted glass: dark, with the sky reflected brighter towards the top and one soft diagonal
    streak, inside a black seal. Untinted faces: the colour is the glass's own."""
    y = (np.arange(h, dtype=np.float32) + 0.5)[:, None] / h
    x = (np.arange(w, dtype=np.float32) + 0.5)[None, :] / w
    g = 0.11 + 0.3 * (1 - y) ** 2 + 0.05 * fbm(rng, h, w, 2, 3)
    streak = np.exp(-(((x - 0.9 * y - rng.uniform(0.1, 0.6)) / 0.08) ** 2))
    g = g + 0.12 * streak * (1 - y)
    img = _rgb(g, (0.78, 0.86, 1.0))
    fy, fx = max(1, int(frame * h)), max(1, int(frame * w * h / max(w, 1)))
    img[:fy], img[-fy:], img[:, :fx], img[:, -fx:] = 0.05, 0.05, 0.05, 0.05
    return img


def headlight_band(rng, h, w) -> np.ndarray:
    """The front between the bonnet and the bumper (untinted): headlight units at both ends
    (chrome reflector, clear lens, a bright lamp), a black grille with bars between them."""
    img = np.full((h, w, 3), 0.09, np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    for x0, x1 in ((0.02, 0.25), (0.75, 0.98)):
        m = (xx >= x0 * w) & (xx < x1 * w) & (yy > 0.15 * h) & (yy < 0.8 * h)
        refl = 0.42 + 0.14 * np.cos((xx - (x0 + x1) / 2 * w) / ((x1 - x0) * w) * 6.0) * np.cos((yy - h / 2) / h * 3)
        img[m] = (refl[m][:, None] * np.array([0.95, 0.96, 1.0], np.float32))
        cx = (x0 + 0.3 * (x1 - x0)) if x0 < 0.5 else (x1 - 0.3 * (x1 - x0))
        lamp = ((xx - cx * w) / (0.05 * w)) ** 2 + ((yy - 0.47 * h) / (0.2 * h)) ** 2 < 1
        img[lamp] = (0.78, 0.78, 0.76)  # daytime: the lamp unlit, a bright reflector
    grille = (xx >= 0.32 * w) & (xx < 0.68 * w) & (yy > 0.2 * h) & (yy < 0.95 * h)
    bars = (yy % max(3, h // 6)) < 1
    img[grille] = 0.05
    img[grille & bars] = 0.3
    img[(xx >= 0.47 * w) & (xx < 0.53 * w) & (yy > 0.35 * h) & (yy < 0.75 * h)] = 0.75  # badge
    return img


def lamp(rng, h, w) -> np.ndarray:
    """A headlamp's clear lens where it wraps round the corner (untinted): chrome and glass."""
    y = (np.arange(h, dtype=np.float32) + 0.5)[:, None] / h
    g = 0.38 + 0.12 * np.cos(y * 5.0) + 0.04 * fbm(rng, h, w, 2, 2)
    return _rgb(np.broadcast_to(g, (h, w)).copy(), (0.95, 0.96, 1.0))


def tail_light(rng, h, w) -> np.ndarray:
    """A rear lamp cluster (untinted): red lens, brighter inner ring, a white reversing lamp."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot((xx + 0.5) / w - 0.5, (yy + 0.5) / h - 0.5) * 2
    img = _rgb(0.55 + 0.25 * np.clip(1 - r, 0, 1) + 0.05 * fbm(rng, h, w, 2, 2), (1.0, 0.12, 0.08))
    img[(r > 0.45) & (r < 0.6)] *= 1.35
    img[int(0.62 * h) :, int(0.15 * w) : int(0.45 * w)] = (0.85, 0.85, 0.82)
    img[:1], img[-1:], img[:, :1], img[:, -1:] = 0.1, 0.1, 0.1, 0.1
    return np.clip(img, 0, 1)


def number_plate(rng, h, w) -> np.ndarray:
    """A European plate (untinted): white, a blue band on the left, black characters, a frame."""
    img = np.full((h, w, 3), 0.92, np.float32)
    img[:, : max(2, w // 11)] = (0.05, 0.15, 0.6)
    x = w // 11 + 3
    while x < w - 4:
        cw = int(rng.integers(3, 5))
        if rng.random() < 0.85:
            img[int(0.2 * h) : int(0.8 * h), x : x + cw] = 0.08
        x += cw + 2
    img[:1], img[-1:], img[:, :1], img[:, -1:] = 0.2, 0.2, 0.2, 0.2
    return img


def wheel_face(rng, h, w) -> np.ndarray:
    """A wheel seen from the side, stretched over its disc: tyre sidewall, five-spoke alloy rim
    (the face's tint colours the rim: silver, dark or steel), hub."""
    yy, xx = np.mgrid[0:h, 0:w]
    dx, dy = (xx + 0.5) / w - 0.5, (yy + 0.5) / h - 0.5
    r = np.hypot(dx, dy) * 2
    ang = np.arctan2(dy, dx)
    g = 0.08 + 0.04 * fbm(rng, h, w, 4, 3)
    rim = r < 0.66
    spokes = np.cos(ang * 5) > 0.1 - 0.6 * np.clip(0.4 - r, 0, 1)
    g = np.where(rim, np.where(spokes | (r > 0.58) | (r < 0.2), 0.72 - 0.2 * r, 0.1), g)
    g = np.where(r < 0.08, 0.35, g)
    g = np.where((r > 0.66) & (r < 0.7), 0.2, g)
    return _rgb(g.astype(np.float32), (1, 1, 1))


def contact_shadow(rng, h, w) -> np.ndarray:
    """The shadow under a vehicle or person, stretched over its footprint: dark asphalt in the
    middle, fading towards the road's own brightness at the border (no alpha: the border is
    the asphalt's mean grey, so it does not show as an edge)."""
    y = ((np.arange(h, dtype=np.float32) + 0.5) / h - 0.5)[:, None] * 2
    x = ((np.arange(w, dtype=np.float32) + 0.5) / w - 0.5)[None, :] * 2
    d = np.clip((np.maximum(np.abs(x) ** 4 + np.abs(y) ** 4, 0) ** 0.25 - 0.55) / 0.45, 0, 1)
    g = 0.34 * (0.12 + 0.88 * d * d * (3 - 2 * d)) + 0.05 * speckle(rng, h, w, 0.15)
    return _rgb(g, (1.0, 1.0, 1.03))


def glass_panes(rng, h, w, n_panes: int, pillar: float = 0.08) -> np.ndarray:
    """Window band: dark reflective panes separated by light pillars (painted, so tinted)."""
    img = paint(rng, h, w)
    g = 0.10 + 0.20 * np.linspace(1, 0.2, h, dtype=np.float32)[:, None] + 0.10 * fbm(rng, h, w, 2, 3)
    panes = _rgb(g, (0.7, 0.8, 0.95))
    x = (np.arange(w) + 0.5) / w * n_panes
    inside = np.abs(x - np.floor(x) - 0.5) < 0.5 - pillar / 2
    rows = (np.arange(h) > 0.1 * h) & (np.arange(h) < 0.9 * h)
    m = rows[:, None] & inside[None, :]
    img[m] = panes[m]
    return img


def rubber(rng, h, w) -> np.ndarray:
    return _rgb(0.07 + 0.03 * fbm(rng, h, w, 4, 3), (1, 1, 1))


def trim(rng, h, w) -> np.ndarray:
    return _rgb(0.14 + 0.04 * fbm(rng, h, w, 4, 3) + 0.03 * speckle(rng, h, w, 0.2), (1, 1, 1))


def barrier_stripes(rng, h, w) -> np.ndarray:
    """A road barrier board (untinted): red and white diagonal stripes, a dirty edge."""
    yy, xx = np.mgrid[0:h, 0:w]
    red = ((xx + yy) // max(2, h // 2)) % 2 == 0
    img = np.where(red[..., None], np.array([0.75, 0.08, 0.06], np.float32), np.array([0.92, 0.92, 0.9], np.float32))
    img = img * (0.92 + 0.08 * fbm(rng, h, w, 4, 3))[..., None]
    e = max(1, h // 16)
    img[:e] *= 0.7
    img[-e:] *= 0.7
    return img


def cardboard(rng, h, w) -> np.ndarray:
    """A cardboard box face, stretched: brown corrugated board, a tape strip across the middle."""
    g = 0.8 + 0.08 * fbm(rng, h, w, 3, 4) + 0.04 * np.sin(np.arange(w) * 1.3)[None, :]
    img = _rgb(g, (0.66, 0.5, 0.32))
    img[int(0.44 * h) : int(0.56 * h)] = (0.78, 0.7, 0.55)
    for edge in (img[:1], img[-1:], img[:, :1], img[:, -1:]):
        edge[:] = (0.45, 0.34, 0.22)
    return img


def shell(rng, h, w) -> np.ndarray:
    """A tortoise shell: dark-rimmed polygonal scutes with lighter centres."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    cell = 16.0
    row = np.floor(yy / cell)
    u = (xx + (row % 2) * cell / 2) / cell
    fu, fv = u - np.floor(u) - 0.5, yy / cell - row - 0.5
    r = np.maximum(np.abs(fu) * 1.15, np.abs(fv))
    g = 0.75 - 0.5 * np.clip((r - 0.3) / 0.2, 0, 1) + 0.08 * fbm(rng, h, w, 4, 3)
    return _rgb(g, (0.55, 0.42, 0.22))


def hair(rng, h, w) -> np.ndarray:
    streak = value_noise(rng, h, w, (2, 24))
    return _rgb(0.75 + 0.25 * (streak - 0.5) + 0.06 * fbm(rng, h, w, 8, 3), (1, 1, 1))


def corrugated(rng, h, w, period: int) -> np.ndarray:
    g = 0.80 + 0.10 * np.sin(np.arange(w) * 2 * np.pi / period)[None, :] + 0.06 * fbm(rng, h, w, 4, 4)
    g += 0.08 * speckle(rng, h, w, 0.02)
    return _rgb(g.astype(np.float32), (1, 1, 1))


def fabric(rng, h, w) -> np.ndarray:
    g = 0.75 + 0.18 * fbm(rng, h, w, 3, 5) + 0.06 * speckle(rng, h, w, 0.3)
    return _rgb(g, (1, 1, 1))


def cone_bands(rng, h, w) -> np.ndarray:
    g = 0.9 + 0.06 * fbm(rng, h, w, 2, 3)
    img = _rgb(g, (1.0, 0.42, 0.08))
    yy = (np.arange(h) + 0.5) / h
    white = ((yy > 0.25) & (yy < 0.38)) | ((yy > 0.55) & (yy < 0.66))
    img[white] = (0.93, 0.93, 0.90)
    return img


def stone(rng, h, w) -> np.ndarray:
    g = 0.55 + 0.25 * fbm(rng, h, w, 4, 6) + 0.12 * speckle(rng, h, w, 0.25)
    veins = np.abs(fbm(rng, h, w, 3, 4)) < 0.05
    g[veins] *= 0.6
    return _rgb(g, (1.0, 0.97, 0.92))


def mottled(rng, h, w) -> np.ndarray:
    spots = fbm(rng, h, w, 6, 4)
    g = 0.65 + 0.15 * fbm(rng, h, w, 24, 3) + 0.1 * speckle(rng, h, w, 0.4)
    g = np.where(spots > 0.2, g * 0.45, g)
    return _rgb(g, (1, 1, 1))


def _wrapped_leaves(rng, h: int, w: int, n: int, size_px: tuple[float, float], colours: np.ndarray) -> np.ndarray:
    """``n`` leaf-shaped ellipses of random size, angle and colour (rows of ``colours`` mixed),
    painted in random order over a dark ground; a leaf that crosses the tile's edge is drawn
    again shifted by the tile size, so the tile wraps without a seam."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = colours[0] * 0.35  # the shadowed inside of the bush between leaves
    xy = rng.random((n, 2)) * (w, h)
    ax = rng.uniform(*size_px, (n, 1)) * (1.0, 0.5)  # a leaf about twice as long as wide
    ang = rng.uniform(0, 180, n)
    mix = rng.random((n, len(colours)))
    mix /= mix.sum(1, keepdims=True)
    cols = (mix @ colours) * rng.uniform(0.55, 1.25, (n, 1))
    sub = 4  # cv2's 2 fractional bits: sub-texel leaf shapes
    for (x, y), (a, b), t, col in zip(xy.tolist(), ax.tolist(), ang.tolist(), cols.tolist()):
        for dy in (-h, 0, h):
            if not -a < y + dy < h + a:
                continue
            for dx in (-w, 0, w):
                if -a < x + dx < w + a:
                    cv2.ellipse(img, (round((x + dx) * sub), round((y + dy) * sub)),
                                (max(1, round(a * sub)), max(1, round(b * sub))), t, 0, 360, col, -1, cv2.LINE_AA, 2)
    return img


HEDGE_LEAVES = 1400  # ours: leaves per hedge tile (1.5 m square): they cover it about twice over
HEDGE_LEAF_PX = (2.0, 4.5)  # ours: a leaf's half length in texels (128 a metre: leaves 3–7 cm, privet's size)


def hedge(rng, h, w) -> np.ndarray:
    """A clipped hedge's surface (privet, beech): a mat of small overlapping leaves in several
    greens, darker hollows between them and a faint large-scale mottling."""
    colours = np.array([[0.20, 0.36, 0.10], [0.30, 0.45, 0.14], [0.16, 0.28, 0.09], [0.36, 0.46, 0.18]], np.float32)
    img = _wrapped_leaves(rng, h, w, HEDGE_LEAVES, HEDGE_LEAF_PX, colours)
    hollow = np.clip(-fbm(rng, h, w, 6, 4) - 0.15, 0, 1)[..., None]  # gaps into the dark inside
    img = img * (1 - 0.7 * hollow) * (0.9 + 0.15 * fbm(rng, h, w, 2, 3))[..., None]
    return np.clip(img, 0, 1)


def lawn(rng, h, w) -> np.ndarray:
    """Mown verge grass: fine blades (short streaks along v), yellower and browner patches."""
    blades = value_noise(rng, h, w, (h // 6, w // 2)) - 0.5  # cells 2 texels wide, 6 long: blade-like
    g = 0.62 + 0.45 * blades + 0.2 * fbm(rng, h, w, 8, 4) + 0.15 * speckle(rng, h, w, 0.25)
    dry = np.clip(fbm(rng, h, w, 4, 4) * 1.5, 0, 1)[..., None]
    green = _rgb(g, (0.30, 0.48, 0.16))
    straw = _rgb(g, (0.50, 0.50, 0.26))
    return np.clip(green * (1 - dry) + straw * dry, 0, 1)


def timber(rng, h, w) -> np.ndarray:
    """Weathered softwood (fence posts and rails): grey-brown, the grain along v."""
    grain = value_noise(rng, h, w, (2, w // 3)) - 0.5
    g = 0.62 + 0.3 * grain + 0.1 * fbm(rng, h, w, 4, 4) + 0.05 * speckle(rng, h, w, 0.2)
    return _rgb(g, (0.62, 0.55, 0.45))


def sky_clouds(rng, h, w) -> np.ndarray:
    """Cloud cover in [0, 1] over azimuth (x, periodic) × elevation (y, row 0 = zenith)."""
    c = fbm(rng, h, w, 8, 6, 0.55)
    return np.clip((c + 0.1) * 1.6, 0, 1)[..., None].repeat(3, axis=2).astype(np.float32)


# --------------------------------------------------------------------------- the atlas

# name → (texels w, texels h, metres w, metres h); metres 0 means stretched over the face.
ROAD_PERIOD_M = 12.0  # ours: lane-marking dash period along the road
LANE_M = 3.5  # ours: lane width
PARKING_M = 2.2  # ours: parking strip beside the outer lane


def road_width_m(lanes_per_dir: int) -> float:
    return 2 * (lanes_per_dir * LANE_M + PARKING_M)


def _tile_specs() -> dict[str, tuple[int, int, float, float]]:
    d = 64  # ours: road and sidewalk texels per metre (≈1.5 cm, finer than a pixel beyond 8 m)
    specs = {
        "road1": (768, _mult8(road_width_m(1) * d), ROAD_PERIOD_M, road_width_m(1)),
        "road2": (768, _mult8(road_width_m(2) * d), ROAD_PERIOD_M, road_width_m(2)),
        "sidewalk": (192, 192, 3.0, 3.0),
        "concrete": (192, 192, 4.0, 4.0),
        "grass": (512, 512, 16.0, 16.0),
        "facade_brick": (144, 152, 3.0, 3.2),
        "facade_plaster": (144, 152, 3.0, 3.2),
        "facade_glass": (144, 152, 3.0, 3.2),
        "facade_stone": (144, 152, 3.0, 3.2),
        "fence": (256, 64, 2.0, 1.0),
        "bark": (64, 128, 0.5, 1.0),
        "foliage": (192, 192, 2.0, 2.0),
        "metal": (64, 64, 1.0, 1.0),
        "paint": (128, 128, 2.0, 2.0),
        "body_side": (256, 32, 0, 0),
        "body_lower": (256, 32, 0, 0),
        "glass": (128, 64, 0, 0),
        "rear_panel": (128, 64, 0, 0),
        "headlights": (128, 32, 0, 0),
        "tail_light": (32, 32, 0, 0),
        "lamp": (16, 16, 0, 0),
        "plate": (64, 16, 0, 0),
        "wheel": (64, 64, 0, 0),
        "shadow": (64, 64, 0, 0),
        "rubber": (32, 32, 0.5, 0.5),
        "trim": (32, 32, 0.5, 0.5),
        "barrier": (128, 32, 0, 0),
        "cardboard": (64, 64, 0, 0),
        "shell": (96, 96, 0.4, 0.4),
        "hair": (32, 32, 0.2, 0.2),
        "corrugated": (128, 128, 1.0, 1.0),
        "bus_side": (128, 192, 2.0, 3.0),
        "fabric": (64, 64, 0.5, 0.5),
        "skin": (64, 64, 0.5, 0.5),
        "cone": (64, 128, 0, 0),
        "bin": (64, 128, 0.5, 1.0),
        "crate": (128, 128, 0, 0),
        "stone": (96, 96, 1.0, 1.0),
        "mottled": (96, 96, 1.0, 1.0),
        "clouds": (1024, 128, 0, 0),
    }
    return specs


# Tiles packed after the main ones, on shelves of their own below them: adding one moves no
# main tile and draws no random number of theirs, so the worlds drawn before stay bit-identical.
EXTRA_TILES = {
    "flat": (64, 64, 1.0, 1.0),  # ours: one uniform grey, a textureless surface (scenario "textureless")
    # the roadside clutter of scenario "verge" (names sort after "flat": its seed index stays 0)
    "hedge": (192, 192, 1.5, 1.5),  # ours: 0.8 cm a texel, fine enough for 3–7 cm leaves
    "lawn": (256, 256, 2.0, 2.0),  # ours: mown grass, blades ~1 cm
    "timber": (64, 128, 0.5, 1.0),  # ours: weathered fence wood, grain along v
}


def _mult8(x: float) -> int:
    return int(round(x / 8.0)) * 8


def make_tile(name: str, rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    if name == "road1":
        return road(rng, h, w, 1, LANE_M, PARKING_M, ROAD_PERIOD_M)
    if name == "road2":
        return road(rng, h, w, 2, LANE_M, PARKING_M, ROAD_PERIOD_M)
    if name == "sidewalk":
        return slabs(rng, h, w, 6, 6)
    if name == "concrete":
        return concrete(rng, h, w)
    if name == "grass":
        return grass(rng, h, w)
    if name == "facade_brick":
        return window_bay(rng, bricks(rng, h, w, 12, 4), (38, 30, 68, 72))
    if name == "facade_plaster":
        wall = _rgb(0.8 + 0.08 * fbm(rng, h, w, 4, 5) + 0.04 * speckle(rng, h, w, 0.2), (1, 1, 1))
        return window_bay(rng, wall, (44, 36, 56, 70), (0.95, 0.95, 0.95))
    if name == "facade_glass":
        wall = _rgb(0.55 + 0.05 * fbm(rng, h, w, 4, 4), (0.9, 0.9, 0.92))
        return window_bay(rng, wall, (10, 14, 124, 124), (0.5, 0.5, 0.52))
    if name == "facade_stone":
        return window_bay(rng, bricks(rng, h, w, 36, 18, (0.7, 0.68, 0.62)), (40, 34, 64, 76))
    if name == "fence":
        return planks(rng, h, w, 20)
    if name == "bark":
        return bark(rng, h, w)
    if name == "foliage":
        return foliage(rng, h, w)
    if name == "metal":
        return _rgb(0.6 + 0.08 * fbm(rng, h, w, 4, 4), (0.9, 0.92, 0.95))
    if name == "paint":
        return paint(rng, h, w)
    if name == "body_side":
        return body_side(rng, h, w, "upper")
    if name == "body_lower":
        return body_side(rng, h, w, "lower")
    if name == "rear_panel":
        return rear_panel(rng, h, w)
    if name == "glass":
        return glass(rng, h, w)
    if name == "headlights":
        return headlight_band(rng, h, w)
    if name == "lamp":
        return lamp(rng, h, w)
    if name == "tail_light":
        return tail_light(rng, h, w)
    if name == "plate":
        return number_plate(rng, h, w)
    if name == "wheel":
        return wheel_face(rng, h, w)
    if name == "shadow":
        return contact_shadow(rng, h, w)
    if name == "rubber":
        return rubber(rng, h, w)
    if name == "trim":
        return trim(rng, h, w)
    if name == "barrier":
        return barrier_stripes(rng, h, w)
    if name == "cardboard":
        return cardboard(rng, h, w)
    if name == "shell":
        return shell(rng, h, w)
    if name == "hair":
        return hair(rng, h, w)
    if name == "corrugated":
        return corrugated(rng, h, w, 16)
    if name == "bus_side":
        body = paint(rng, h, w)
        band = glass_panes(rng, h // 2, w, 1, 0.12)
        body[h // 8 : h // 8 + h // 2] = band
        return body
    if name == "fabric":
        return fabric(rng, h, w)
    if name == "skin":
        return _rgb(0.85 + 0.05 * fbm(rng, h, w, 4, 3), (1, 1, 1))
    if name == "cone":
        return cone_bands(rng, h, w)
    if name == "bin":
        return corrugated(rng, h, w, 8)
    if name == "crate":
        img = planks(rng, h, w, 5, (0.72, 0.58, 0.38), vertical=False)
        img[:, :8] *= 0.8
        img[:, -8:] *= 0.8
        return img
    if name == "stone":
        return stone(rng, h, w)
    if name == "mottled":
        return mottled(rng, h, w)
    if name == "clouds":
        return sky_clouds(rng, h, w)
    if name == "flat":
        return np.full((h, w, 3), 0.75, np.float32)
    if name == "hedge":
        return hedge(rng, h, w)
    if name == "lawn":
        return lawn(rng, h, w)
    if name == "timber":
        return timber(rng, h, w)
    raise KeyError(name)


def build_atlas(seed: int) -> Atlas:
    """Generate every material tile from ``seed`` and pack them into a mip-mapped atlas."""
    specs = _tile_specs()
    tiles_img: dict[str, np.ndarray] = {}
    for i, (name, (w, h, _, _)) in enumerate(sorted(specs.items())):
        rng = np.random.default_rng([seed, i, 7771])
        img = make_tile(name, rng, w, h)
        assert img.shape == (h, w, 3), (name, img.shape)
        tiles_img[name] = np.clip(img, 0, 1).astype(np.float32)
    # shelf packing, tallest first
    order = sorted(specs, key=lambda n: (-specs[n][1], n))
    x = y = shelf_h = 0
    pos: dict[str, tuple[int, int]] = {}
    for name in order:
        w, h = specs[name][0] + 2 * PAD, specs[name][1] + 2 * PAD
        if x + w > ATLAS_W:
            x, y, shelf_h = 0, y + shelf_h, 0
        pos[name] = (x, y)
        x += w
        shelf_h = max(shelf_h, h)
    x, y, shelf_h = 0, _mult8(y + shelf_h + 8), 0
    for i, (name, (w, h, _, _)) in enumerate(sorted(EXTRA_TILES.items())):
        img = make_tile(name, np.random.default_rng([seed, 1000 + i, 7771]), w, h)
        tiles_img[name] = np.clip(img, 0, 1).astype(np.float32)
        if x + w + 2 * PAD > ATLAS_W:
            x, y, shelf_h = 0, y + shelf_h, 0
        pos[name] = (x, y)
        x += w + 2 * PAD
        shelf_h = max(shelf_h, h + 2 * PAD)
    specs = specs | EXTRA_TILES
    total_h = _mult8(y + shelf_h + 8)
    levels = []
    for lev in range(NLEV):
        f = 2**lev
        atlas = np.zeros((total_h // f, ATLAS_W // f, 3), np.uint8)
        pad = PAD // f
        for name, (sx, sy) in pos.items():
            img = tiles_img[name]
            if lev:
                img = cv2.resize(img, (img.shape[1] // f, img.shape[0] // f), interpolation=cv2.INTER_AREA)
            img = np.pad(img, ((pad, pad), (pad, pad), (0, 0)), mode="wrap")
            atlas[sy // f : sy // f + img.shape[0], sx // f : sx // f + img.shape[1]] = np.round(img * 255)
        levels.append(atlas)
    packed = np.zeros((total_h, 2 * ATLAS_W, 3), np.uint8)
    for lev, img in enumerate(levels):
        x = int(2 * ATLAS_W * (1 - 2.0**-lev))
        packed[: img.shape[0], x : x + img.shape[1]] = img
    tiles = {n: Tile(pos[n][0] + PAD, pos[n][1] + PAD, specs[n][0], specs[n][1], specs[n][2], specs[n][3]) for n in specs}
    return Atlas(levels, tiles, packed)
