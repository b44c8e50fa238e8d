"""Faces: planar convex polygons with a texture frame, the synthetic world's only primitive.

``FaceList`` accumulates them (and builds boxes, frusta, prisms, tubes and convex hulls out of
them); ``arrays()`` packs them as (F, MAXV, 3) vertices and (F, 23) rows for the renderer.
"""

from __future__ import annotations

import numpy as np

from mining.sources.synthetic.textures import Atlas, Tile

MAXV = 8  # vertices per face (padded)
DOWN = np.array([0.0, 1.0, 0.0])


class FaceList:
    """Accumulates faces; ``arrays()`` packs them for the renderer."""

    def __init__(self, atlas: Atlas, material: str | None = None):
        """``material``: every face takes this material instead of its own (a textureless object)."""
        self.atlas = atlas
        self.material = material
        self.verts: list[np.ndarray] = []
        self.rows: list[np.ndarray | None] = []  # per face: normal(3) O(3) U(3) V(3) tile(4) tint(3) obj skey part nv
        self._pending: list[tuple] = []  # polygons whose rows ``_finish`` computes (None in rows until then)

    def add(self, pts, normal, origin, u_dir, v_dir, material: str, tint=(1, 1, 1), obj: int = 0,
            skey: float = 0.0, part: int = 0, offset=(0.0, 0.0), extent=None, own: bool = False) -> None:
        """One face. ``u_dir``/``v_dir`` are unit texture axes; ``extent`` (u, v metres) stretches a
        stretch material over the face, else the material's texels-per-metre apply. ``own``: keep
        this face's material even when the list overrides materials (a shadow stays a shadow)."""
        tile: Tile = self.atlas.tiles[material if own or not self.material else self.material]
        if tile.metres_w == 0:
            ext = extent if extent is not None else (1.0, 1.0)
            du, dv = tile.w / max(ext[0], 1e-3), tile.h / max(ext[1], 1e-3)
        else:
            du, dv = tile.w / tile.metres_w, tile.h / tile.metres_h
        p = np.asarray(pts, float)
        pad = np.repeat(p[-1:], MAXV - len(p), axis=0)
        self.verts.append(np.concatenate([p, pad]))
        o = np.asarray(origin, float) - offset[0] * np.asarray(u_dir) - offset[1] * np.asarray(v_dir)
        row = np.concatenate([normal, o, np.asarray(u_dir) * du, np.asarray(v_dir) * dv,
                              [tile.x0, tile.y0, tile.w, tile.h], tint, [obj, skey, part, len(p)]])
        self.rows.append(row)

    def quad(self, p0, p1, p3, normal, material, tint=(1, 1, 1), obj=0, skey=0.0, part=0, offset=(0.0, 0.0)):
        """Parallelogram with corner ``p0``, u edge to ``p1``, v edge to ``p3``."""
        p0, p1, p3 = (np.asarray(x, float) for x in (p0, p1, p3))
        eu, ev = p1 - p0, p3 - p0
        lu, lv = np.linalg.norm(eu), np.linalg.norm(ev)
        self.add([p0, p1, p1 + ev, p3], normal, p0, eu / lu, ev / lv, material, tint, obj, skey, part, offset, (lu, lv))

    def box(self, center, half, R, mats: dict[str, str], tint=(1, 1, 1), obj=0, skey=0.0, part=0,
            offset=(0.0, 0.0), skip=("bottom",)):
        """Axis-aligned (in R's frame) box; ``mats`` maps side/front/rear/top/bottom to materials."""
        c = np.asarray(center, float)
        ax, ay, az = (R[:, i] * half[i] for i in range(3))
        ex, ey, ez = R[:, 0], R[:, 1], R[:, 2]
        faces = {
            "right": (c + ax - ay + az, c + ax - ay - az, c + ax + ay + az, ex),
            "left": (c - ax - ay - az, c - ax - ay + az, c - ax + ay - az, -ex),
            "front": (c - ax - ay + az, c + ax - ay + az, c - ax + ay + az, ez),
            "rear": (c + ax - ay - az, c - ax - ay - az, c + ax + ay - az, -ez),
            "top": (c - ax - ay - az, c + ax - ay - az, c - ax - ay + az, -ey),
            "bottom": (c - ax + ay + az, c + ax + ay + az, c - ax + ay - az, ey),
        }
        for name, (p0, p1, p3, n) in faces.items():
            if name in skip:
                continue
            key = "side" if name in ("right", "left") else name
            self.quad(p0, p1, p3, n, mats.get(key, mats.get("all")), tint, obj, skey, part, offset)

    def convex(self, points, material, tint=(1, 1, 1), obj=0, part=0, offset=(0.0, 0.0)):
        """Faces of the convex hull of ``points`` (rocks, blobs), outward normals."""
        from scipy.spatial import ConvexHull

        pts = np.asarray(points, float)
        hull = ConvexHull(pts)
        centre = pts.mean(0)
        for simplex, eq in zip(hull.simplices, hull.equations):
            tri = pts[simplex]
            n = eq[:3]
            if np.dot(tri.mean(0) - centre, n) < 0:
                n = -n
            u = tri[1] - tri[0]
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            self.add(tri, n, tri[0], u, v, material, tint, obj, 0.0, part, offset)

    def poly(self, pts, outward, material: str, tint=(1, 1, 1), obj: int = 0, part: int = 0, u_hint=None,
             own: bool = False, offset=(0.0, 0.0)) -> None:
        """A planar convex polygon whose normal points to the side of ``outward``. The texture's u
        axis follows ``u_hint`` (projected on the plane; default: the first edge), v points down
        the face where it can; a stretch material spans the polygon's bounding rectangle.
        (Computed for all polygons at once in ``arrays()``: meshes have hundreds.)"""
        p = np.asarray(pts, float)
        if len(p) > MAXV:  # in fan pieces of at most MAXV vertices, one texture frame over all
            q = np.roll(p, -1, 0)
            d, e = p - q, p + q
            n = np.array([d[:, 1] @ e[:, 2], d[:, 2] @ e[:, 0], d[:, 0] @ e[:, 1]])
            n /= np.linalg.norm(n)
            n = -n if n @ np.asarray(outward, float) < 0 else n
            u = np.asarray(u_hint, float) if u_hint is not None else p[1] - p[0]
            u = u - (u @ n) * n
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            v = -v if v[1] < -1e-9 else v
            ss, tt = (p - p[0]) @ u, (p - p[0]) @ v
            origin = p[0] + ss.min() * u + tt.min() * v
            ext = (max(ss.max() - ss.min(), 1e-3), max(tt.max() - tt.min(), 1e-3))
            for i in range(1, len(p) - 1, MAXV - 2):
                piece = p[np.r_[0, i : min(i + MAXV - 1, len(p))]]
                self.add(piece, n, origin, u, v, material, tint, obj, 0.0, part, offset, ext, own)
            return
        self.verts.append(np.concatenate([p, np.repeat(p[-1:], MAXV - len(p), axis=0)]) if len(p) < MAXV else p)
        self.rows.append(None)
        tile: Tile = self.atlas.tiles[material if own or not self.material else self.material]
        self._pending.append((len(self.rows) - 1, outward, u_hint, tile, tint, obj, part, len(p), offset))

    def _finish(self) -> None:
        """The pending polygons' rows: Newell normals, texture frames and extents, vectorised."""
        if not self._pending:
            return
        idx = np.array([x[0] for x in self._pending])
        P = np.array([self.verts[i] for i in idx])  # (n, MAXV, 3); padding repeats the last vertex
        Q = np.roll(P, -1, 1)
        d, e = P - Q, P + Q
        n = np.stack([np.einsum("ij,ij->i", d[..., 1], e[..., 2]), np.einsum("ij,ij->i", d[..., 2], e[..., 0]),
                      np.einsum("ij,ij->i", d[..., 0], e[..., 1])], 1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        out = np.array([x[1] for x in self._pending], float)
        n *= np.where(np.einsum("ij,ij->i", n, out) < 0, -1.0, 1.0)[:, None]
        hint = np.array([x[2] if x[2] is not None else (np.nan, np.nan, np.nan) for x in self._pending], float)
        edge = P[:, 1] - P[:, 0]
        u = np.where(np.isnan(hint), edge, hint)
        u -= np.einsum("ij,ij->i", u, n)[:, None] * n
        bad = np.einsum("ij,ij->i", u, u) < 1e-18
        u[bad] = edge[bad] - np.einsum("ij,ij->i", edge[bad], n[bad])[:, None] * n[bad]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v = np.cross(n, u)
        v *= np.where(v[:, 1] < -1e-9, -1.0, 1.0)[:, None]  # v along DOWN where the face allows
        rel = P - P[:, :1]
        s, t = np.einsum("fkj,fj->fk", rel, u), np.einsum("fkj,fj->fk", rel, v)
        origin = P[:, 0] + s.min(1)[:, None] * u + t.min(1)[:, None] * v
        ext = np.maximum(np.stack([s.max(1) - s.min(1), t.max(1) - t.min(1)], 1), 1e-3)
        tiles = [x[3] for x in self._pending]
        tw = np.array([[tl.w, tl.h] for tl in tiles], float)
        metres = np.array([[tl.metres_w, tl.metres_h] for tl in tiles], float)
        scale = np.where(metres[:, :1] == 0, tw / ext, tw / np.where(metres == 0, 1.0, metres))
        off = np.array([x[8] for x in self._pending], float)
        o = origin - off[:, :1] * u - off[:, 1:] * v
        rows = np.concatenate([n, o, u * scale[:, :1], v * scale[:, 1:], [[tl.x0, tl.y0, tl.w, tl.h] for tl in tiles],
                               np.array([x[4] for x in self._pending], float),
                               np.array([[x[5], 0.0, x[6], x[7]] for x in self._pending], float)], 1)
        for k, i in enumerate(idx):
            self.rows[i] = rows[k]
        self._pending = []

    def frustum(self, bottom, top, half_bottom, half_top, R, material: str, tint=(1, 1, 1), obj: int = 0,
                part: int = 0, caps: tuple[bool, bool] = (False, True), mats: dict | None = None, tints: dict | None = None):
        """A box tapered between two rectangles (centres ``bottom``/``top``, half sizes (x, z) in R's
        frame, the axis along R's y): four trapezoids (planar: each is symmetric) and the caps
        asked for (bottom, top). ``mats``/``tints`` per side (front/rear/left/right/top/bottom)."""
        mats, tints = mats or {}, tints or {}
        b, t = np.asarray(bottom, float), np.asarray(top, float)
        ex, ez = R[:, 0], R[:, 2]

        def ring(c, hx, hz):
            return [c - hx * ex - hz * ez, c + hx * ex - hz * ez, c + hx * ex + hz * ez, c - hx * ex + hz * ez]

        rb, rt = ring(b, *half_bottom), ring(t, *half_top)
        mid = (b + t) / 2
        for i, name in enumerate(("rear", "right", "front", "left")):
            j = (i + 1) % 4
            quad = [rb[i], rb[j], rt[j], rt[i]]
            out = np.mean(quad, 0) - mid
            self.poly(quad, out, mats.get(name, material), tints.get(name, tint), obj, part,
                      u_hint=rb[j] - rb[i])
        if caps[0]:
            self.poly(rb, b - t, mats.get("bottom", material), tints.get("bottom", tint), obj, part, u_hint=ex)
        if caps[1]:
            self.poly(rt, t - b, mats.get("top", material), tints.get("top", tint), obj, part, u_hint=ex)

    def prism(self, ring, axis, material: str, tint=(1, 1, 1), obj: int = 0, part: int = 0,
              caps: tuple[bool, bool] = (True, True), cap_material: str | None = None, cap_tint=None,
              skip=None) -> None:
        """A convex polygon ``ring`` (≤ MAXV points) extruded by the vector ``axis``: side quads
        (``skip(i)`` True leaves side i out) and the two caps."""
        r0 = np.asarray(ring, float)
        r1 = r0 + np.asarray(axis, float)
        c = (r0.mean(0) + r1.mean(0)) / 2
        for i in range(len(r0)):
            if skip is not None and skip(i):
                continue
            j = (i + 1) % len(r0)
            quad = [r0[i], r0[j], r1[j], r1[i]]
            self.poly(quad, np.mean(quad, 0) - c, material, tint, obj, part, u_hint=r0[j] - r0[i])
        cm, ct = cap_material or material, tint if cap_tint is None else cap_tint
        if caps[0]:
            self.poly(r0, -np.asarray(axis, float), cm, ct, obj, part)
        if caps[1]:
            self.poly(r1, np.asarray(axis, float), cm, ct, obj, part)

    def tube(self, a, b, half_w: float, material: str, tint=(1, 1, 1), obj: int = 0, part: int = 0,
             across=None, half_d: float | None = None) -> None:
        """A thin four-sided bar from ``a`` to ``b`` (frame tubes, handles, branches); ``across`` is
        the direction of its width (default: x, or z for a bar along x)."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        ax = b - a
        L = np.linalg.norm(ax)
        if L < 1e-6:
            return
        ax /= L
        e1 = np.asarray(across, float) if across is not None else (np.array([1.0, 0, 0]) if abs(ax[0]) < 0.9 else np.array([0, 0, 1.0]))
        e1 = e1 - (e1 @ ax) * ax
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(ax, e1)
        hd = half_w if half_d is None else half_d
        ring = [a - half_w * e1 - hd * e2, a + half_w * e1 - hd * e2, a + half_w * e1 + hd * e2, a - half_w * e1 + hd * e2]
        self.prism(ring, b - a, material, tint, obj, part, caps=(False, False))

    def extend(self, verts: np.ndarray, rows: np.ndarray) -> None:
        """Faces already packed (another list's ``arrays()``, moved)."""
        self.verts.extend(verts)
        self.rows.extend(rows)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        self._finish()
        if not self.verts:
            return np.zeros((0, MAXV, 3)), np.zeros((0, 23))
        return np.array(self.verts), np.array(self.rows)


# row layout of FaceList.rows
R_N, R_O, R_U, R_V, R_TILE, R_TINT, R_OBJ, R_SKEY, R_PART, R_NV = 0, 3, 6, 9, 12, 16, 19, 20, 21, 22


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
