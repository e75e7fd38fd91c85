"""Exact ray casting of the synthetic street's analytic primitives, and their shading.

Geometry lives in road-aligned coordinates: ``s`` is arc length along the road centreline,
``l`` the lateral offset (positive = left), ``z`` height above the road surface. The centreline
is a circular arc of curvature ``kappa`` through the world origin with heading +x there
(a straight line along +x when ``kappa == 0``). Primitives:

- the ground: road plane ``z = 0`` for ``|l| < kerb_l``, sidewalk plane ``z = kerb_h`` beyond,
  kerb faces (constant ``l``) in between;
- road boxes ``s0<=s<=s1, l0<=l<=l1, z0<=z<=z1`` (buildings, cars): their faces are horizontal
  planes, radial planes (constant ``s``) and vertical cylinders about the arc centre (constant
  ``l``; planes when straight), each intersected in closed form;
- vertical cylinders (poles, trunks) and spheres (tree crowns) in world coordinates.

A ray is ``o + t * d`` with one origin per call and any number of directions. Camera rays use
``d`` with a unit camera-z component, so the returned ``t`` is the z-depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEAR = 1e-4
_TINY = 1e-30

# hit kinds
SKY, GROUND, BOX, CYLINDER, SPHERE = 0, 1, 2, 3, 4
# ground parts (stored as the hit's index)
ROAD, KERB, SIDEWALK = 0, 1, 2
# box faces: bottom, top, lower-l, upper-l, lower-s, upper-s
Z0, Z1, L0, L1, S0, S1 = 0, 1, 2, 3, 4, 5
# cylinder faces
SIDE, TOP, BOTTOM = 0, 1, 2


class RoadArc:
    """Road-aligned coordinates on a circular centreline of curvature ``kappa`` (1/m, left > 0)."""

    def __init__(self, curvature: float):
        k = float(curvature)
        self.kappa = 0.0 if abs(k) < 1e-9 else k
        self.radius = np.inf if self.kappa == 0.0 else 1.0 / self.kappa

    def heading(self, s):
        """Heading (rad, about +z) of the centreline at arc length ``s``."""
        return self.kappa * np.asarray(s, dtype=np.float64)

    def tangent(self, s):
        th = self.heading(s)
        return np.cos(th), np.sin(th)

    def normal(self, s):
        """Unit left normal (x, y) at ``s``."""
        th = self.heading(s)
        return -np.sin(th), np.cos(th)

    def to_world(self, s, l):
        """Road (s, l) -> world (x, y); broadcasts."""
        s, l = np.broadcast_arrays(np.asarray(s, np.float64), np.asarray(l, np.float64))
        if self.kappa == 0.0:
            return s.copy(), l.copy()
        th = self.kappa * s
        rl = self.radius - l
        return np.sin(th) * rl, self.radius - np.cos(th) * rl

    def to_road(self, x, y):
        """World (x, y) -> road (s, l); valid for |kappa * s| < pi."""
        if self.kappa == 0.0:
            return np.asarray(x, np.float64), np.asarray(y, np.float64)
        r0 = self.radius
        sg = np.sign(r0)
        vy = y - r0
        l = r0 - sg * np.hypot(x, vy)
        s = np.arctan2(sg * x, -sg * vy) / self.kappa
        return s, l


@dataclass
class Primitives:
    """Everything a ray can hit. Box and cylinder/sphere fields are (n,) float64 arrays."""

    arc: RoadArc
    kerb_l: float
    kerb_h: float
    boxes: np.ndarray      # (nb, 6): s0, s1, l0, l1, z0, z1
    cylinders: np.ndarray  # (nc, 5): cx, cy, r, z0, z1 (world)
    spheres: np.ndarray    # (ns, 4): cx, cy, cz, r (world)

    def bound_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points whose convex hull holds each primitive.

        Returns (kinds (n,), indices (n,), points (n, 16, 3)) over boxes, cylinders, spheres.
        """
        parts = []
        kinds, idx = [], []
        if len(self.boxes):
            parts.append(box_hull_points(self.arc, self.boxes))
            kinds.append(np.full(len(self.boxes), BOX))
            idx.append(np.arange(len(self.boxes)))
        if len(self.cylinders):
            c = self.cylinders
            lo = np.stack([c[:, 0] - c[:, 2], c[:, 1] - c[:, 2], c[:, 3]], -1)
            hi = np.stack([c[:, 0] + c[:, 2], c[:, 1] + c[:, 2], c[:, 4]], -1)
            parts.append(_aabb_points(lo, hi))
            kinds.append(np.full(len(c), CYLINDER))
            idx.append(np.arange(len(c)))
        if len(self.spheres):
            sp = self.spheres
            parts.append(_aabb_points(sp[:, :3] - sp[:, 3:4], sp[:, :3] + sp[:, 3:4]))
            kinds.append(np.full(len(sp), SPHERE))
            idx.append(np.arange(len(sp)))
        if not parts:
            return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 16, 3))
        return np.concatenate(kinds), np.concatenate(idx), np.concatenate(parts)


