"""Z-buffer rasteriser of textured planar faces for a rectified pinhole camera.

Per face: clip against the near plane, project, fill its mask in its bounding rectangle
(cv2.fillConvexPoly), evaluate the exact inverse depth (affine in u, v for a plane), z-test,
write the face id. Faces go nearest first, so a face whose whole rectangle is already covered
by nearer surfaces is skipped after one comparison. Small faces (most faces: distant structure
and objects) skip the per-face Python loop: one vectorised pass tests their few candidate
pixels against the edge lines and resolves the z-test by sorting.

Shading. For a plane, texture coordinates are a homography of the pixel: s = (A·p)/(C·p) with
p = (u, v, 1) and C·p the inverse depth the rasteriser already stored. So a pixel needs its
face's A and B rows (six numbers), its tile, its light and one number for the mip level: the
texel area per pixel is |det J| = |det H| / (C·p)³ (H = [A; B; C]), a per-face constant times
z³. Two bilinear remaps of the packed atlas (levels ⌊lev⌋ and ⌊lev⌋+1) blend trilinearly.
Shading runs in bands of rows so its temporaries stay in cache; every pixel depends only on
its own face id and inverse depth, so the band height changes no bit.
"""

from __future__ import annotations

import cv2
import numpy as np

from mining.sources.synthetic.scene import R_N, R_NV, R_O, R_TILE, R_U, R_V
from mining.sources.synthetic.textures import NLEV, Atlas

NEAR_M = 0.3  # ours: near clipping plane
FAR_M = 400.0  # ours: faces entirely beyond are dropped
SUB = 4  # fillConvexPoly fixed-point bits (1/16 px vertices)
SKY_INVZ = 1e-6  # ours: inverse depth stored for sky pixels (1000 km; any face is nearer)
MIP_BIAS = -0.2  # ours: level offset (slightly sharper than the texel-area level)
SMALL_PX = 8  # ours: faces within this square rectangle are rasterised together, vectorised
EDGE_MARGIN_PX = 0.42  # ours: edge lines moved out this far match cv2.fillConvexPoly's coverage (measured)
STRIP = 24  # ours: rows shaded at a time (temporaries fit the L2 cache)


