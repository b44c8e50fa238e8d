"""Z-buffer rasteriser of textured planar faces for a rectified pinhole camera.

Per face: clip against the near plane, project, fill its mask in its bounding rectangle
(cv2.fillConvexPoly), evaluate the exact inverse depth (affine in u, v for a plane), z-test,
write the face id. Then per pixel: texture coordinates from the ray–plane intersection
(again affine over depth), mip level from the texel footprint, bilinear atlas lookup, and
Lambert shading against the sun.
"""

from __future__ import annotations

import cv2
import numpy as np

from mining.sources.synthetic.scene import MAXV, R_N, R_NV, R_O, R_TILE, R_TINT, R_U, R_V
from mining.sources.synthetic.textures import NLEV, Atlas

NEAR_M = 0.3  # ours: near clipping plane
FAR_M = 400.0  # ours: faces entirely beyond are dropped
SUB = 4  # fillConvexPoly fixed-point bits (1/16 px vertices)


class Camera:
    def __init__(self, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
        self.fx, self.fy, self.cx, self.cy, self.w, self.h = fx, fy, cx, cy, width, height
        self.u = np.arange(width, dtype=np.float32)
        self.v = np.arange(height, dtype=np.float32)


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


def rasterize(cam: Camera, verts: np.ndarray, rows: np.ndarray, R: np.ndarray, t: np.ndarray):
    """Faces in map frame, camera from map ``Pc = R Pm + t`` → (face id (H,W) int32, -1 = sky;
    inverse depth (H,W) float32; per-face camera-frame rows)."""
    H, W = cam.h, cam.w
    V = verts @ R.T + t
    n = rows[:, R_N : R_N + 3] @ R.T
    dp = np.einsum("ij,ij->i", n, V[:, 0])
    z = V[:, :, 2]
    keep = (dp < -1e-6) & (z.max(1) > NEAR_M) & (z.min(1) < FAR_M)
    zc = np.maximum(z, NEAR_M)
    px = cam.fx * V[:, :, 0] / zc + cam.cx
    py = cam.fy * V[:, :, 1] / zc + cam.cy
    allin = z.min(1) >= NEAR_M
    keep &= ~(allin & ((px.max(1) < -1) | (px.min(1) > W) | (py.max(1) < -1) | (py.min(1) > H)))
    ids = np.full((H, W), -1, np.int32)
    invz = np.zeros((H, W), np.float32)
    # inverse depth plane: 1/z = (n·r)/dp with r = ((u-cx)/fx, (v-cy)/fy, 1)
    ia = (n[:, 0] / cam.fx / dp).astype(np.float32)
    ib = (n[:, 1] / cam.fy / dp).astype(np.float32)
    ic = ((n[:, 2] - n[:, 0] * cam.cx / cam.fx - n[:, 1] * cam.cy / cam.fy) / dp).astype(np.float32)
    # inverse depth range of each face's (unclipped) vertices: raster edge pixels just outside
    # an oblique face must not extrapolate its plane to a wrong depth
    izv = 1.0 / np.maximum(zc, NEAR_M)
    iz_lo, iz_hi = (izv.min(1) * 0.999).astype(np.float32), (izv.max(1) * 1.001).astype(np.float32)
    bx0 = np.floor(px.min(1)).clip(0, W).astype(int)
    by0 = np.floor(py.min(1)).clip(0, H).astype(int)
    bx1 = (np.ceil(px.max(1)) + 1).clip(0, W).astype(int)
    by1 = (np.ceil(py.max(1)) + 1).clip(0, H).astype(int)
    pq = np.round(np.stack([px, py], 2).clip(-1e5, 1e5) * (1 << SUB)).astype(np.int32)
    nvs = rows[:, R_NV].astype(int)
    for f in np.nonzero(keep)[0].tolist():
        nv = nvs[f]
        if allin[f]:
            x0, y0, x1, y1 = bx0[f], by0[f], bx1[f], by1[f]
            if x1 <= x0 or y1 <= y0:
                continue
            q = pq[f, :nv] - ((x0 << SUB), (y0 << SUB))
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
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, q, 1, lineType=cv2.LINE_8, shift=SUB)
        iz = (ia[f] * cam.u[x0:x1])[None, :] + (ib[f] * cam.v[y0:y1] + ic[f])[:, None]
        np.clip(iz, iz_lo[f], iz_hi[f], out=iz)
        zr = invz[y0:y1, x0:x1]
        win = iz > zr
        win &= mask.view(bool)
        np.copyto(zr, iz, where=win)
        np.copyto(ids[y0:y1, x0:x1], f, where=win)
    return ids, invz, V, n