def _aabb_points(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n,3),(n,3) -> (n,16,3): the 8 corners, each twice (so every hull set has 16 points)."""
    sel = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
    pts = np.where(sel[None], hi[:, None, :], lo[:, None, :])
    return np.concatenate([pts, pts], axis=1)


def box_hull_points(arc: RoadArc, boxes: np.ndarray) -> np.ndarray:
    """(nb,6) road boxes -> (nb,16,3): 4 stations along s x 2 laterals x 2 heights.

    Between stations the outer arc bulges past the chord by at most the sagitta; pushing the
    laterals outward by it keeps the hull conservative.
    """
    s0, s1, l0, l1, z0, z1 = boxes.T
    f = np.linspace(0.0, 1.0, 4)
    ss = s0[:, None] + (s1 - s0)[:, None] * f[None]  # (nb,4)
    if arc.kappa != 0.0:
        half = 0.5 * abs(arc.kappa) * (s1 - s0) / 3.0
        rho = np.maximum(abs(arc.radius - l0), abs(arc.radius - l1))
        sag = rho * (1.0 - np.cos(half)) + 1e-6
    else:
        sag = np.zeros_like(s0)
    ls = np.stack([l0 - sag, l1 + sag], -1)  # (nb,2)
    x, y = arc.to_world(ss[:, :, None], ls[:, None, :])  # (nb,4,2)
    x = np.repeat(x.reshape(len(boxes), 8, 1), 2, axis=2).reshape(len(boxes), 16)
    y = np.repeat(y.reshape(len(boxes), 8, 1), 2, axis=2).reshape(len(boxes), 16)
    z = np.tile(np.stack([z0, z1], -1), (1, 8))
    return np.stack([x, y, z], -1)


# ---------------------------------------------------------------------------------------------
# closed-form intersections: each takes origin o (3,) and direction arrays dx, dy, dz of any
# common shape and returns t (inf where missed) and a face/part code, same shape.


def _circle_roots(qx: float, qy: float, rho: float, dx, dy):
    """Roots t_lo <= t_hi of |q + t d|_xy = rho (q: origin minus circle centre), hit mask."""
    a = np.maximum(dx * dx + dy * dy, _TINY)
    b = qx * dx + qy * dy
    qn = float(np.hypot(qx, qy))
    c = (qn - rho) * (qn + rho)
    disc = b * b - a * c
    hit = disc >= 0.0
    sq = np.sqrt(np.maximum(disc, 0.0))
    # stable pair of roots: no cancellation between -b and sqrt(disc)
    tmp = -(b + np.copysign(sq, b))
    tmp = np.where(tmp == 0.0, -_TINY, tmp)
    r1 = tmp / a
    r2 = c / tmp
    return np.minimum(r1, r2), np.maximum(r1, r2), hit


def _l_surface_roots(arc: RoadArc, lat: float, o, dx, dy):
    """Up to two ray parameters where the ray meets the vertical surface l = lat (inf if none)."""
    if arc.kappa == 0.0:
        dys = np.where(dy == 0.0, _TINY, dy)
        t = (lat - o[1]) / dys
        return t, np.full_like(t, np.inf)
    lo, hi, hit = _circle_roots(o[0], o[1] - arc.radius, abs(arc.radius - lat), dx, dy)
    return np.where(hit, lo, np.inf), np.where(hit, hi, np.inf)


def hit_ground(arc: RoadArc, kerb_l: float, kerb_h: float, o, dx, dy, dz):
    """Road plane, sidewalk plane and the two kerb faces. Returns (t, part)."""
    t = np.full(dx.shape, np.inf)
    part = np.zeros(dx.shape, np.int8)
    down = dz < 0.0
    dzn = np.where(down, dz, -1.0)
    for height, inside_road, code in ((0.0, True, ROAD), (kerb_h, False, SIDEWALK)):
        if o[2] <= height:
            continue
        tp = (height - o[2]) / dzn  # finite; rays going up are masked below
        if arc.kappa == 0.0:
            lat = o[1] + tp * dy
        else:
            _, lat = arc.to_road(o[0] + tp * dx, o[1] + tp * dy)
        on = np.abs(lat) < kerb_l if inside_road else np.abs(lat) >= kerb_l
        better = down & on & (tp < t)
        t = np.where(better, tp, t)
        part[better] = code
    for lat in (kerb_l, -kerb_l):
        roots = _l_surface_roots(arc, lat, o, dx, dy)
        for tk in roots[:1] if arc.kappa == 0.0 else roots:
            zk = o[2] + tk * dz
            better = (tk > NEAR) & (zk >= 0.0) & (zk <= kerb_h) & (tk < t)
            t = np.where(better, tk, t)
            part[better] = KERB
    return t, part


def _hit_aabb(box, o, inv):
    """Straight road: boxes are axis-aligned (s = x, l = y). inv: reciprocal directions.

    Returns (t, face) where face is a function of a mask over the rays (computed only for the
    rays where the box turns out nearest).
    """
    s0, s1, l0, l1, z0, z1 = (float(v) for v in box)
    enters, t_in, t_out = [], None, None
    for lo, hi, oi, iv in ((s0, s1, o[0], inv[0]), (l0, l1, o[1], inv[1]), (z0, z1, o[2], inv[2])):
        ta = (lo - oi) * iv
        tb = (hi - oi) * iv
        enter = np.minimum(ta, tb)
        leave = np.maximum(ta, tb)
        enters.append(enter)
        t_in = enter if t_in is None else np.maximum(t_in, enter)
        t_out = leave if t_out is None else np.minimum(t_out, leave)
    ok = (t_in <= t_out) & (t_in > NEAR)

    def face(m):
        ti = t_in[m]
        pos = [iv[m] > 0.0 for iv in inv]
        f = np.where(pos[2], Z0, Z1)
        f = np.where(ti == enters[1][m], np.where(pos[1], L0, L1), f)
        f = np.where(ti == enters[0][m], np.where(pos[0], S0, S1), f)
        return f.astype(np.int8)

    return np.where(ok, t_in, np.inf), face


def hit_box(arc: RoadArc, box, o, dx, dy, dz, inv=None):
    """First entry of the ray into one road box. Returns (t, face).

    inv: optional reciprocal directions (1/dx, 1/dy, 1/dz) with zeros replaced, for straight roads.
    """
    if arc.kappa == 0.0:
        if inv is None:
            inv = tuple(1.0 / np.where(d == 0.0, _TINY, d) for d in (dx, dy, dz))
        return _hit_aabb(box, o, inv)
    s0, s1, l0, l1, z0, z1 = (float(v) for v in box)
    dzs = np.where(dz == 0.0, _TINY, dz)
    ta = (z0 - o[2]) / dzs
    tb = (z1 - o[2]) / dzs
    t_in = np.minimum(ta, tb)
    t_out = np.maximum(ta, tb)
    face = np.where(ta < tb, Z0, Z1).astype(np.int8)
    # s bounds: half-spaces bounded by the radial planes through the arc at s0 and s1
    for sb, sign, code in ((s0, 1.0, S0), (s1, -1.0, S1)):
        tx, ty = arc.tangent(sb)
        px, py = arc.to_world(sb, 0.0)
        a = sign * (tx * (o[0] - px) + ty * (o[1] - py))
        b = sign * (tx * dx + ty * dy)
        b = np.where(b == 0.0, _TINY, b)
        ts = -a / b
        enter = b > 0.0
        m = enter & (ts > t_in)
        t_in = np.where(m, ts, t_in)
        face = np.where(m, code, face).astype(np.int8)
        t_out = np.where(enter, t_out, np.minimum(t_out, ts))
    if arc.kappa == 0.0:
        dys = np.where(dy == 0.0, _TINY, dy)
        ta = (l0 - o[1]) / dys
        tb = (l1 - o[1]) / dys
        tl = np.minimum(ta, tb)
        m = tl > t_in
        t_in = np.where(m, tl, t_in)
        face = np.where(m, np.where(ta < tb, L0, L1), face).astype(np.int8)
        t_out = np.minimum(t_out, np.maximum(ta, tb))
        ok = (t_in <= t_out) & (t_in > NEAR)
        return np.where(ok, t_in, np.inf), face
    # curved: l bounds are an annulus about the arc centre (at most two intervals on a ray)
    r0 = arc.radius
    rho0, rho1 = abs(r0 - l0), abs(r0 - l1)
    if rho0 >= rho1:
        rho_out, rho_in, f_out, f_in = rho0, rho1, L0, L1
    else:
        rho_out, rho_in, f_out, f_in = rho1, rho0, L1, L0
    qx, qy = o[0], o[1] - r0
    a1, a2, hit_a = _circle_roots(qx, qy, rho_out, dx, dy)
    b1, b2, hit_b = _circle_roots(qx, qy, rho_in, dx, dy)
    st1 = np.maximum(t_in, a1)
    end1 = np.minimum(t_out, np.where(hit_b, b1, a2))
    ok1 = hit_a & (st1 <= end1) & (st1 > NEAR)
    st2 = np.maximum(t_in, b2)
    end2 = np.minimum(t_out, a2)
    ok2 = hit_b & (st2 <= end2) & (st2 > NEAR)
    f1 = np.where(a1 > t_in, f_out, face)
    f2 = np.where(b2 > t_in, f_in, face)
    t = np.where(ok1, st1, np.where(ok2, st2, np.inf))
    return t, np.where(ok1, f1, f2).astype(np.int8)


def hit_cylinder(cyl, o, dx, dy, dz):
    """Vertical capped cylinder (cx, cy, r, z0, z1). Returns (t, face)."""
    cx, cy, r, z0, z1 = (float(v) for v in cyl)
    lo, _, hit = _circle_roots(o[0] - cx, o[1] - cy, r, dx, dy)
    zs = o[2] + lo * dz
    side = hit & (lo > NEAR) & (zs >= z0) & (zs <= z1)
    t = np.where(side, lo, np.inf)
    face = np.zeros(dx.shape, np.int8)
    for zc, code, ok_side in ((z1, TOP, o[2] > z1), (z0, BOTTOM, o[2] < z0)):
        if not ok_side:
            continue
        dzs = np.where(dz == 0.0, _TINY, dz)
        tc = (zc - o[2]) / dzs
        px = o[0] + tc * dx - cx
        py = o[1] + tc * dy - cy
        cap = (tc > NEAR) & (px * px + py * py <= r * r) & (tc < t)
        t = np.where(cap, tc, t)
        face[cap] = code
    return t, face


def hit_sphere(sph, o, dx, dy, dz):
    """Sphere (cx, cy, cz, r). Returns (t, face=0)."""
    cx, cy, cz, r = (float(v) for v in sph)
    qx, qy, qz = o[0] - cx, o[1] - cy, o[2] - cz
    a = dx * dx + dy * dy + dz * dz
    b = qx * dx + qy * dy + qz * dz
    qn = float(np.sqrt(qx * qx + qy * qy + qz * qz))
    c = (qn - r) * (qn + r)
    disc = b * b - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    tmp = -(b + np.copysign(sq, b))
    tmp = np.where(tmp == 0.0, -_TINY, tmp)
    t = np.minimum(tmp / a, c / tmp)
    ok = (disc >= 0.0) & (t > NEAR)
    return np.where(ok, t, np.inf), np.zeros(dx.shape, np.int8)


# ---------------------------------------------------------------------------------------------
# culling


def screen_rects(points: np.ndarray, w2c: np.ndarray, K: np.ndarray, width: int, height: int,
                 near: float = 1e-3):
    """Pixel rectangles that hold each hull's projection (pixel j's centre is at j + 0.5).

    points: (n, P, 3) world; w2c: (4, 4) world-to-camera (OpenCV); K: (3, 3).
    Returns (rects (n, 4) int: v0, v1, u0, u1 half-open; zmin (n,) nearest camera z; visible (n,)).
    Hulls crossing the near plane are clipped against it (all front/behind point pairs), so
    the rectangle stays conservative for objects beside the camera.
    """
    n, P, _ = points.shape
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[..., 2]
    front = z > near
    umin, umax = np.full(n, 1e7), np.full(n, -1e7)
    vmin, vmax = np.full(n, 1e7), np.full(n, -1e7)
    full = front.all(1)
    crossing = np.flatnonzero(front.any(1) & ~full)

    def extent(p, valid, rows):
        zz = np.where(valid, np.maximum(p[..., 2], near), 1.0)
        u = np.clip(K[0, 0] * p[..., 0] / zz + K[0, 1] * p[..., 1] / zz + K[0, 2], -1e7, 1e7)
        v = np.clip(K[1, 1] * p[..., 1] / zz + K[1, 2], -1e7, 1e7)
        umin[rows] = np.where(valid, u, 1e7).min(1)
        umax[rows] = np.where(valid, u, -1e7).max(1)
        vmin[rows] = np.where(valid, v, 1e7).min(1)
        vmax[rows] = np.where(valid, v, -1e7).max(1)

    rows = np.flatnonzero(full)
    extent(pc[rows], front[rows], rows)
    if len(crossing):
        pcc, zc, fc = pc[crossing], z[crossing], front[crossing]
        dzp = zc[:, None, :] - zc[:, :, None]
        alpha = (near - zc[:, :, None]) / np.where(np.abs(dzp) < 1e-12, 1e-12, dzp)
        cross = fc[:, :, None] & ~fc[:, None, :]
        clip = pcc[:, :, None, :] + alpha[..., None] * (pcc[:, None, :, :] - pcc[:, :, None, :])
        m = len(crossing)
        extent(np.concatenate([pcc, clip.reshape(m, P * P, 3)], axis=1),
               np.concatenate([fc, cross.reshape(m, P * P)], axis=1), crossing)
    zmin = np.where(full, np.where(front, z, np.inf).min(1), near)
    u0 = np.clip(np.floor(umin - 0.5) - 1, 0, width).astype(np.int64)
    u1 = np.clip(np.floor(umax - 0.5) + 2, 0, width).astype(np.int64)
    v0 = np.clip(np.floor(vmin - 0.5) - 1, 0, height).astype(np.int64)
    v1 = np.clip(np.floor(vmax - 0.5) + 2, 0, height).astype(np.int64)
    visible = front.any(1) & (u1 > u0) & (v1 > v0)
    return np.stack([v0, v1, u0, u1], -1), zmin, visible


# ---------------------------------------------------------------------------------------------
# the cast


@dataclass
class Hits:
    """Nearest hit per ray: t (inf = sky), kind (SKY/GROUND/...), index (object or ground part),
    face (per kind). All share the ray arrays' shape."""

    t: np.ndarray
    kind: np.ndarray
    index: np.ndarray
    face: np.ndarray