class Camera:
    def __init__(self, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
        self.fx, self.fy, self.cx, self.cy, self.w, self.h = fx, fy, cx, cy, width, height
        self.u = np.arange(width, dtype=np.float32)
        self.v = np.arange(height, dtype=np.float32)
        self.ugrid = np.repeat(self.u[None, :], height, 0)
        self.vgrid = np.repeat(self.v[:, None], width, 1)


def _clip_near(poly: np.ndarray) -> np.ndarray:
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= NEAR_M, b[2] >= NEAR_M
        if ina:
            out.append(a)
        if ina != inb:
            t = (NEAR_M - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out)


def inverse_depth_planes(cam: Camera, rows: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per face (camera-frame vertices ``V``): C = (ia, ib, ic) with 1/z = ia·u + ib·v + ic, and n·X0.
    From the plane n·X = dp and X = z·((u-cx)/fx, (v-cy)/fy, 1)."""
    n = rows[:, R_N : R_N + 3]
    dp = np.einsum("ij,ij->i", n, V[:, 0])
    safe = np.where(np.abs(dp) > 1e-12, dp, 1e-12)
    C = np.stack([n[:, 0] / cam.fx, n[:, 1] / cam.fy, n[:, 2] - n[:, 0] * cam.cx / cam.fx - n[:, 1] * cam.cy / cam.fy], 1)
    return C / safe[:, None], dp


def to_camera(verts: np.ndarray, rows: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and the rows' normal, origin and texture axes from map to camera frame (float64)."""
    V = verts @ R.T + t
    rc = rows.copy()
    for c in (R_N, R_U, R_V):
        rc[:, c : c + 3] = rows[:, c : c + 3] @ R.T
    rc[:, R_O : R_O + 3] = rows[:, R_O : R_O + 3] @ R.T + t
    return V, rc


def rasterize(cam: Camera, V: np.ndarray, rows_cam: np.ndarray, C: np.ndarray, dp: np.ndarray, small_px: int = SMALL_PX):
    """Camera-frame faces → (face id (H,W) int32, -1 = sky; inverse depth (H,W) float32, SKY_INVZ on sky).
    Faces within a ``small_px`` square go through the vectorised pass (0: none)."""
    H, W = cam.h, cam.w
    z = V[:, :, 2]
    keep = (dp < -1e-6) & (z.max(1) > NEAR_M) & (z.min(1) < FAR_M)
    zc = np.maximum(z, NEAR_M)
    px = cam.fx * V[:, :, 0] / zc + cam.cx
    py = cam.fy * V[:, :, 1] / zc + cam.cy
    allin = z.min(1) >= NEAR_M
    keep &= ~(allin & ((px.max(1) < -1) | (px.min(1) > W) | (py.max(1) < -1) | (py.min(1) > H)))
    ids = np.full((H, W), -1, np.int32)
    invz = np.full((H, W), SKY_INVZ, np.float32)
    # inverse depth range of each face's (unclipped) vertices: raster edge pixels just outside
    # an oblique face must not extrapolate its plane to a wrong depth
    izv = 1.0 / zc
    iz_lo, iz_hi = (izv.min(1) * 0.999).astype(np.float32), (izv.max(1) * 1.001).astype(np.float32)
    bx0 = np.floor(px.min(1)).clip(0, W).astype(int)
    by0 = np.floor(py.min(1)).clip(0, H).astype(int)
    bx1 = (np.ceil(px.max(1)) + 1).clip(0, W).astype(int)
    by1 = (np.ceil(py.max(1)) + 1).clip(0, H).astype(int)
    pq = np.round(np.stack([px, py], 2).clip(-1e5, 1e5) * (1 << SUB)).astype(np.int32)
    pq -= np.stack([bx0, by0], 1)[:, None, :].astype(np.int32) << SUB  # relative to the rectangle
    # small faces (most of them: distant structure and objects) in one vectorised pass after
    # the loop; the rest nearest first (by the nearest vertex), ties by face index
    small = keep & allin & (bx1 - bx0 <= small_px) & (by1 - by0 <= small_px)
    cand = np.nonzero(keep & ~small)[0]
    cand = cand[np.argsort(-izv[cand].max(1), kind="stable")]
    per_face = zip(cand.tolist(), allin[cand].tolist(), rows_cam[cand, R_NV].astype(int).tolist(),
                   bx0[cand].tolist(), by0[cand].tolist(), bx1[cand].tolist(), by1[cand].tolist(),
                   iz_lo[cand].tolist(), iz_hi[cand].tolist(), *C[cand].astype(np.float32).T.tolist())
    for f, inside, nv, x0, y0, x1, y1, lo, hi, ia, ib, ic in per_face:
        if inside:
            if x1 <= x0 or y1 <= y0:
                continue
            zr = invz[y0:y1, x0:x1]
            if cv2.minMaxLoc(zr)[0] > hi:  # occluded: nearer faces already cover the whole rectangle
                continue
            q = pq[f, :nv]
        else:
            poly = _clip_near(V[f, :nv])
            if len(poly) < 3:
                continue
            p = np.stack([cam.fx * poly[:, 0] / poly[:, 2] + cam.cx, cam.fy * poly[:, 1] / poly[:, 2] + cam.cy], 1)
            x0, y0 = max(0, int(np.floor(p[:, 0].min()))), max(0, int(np.floor(p[:, 1].min())))
            x1, y1 = min(W, int(np.ceil(p[:, 0].max())) + 1), min(H, int(np.ceil(p[:, 1].max())) + 1)
            if x1 <= x0 or y1 <= y0:
                continue
            q = np.round((p - [x0, y0]) * (1 << SUB)).astype(np.int32)
            zr = invz[y0:y1, x0:x1]
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, q, 1, lineType=cv2.LINE_8, shift=SUB)
        # (OpenCV calls: a few microseconds less per face than the numpy equivalents)
        iz = cv2.addWeighted(cam.ugrid[y0:y1, x0:x1], ia, cam.vgrid[y0:y1, x0:x1], ib, ic)
        cv2.min(iz, hi, dst=iz)
        cv2.max(iz, lo, dst=iz)
        win = cv2.compare(iz, zr, cv2.CMP_GT)  # 0 / 255
        cv2.bitwise_and(win, mask, dst=win)  # 0 / 1
        cv2.copyTo(iz, win, zr)
        np.copyto(ids[y0:y1, x0:x1], f, where=win.view(bool))
    sel = np.nonzero(small)[0]
    _raster_small(small_px, sel, px[sel], py[sel], bx0[sel], by0[sel], bx1[sel], by1[sel], C[sel].astype(np.float32),
                  iz_lo[sel], iz_hi[sel], ids, invz)
    return ids, invz


def _raster_small(side, f, px, py, bx0, by0, bx1, by1, C, lo, hi, ids, invz) -> None:
    """Faces whose rectangle fits a ``side`` square, all at once: a pixel is in a face when its
    centre lies inside every edge line moved EDGE_MARGIN_PX outwards; z-test against the buffer,
    then the nearest candidate per pixel wins (ties: the lower face index)."""
    if len(f) == 0:
        return
    H, W = ids.shape
    o = np.arange(side, dtype=np.float32)
    X = (bx0[:, None, None] + o[None, None, :]).astype(np.float32)  # (n, 1, S) pixel centres
    Y = (by0[:, None, None] + o[None, :, None]).astype(np.float32)  # (n, S, 1)
    valid = (X < bx1[:, None, None]) & (Y < by1[:, None, None])
    # vertices are padded by repeating the last one: the extra edges have zero length and
    # pass every pixel, the one back to vertex 0 closes the polygon
    qx = (np.round(px * (1 << SUB)) / (1 << SUB)).astype(np.float32)  # the raster's 1/16 px grid
    qy = (np.round(py * (1 << SUB)) / (1 << SUB)).astype(np.float32)
    dx, dy = np.roll(qx, -1, 1) - qx, np.roll(qy, -1, 1) - qy
    orient = np.sign(np.sum(qx * np.roll(qy, -1, 1) - np.roll(qx, -1, 1) * qy, 1))[:, None]
    dx, dy = dx * orient, dy * orient
    margin = EDGE_MARGIN_PX * np.hypot(dx, dy)
    inside = valid
    for k in range(qx.shape[1]):
        e = (Y - qy[:, k, None, None]) * dx[:, k, None, None] - (X - qx[:, k, None, None]) * dy[:, k, None, None]
        inside = inside & (e >= -margin[:, k, None, None])  # e > 0: the polygon's side of edge k
    iz = C[:, 0, None, None] * X + C[:, 1, None, None] * Y + C[:, 2, None, None]
    iz = np.clip(iz, lo[:, None, None], hi[:, None, None])
    Xi, Yi = np.broadcast_to(X, inside.shape).astype(np.int32), np.broadcast_to(Y, inside.shape).astype(np.int32)
    pix = (Yi * W + Xi)[inside]
    iz = iz[inside]
    face = np.broadcast_to(f[:, None, None], inside.shape)[inside]
    nearer = iz > invz.ravel()[pix]
    pix, iz, face = pix[nearer], iz[nearer], face[nearer]
    if len(pix) == 0:
        return
    order = np.lexsort((face, -iz, pix))
    pix, iz, face = pix[order], iz[order], face[order]
    first = np.r_[True, pix[1:] != pix[:-1]]
    invz.ravel()[pix[first]] = iz[first]
    ids.ravel()[pix[first]] = face[first]


def texture_tables(cam: Camera, atlas: Atlas, V: np.ndarray, rows_cam: np.ndarray, C: np.ndarray) -> np.ndarray:
    """(11, F) float32, per face: A/w (3), B/h (3) in tile units, tile x0 − 2·ATLAS_W, y0, w, h, mip constant."""
    F = len(rows_cam)
    tile = rows_cam[:, R_TILE : R_TILE + 4]
    O = rows_cam[:, R_O : R_O + 3]
    K = np.array([[1 / cam.fx, 0, -cam.cx / cam.fx], [0, 1 / cam.fy, -cam.cy / cam.fy], [0, 0, 1]])
    HM = np.zeros((F, 3, 3))
    for k, col in enumerate((R_U, R_V)):
        Uc = rows_cam[:, col : col + 3]
        g = Uc @ K  # s·(1/z) = (g·p) − (Uc·O)·(C·p), texels
        HM[:, k] = g - np.einsum("ij,ij->i", Uc, O)[:, None] * C
    HM[:, 2] = C
    det = np.abs(np.einsum("fi,fi->f", HM[:, 0], np.cross(HM[:, 1], HM[:, 2])))  # 3×3 determinants (triple product)
    tab = np.zeros((F, 11))
    tab[:, 0:3] = HM[:, 0] / tile[:, 2:3]
    tab[:, 3:6] = HM[:, 1] / tile[:, 3:4]
    # shift each face's tile coordinates by whole repeats so they stay small on the face
    # (float32 precision far from the map origin); the wrap makes this invisible
    for k, col, size in ((0, R_U, tile[:, 2]), (3, R_V, tile[:, 3])):
        at_vertex = np.einsum("ij,ij->i", rows_cam[:, col : col + 3], V[:, 0] - O) / size
        tab[:, k : k + 3] -= np.floor(at_vertex)[:, None] * C
    tab[:, 6] = tile[:, 0] - 2 * atlas.levels[0].shape[1]
    tab[:, 7:10] = tile[:, 1:4]
    tab[:, 10] = 0.5 * np.log2(np.maximum(det, 1e-30)) + MIP_BIAS
    return np.ascontiguousarray(tab.T.astype(np.float32))


def shade(cam: Camera, atlas: Atlas, ids: np.ndarray, invz: np.ndarray, tab: np.ndarray, light: np.ndarray,
          sky: np.ndarray, strip: int = STRIP) -> np.ndarray:
    """RGB float32 image: atlas texel (0–255) × ``light`` (F, 3) per face; ``sky`` fills sky pixels.
    Runs in bands of ``strip`` rows so every per-pixel temporary stays in the core's cache."""
    if tab.shape[1] > 32767:
        raise ValueError(f"{tab.shape[1]} faces: the per-face lookups take at most 32767")
    out = np.empty((cam.h, cam.w, 3), np.float32)
    # per-face tables as 1-row images: a nearest-neighbour remap gathers 3–4 values per pixel
    # in one pass (several times cheaper than np.take per value); sky (−1) reads the zero border
    tables = [np.ascontiguousarray(tab[k : k + 4].T[None]) for k in (0, 4, 8)]
    tables.append(np.ascontiguousarray(light[None], dtype=np.float32))
    idmap = np.zeros((strip, cam.w, 2), np.int16)
    for y0 in range(0, cam.h, strip):
        y1 = min(cam.h, y0 + strip)
        m = idmap[: y1 - y0]
        m[..., 0] = ids[y0:y1]
        g = [cv2.remap(tb, m, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) for tb in tables]
        _shade_band(cam, atlas, ids[y0:y1], invz[y0:y1], cam.v[y0:y1, None], g, sky[y0:y1], out[y0:y1])
    return out


def _shade_band(cam, atlas, ids, invz, vv, g, sky, out) -> None:
    a0, a1, a2, b0, b1, b2, x0, y0, tw, th, kf = (g[k // 4][..., k % 4] for k in range(11))
    z = np.reciprocal(invz)
    uu = cam.u[None, :]
    s = a0 * uu
    s += a1 * vv
    s += a2
    s *= z
    t = b0 * uu
    t += b1 * vv
    t += b2
    t *= z
    s -= np.floor(s)
    t -= np.floor(t)
    s *= tw
    s += x0  # texel x relative to 2·ATLAS_W (folds the packed-level offset in)
    t *= th
    t += y0
    # mip level from the texel area per pixel: 0.5·log2|det H| + 1.5·log2 z
    lev = np.log2(z)
    lev *= 1.5
    lev += kf
    np.maximum(lev, 0, out=lev)
    np.minimum(lev, NLEV - 1 - 1e-3, out=lev)
    base = lev.astype(np.int32)
    frac = np.subtract(lev, base, dtype=np.float32)
    # level L of the packed atlas starts at x = 2·W·(1 − 2^−L): x_L = (x − 2W)·2^−L + 2W
    W2 = 2.0 * atlas.levels[0].shape[1]
    np.negative(base, out=base)
    xa = np.ldexp(s, base)
    xa += W2 - 0.5
    ya = np.ldexp(t, base)
    ya -= 0.5
    a = cv2.remap(atlas.packed, xa, ya, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # level L+1 from level L's sample coordinates: x_{L+1} = x_L/2 + W − 1/4, y_{L+1} = y_L/2 − 1/4
    xa *= 0.5
    xa += 0.5 * W2 - 0.25
    ya *= 0.5
    ya -= 0.25
    b = cv2.remap(atlas.packed, xa, ya, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    d = cv2.blendLinear(a.astype(np.float32), b.astype(np.float32), 1 - frac, frac)  # trilinear: across levels
    np.multiply(d, g[3], out=out)
    skym = ids < 0
    if skym.any():
        cv2.copyTo(sky, skym.view(np.uint8), out)