def shade(cam: Camera, atlas: Atlas, ids: np.ndarray, invz: np.ndarray, rows: np.ndarray, Vc: np.ndarray,
          R: np.ndarray, t: np.ndarray, light: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """RGB float32 image in [0, 1]-ish of the rasterised faces; ``light`` (F,3) per-face colour gain."""
    H, W = cam.h, cam.w
    F = len(rows)
    # per-face texture-coordinate planes in camera frame: s = z·(a u + b v + c) + d
    O = rows[:, R_O : R_O + 3] @ R.T + t
    coef = np.zeros((F + 1, 12), np.float32)
    for k, col in enumerate((R_U, R_V)):
        Uc = rows[:, col : col + 3] @ R.T
        coef[:F, 4 * k + 0] = Uc[:, 0] / cam.fx
        coef[:F, 4 * k + 1] = Uc[:, 1] / cam.fy
        coef[:F, 4 * k + 2] = Uc[:, 2] - Uc[:, 0] * cam.cx / cam.fx - Uc[:, 1] * cam.cy / cam.fy
        coef[:F, 4 * k + 3] = -np.einsum("ij,ij->i", Uc, O)
    coef[:F, 8:12] = rows[:, R_TILE : R_TILE + 4]
    coef[F, 10:12] = 1
    idx = np.where(ids < 0, F, ids)
    valid = ids >= 0
    cT = np.ascontiguousarray(coef.T)
    g = [np.take(cT[k], idx) for k in range(12)]
    z = np.where(valid, 1.0 / np.maximum(invz, 1e-9), 0).astype(np.float32)
    uu, vv = cam.u[None, :], cam.v[:, None]
    S = (g[0] * uu + g[1] * vv + g[2]) * z + g[3]
    T = (g[4] * uu + g[5] * vv + g[6]) * z + g[7]
    # texel footprint per pixel (min of forward/backward differences, so face borders stay sharp)
    # geometric mean of the u and v footprints: a compromise for surfaces seen at grazing
    # angles (the road), sharp across, slightly aliased along the viewing direction
    fp = _footprint(S, T, 1) * _footprint(S, T, 0)
    lev = np.clip(0.5 * np.log2(np.maximum(fp, 1e-12)) - 0.2, 0, NLEV - 1 - 1e-3)
    tx = g[8] + (S - np.floor(S / g[10]) * g[10])
    ty = g[9] + (T - np.floor(T / g[11]) * g[11])
    # trilinear mip lookup in the packed atlas: two bilinear remaps (levels ⌊lev⌋ and ⌊lev⌋+1)
    base = np.floor(lev)
    frac = lev - base
    scale = np.exp2(-base)
    off = (2 * atlas.levels[0].shape[1]) * (1 - scale)
    ax, ay = tx * scale, ty * scale
    a = cv2.remap(atlas.packed, off + ax - 0.5, ay - 0.5, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    scale *= 0.5
    off = (2 * atlas.levels[0].shape[1]) * (1 - scale)
    ax *= 0.5
    ay *= 0.5
    b = cv2.remap(atlas.packed, off + ax - 0.5, ay - 0.5, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = a.astype(np.float32)
    out += (b - out) * frac[..., None]
    out *= 1.0 / 255.0
    lt = np.concatenate([light, np.zeros((1, 3), np.float32)])
    for ch in range(3):
        out[..., ch] *= np.take(lt[:, ch], idx)
    out[~valid] = sky[~valid]
    return out


def _footprint(S: np.ndarray, T: np.ndarray, axis: int) -> np.ndarray:
    dS = np.abs(np.diff(S, axis=axis)) + np.abs(np.diff(T, axis=axis))
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 0)
    a = np.pad(dS, pad, mode="edge")
    pad[axis] = (0, 1)
    b = np.pad(dS, pad, mode="edge")
    return np.minimum(a, b)