def _hit_object(prims: Primitives, kind: int, i: int, o, dx, dy, dz, inv):
    if kind == BOX:
        return hit_box(prims.arc, prims.boxes[i], o, dx, dy, dz, inv)
    if kind == CYLINDER:
        return hit_cylinder(prims.cylinders[i], o, dx, dy, dz)
    return hit_sphere(prims.spheres[i], o, dx, dy, dz)


def cast(prims: Primitives, o, dx, dy, dz, candidates) -> Hits:
    """Nearest hit of rays o + t (dx, dy, dz).

    candidates: iterable of (kind, index, sel, zmin): the rays object (kind, index) may hit,
    ``sel`` a tuple of slices (a view) or an integer index array into the ray arrays; ``zmin``
    a lower bound on its t (None if unknown), used to skip objects hidden behind earlier hits.
    Objects are tried in the given order; front-to-back order skips the most.
    """
    # only rays going down can meet the ground (the camera is above the sidewalk): cast the
    # rows holding any of them
    t = np.full(dx.shape, np.inf)
    part = np.zeros(dx.shape, np.int8)
    if o[2] > prims.kerb_h and dz.ndim:
        down = np.flatnonzero((dz < 0.0).reshape(len(dz), -1).any(axis=1))
        rows = slice(down[0], down[-1] + 1) if len(down) else slice(0, 0)
    else:
        rows = slice(None)
    if dz[rows].size:
        t[rows], part[rows] = hit_ground(prims.arc, prims.kerb_l, prims.kerb_h, o,
                                         dx[rows], dy[rows], dz[rows])
    kind = np.where(np.isfinite(t), GROUND, SKY).astype(np.int8)
    index = part.astype(np.int32)
    face = np.zeros(dx.shape, np.int8)
    inv = None
    if prims.arc.kappa == 0.0:
        inv = tuple(1.0 / np.where(d == 0.0, _TINY, d) for d in (dx, dy, dz))
    for k, i, sel, zmin in candidates:
        tb = t[sel]
        if tb.size == 0 or (zmin is not None and tb.max() <= zmin):
            continue
        inv_sel = None if inv is None or k != BOX else tuple(a[sel] for a in inv)
        tt, ff = _hit_object(prims, k, i, o, dx[sel], dy[sel], dz[sel], inv_sel)
        m = tt < tb
        tie = tt == tb
        if tie.any():
            # touching faces: the lower (kind, index) wins, whatever order objects come in
            tie &= np.isfinite(tt)
            kb, ib = kind[sel], index[sel]
            m |= tie & ((k < kb) | ((k == kb) & (i < ib)))
        if not m.any():
            continue
        if isinstance(sel, tuple):
            t[sel] = np.where(m, tt, tb)
            kind[sel][m] = k
            index[sel][m] = i
            face[sel][m] = ff(m) if callable(ff) else ff[m]
        else:
            where = sel[m]
            t[where] = tt[m]
            kind[where] = k
            index[where] = i
            face[where] = ff(m) if callable(ff) else ff[m]
    return Hits(t, kind, index, face)


def cast_camera(prims: Primitives, c2w: np.ndarray, K: np.ndarray, width: int, height: int,
                bounds=None, cull: bool = True):
    """Cast one pinhole camera's pixel rays (centre of pixel (v, u) at (u + 0.5, v + 0.5)).

    bounds: prims.bound_points(), if already computed. cull=False tests every ray against every
    object (the reference the culled cast must equal).
    Returns (hits (H, W), origin (3,), (dx, dy, dz) each (H, W) with unit camera-z, so t is depth).
    """
    c2w = np.asarray(c2w, np.float64)
    K = np.asarray(K, np.float64)
    rot = c2w[:3, :3]
    o = c2w[:3, 3].copy()
    u = (np.arange(width) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(height) + 0.5 - K[1, 2]) / K[1, 1]
    u = u - K[0, 1] * v[:, None] / K[0, 0] if K[0, 1] != 0.0 else np.broadcast_to(u, (height, width))
    vv = np.broadcast_to(v[:, None], (height, width))
    d = [rot[r, 0] * u + rot[r, 1] * vv + rot[r, 2] for r in range(3)]
    kinds, idx, pts = bounds if bounds is not None else prims.bound_points()
    if not cull:
        everything = (slice(None), slice(None))
        cands: list[tuple[int, int, tuple[slice, slice], float | None]] = [
            (int(k), int(i), everything, None) for k, i in zip(kinds, idx)]
        return cast(prims, o, d[0], d[1], d[2], cands), o, d
    w2c = np.linalg.inv(c2w)
    rects, zmin, vis = screen_rects(pts, w2c, K, width, height)
    order = np.argsort(zmin, kind="stable")
    cands = [(int(kinds[j]), int(idx[j]),
              (slice(rects[j, 0], rects[j, 1]), slice(rects[j, 2], rects[j, 3])), float(zmin[j]))
             for j in order if vis[j]]
    hits = cast(prims, o, d[0], d[1], d[2], cands)
    return hits, o, d


# ---------------------------------------------------------------------------------------------
# shading


# face normals on a straight road, up to sign: Z0, Z1, L0, L1, S0, S1
_BOX_NORMALS = np.array([[0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 1, 0], [1, 0, 0], [1, 0, 0]], np.float32)


def group_normals(prims: Primitives, kind: int, part: int, index, face, px, py, pz, s) -> np.ndarray:
    """Unit normals (m, 3) float32, up to sign, of hits on one kind of surface.

    part: the ground part when kind is GROUND; index/face: per hit; px, py, pz: hit points;
    s: their road arc length.
    """
    m = len(index)
    n = np.zeros((m, 3), np.float32)
    if kind == GROUND:
        if part != KERB:
            n[:, 2] = 1.0
            return n
        n[:, 1] = 1.0
        th = prims.arc.heading(s)
    elif kind == BOX:
        n[:] = _BOX_NORMALS[face]
        if prims.arc.kappa == 0.0:
            return n
        sb = np.where(face == S0, prims.boxes[index, 0], prims.boxes[index, 1])
        th = prims.arc.heading(np.where((face == S0) | (face == S1), sb, s))
    elif kind == CYLINDER:
        c = prims.cylinders[index]
        side = face == SIDE
        n[:, 0] = np.where(side, (px - c[:, 0]) / c[:, 2], 0.0)
        n[:, 1] = np.where(side, (py - c[:, 1]) / c[:, 2], 0.0)
        n[:, 2] = np.where(side, 0.0, 1.0)
        return n
    else:
        c = prims.spheres[index]
        n[:] = (np.stack([px, py, pz], -1) - c[:, :3]) / c[:, 3:4]
        return n
    if prims.arc.kappa != 0.0:  # turn road-aligned normals by the local heading
        c, sn = np.cos(th), np.sin(th)
        x, y = n[:, 0].astype(np.float64), n[:, 1].astype(np.float64)
        n[:, 0] = x * c - y * sn
        n[:, 1] = x * sn + y * c
    return n


def light(normal: np.ndarray, sign: np.ndarray, sun: np.ndarray,
          ambient: float = 0.42, diffuse: float = 0.68) -> np.ndarray:
    """Lambert shading factor (m,): normal (m, 3) times sign (m,) faces the viewer; sun (3,)
    unit, towards the sun. Colour = albedo * factor."""
    return ambient + diffuse * np.clip((normal @ sun) * sign, 0.0, None)


def sky_colour(dx, dy, dz, sun: np.ndarray, zenith, horizon) -> np.ndarray:
    """Sky radiance (m,3) for directions (m,) each: vertical gradient plus a sun disc and glow."""
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    el = np.clip(dz / norm, -1.0, 1.0)
    f = np.clip(el, 0.0, 1.0) ** 0.55
    col = np.asarray(horizon)[None] * (1.0 - f)[:, None] + np.asarray(zenith)[None] * f[:, None]
    cosang = (dx * sun[0] + dy * sun[1] + dz * sun[2]) / norm
    glow = np.clip((cosang - 0.97) / 0.03, 0.0, 1.0) ** 3 * 0.35
    disc = (cosang > 0.99993).astype(np.float64)
    return np.clip(col + (glow + disc)[:, None] * np.array([1.0, 0.95, 0.85])[None], 0.0, 1.2)
