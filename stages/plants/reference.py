"""Plain numpy versions of the maths in kernels.cl: small and obviously right.
Tests compare them with the kernels; `use_opencl = false` runs them instead.

Vertex layout (VERT, 14 float32 per vertex), shared by wood, leaves, blades:
    0-2 position   3-5 normal   6-7 uv   8 wind branch weight   9 wind flutter weight
    10 wind phase  11-13 wind pivot
"""
from __future__ import annotations

import numpy as np

VERT = 14
RING = 20  # c.xyz N.xyz B.xyz T.xyz radius slope v bw phase pivot.xyz
LEAF = 17  # pos.xyz H.xyz L.xyz U.xyz scale reserved curl(1/m) bw phase
TMPL = 9  # x (along L) y (along H) z (along U) in metres, nL nH nU, u v, flutter
BLADE = 14  # root.xyz control.xyz tip.xyz side.xyz width phase


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def tube_rings(ring: np.ndarray, sides: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Ring r has sides[r] + 1 vertices (the last repeats the first at u = 1)
    starting at row offset[r]: position c + radius (cos t N + sin t B),
    normal along (cos t N + sin t B) + slope T, uv = (k / sides, v)."""
    ring = ring.astype(np.float64)
    sides = sides.astype(np.int64)
    counts = sides + 1
    n = int(counts.sum())
    out = np.zeros((n, VERT), np.float32)
    if n == 0:
        return out
    r_of = np.repeat(np.arange(len(ring)), counts)
    k = np.arange(n) - np.repeat(offset.astype(np.int64), counts)
    s = sides[r_of]
    theta = 2.0 * np.pi * k / s
    c, sn = np.cos(theta), np.sin(theta)
    c[k == s], sn[k == s] = 1.0, 0.0
    R = ring[r_of]
    d = c[:, None] * R[:, 3:6] + sn[:, None] * R[:, 6:9]
    out[:, 0:3] = R[:, 0:3] + R[:, 12:13] * d
    out[:, 3:6] = _normalize(d + R[:, 13:14] * R[:, 9:12])
    out[:, 6] = k / s
    out[:, 7] = R[:, 14]
    out[:, 8] = R[:, 15]
    out[:, 9] = 0.0
    out[:, 10] = R[:, 16]
    out[:, 11:14] = R[:, 17:20]
    return out


def leaf_instances(leaf: np.ndarray, tmpl: np.ndarray) -> np.ndarray:
    """Every leaf gets every template vertex, drooped by curl and scaled:
    p = pos + scale (x L + y H + (z - curl y^2) U); the normal tilts with the
    droop: n ~ nL L + (nH + 2 curl y nU) H + nU U."""
    leaf = leaf.astype(np.float64)
    tmpl = tmpl.astype(np.float64)
    nl, nt = len(leaf), len(tmpl)
    out = np.zeros((nl * nt, VERT), np.float32)
    if nl == 0 or nt == 0:
        return out
    Lf = np.repeat(leaf, nt, axis=0)
    T = np.tile(tmpl, (nl, 1))
    pos, H, Lv, U = Lf[:, 0:3], Lf[:, 3:6], Lf[:, 6:9], Lf[:, 9:12]
    sc, curl = Lf[:, 12:13], Lf[:, 14:15]
    x, y, z = T[:, 0:1], T[:, 1:2], T[:, 2:3]
    out[:, 0:3] = pos + sc * (x * Lv + y * H + (z - curl * y * y) * U)
    nL, nH, nU = T[:, 3:4], T[:, 4:5], T[:, 5:6]
    out[:, 3:6] = _normalize(nL * Lv + (nH + 2.0 * curl * y * nU) * H + nU * U)
    out[:, 6:8] = T[:, 6:8]
    out[:, 8] = Lf[:, 15]
    out[:, 9] = T[:, 8]
    out[:, 10] = Lf[:, 16]
    out[:, 11:14] = pos
    return out


def grass_blades(blade: np.ndarray, rows: np.ndarray, taper: float) -> np.ndarray:
    """Seed 000 eq. 2.5/2.6 as one strip per blade: rows at the curve
    parameters rows[b, j] (0 = root .. 1 = tip, n + 1 per blade) on the
    quadratic Bezier c(v) = (1-v)^2 b + 2v(1-v) h + v^2 t (De Casteljau), two
    vertices c -+ side w (1 - v^taper) / 2 per row and one tip vertex:
    2n + 1 vertices, 2n - 1 triangles. Normal = side x tangent."""
    blade = blade.astype(np.float64)
    rows = np.asarray(rows, np.float64)
    nb = len(blade)
    n = rows.shape[1] - 1 if rows.ndim == 2 else 0
    per = 2 * n + 1
    out = np.zeros((nb * per, VERT), np.float32)
    if nb == 0:
        return out
    b, h, t, s = blade[:, None, 0:3], blade[:, None, 3:6], blade[:, None, 6:9], blade[:, None, 9:12]
    w = blade[:, None, 12:13]
    vv = rows[:, :, None]
    a = b + vv * (h - b)
    q = h + vv * (t - h)
    c = a + vv * (q - a)
    tan = q - a
    nrm = _normalize(np.cross(np.broadcast_to(s, tan.shape), tan))
    half = 0.5 * w * (1.0 - vv ** taper)
    left, right = c - s * half, c + s * half
    o = out.reshape(nb, per, VERT)
    o[:, 0:2 * n:2, 0:3] = left[:, :n]
    o[:, 1:2 * n:2, 0:3] = right[:, :n]
    o[:, 2 * n, 0:3] = c[:, n]
    o[:, 0:2 * n:2, 3:6] = nrm[:, :n]
    o[:, 1:2 * n:2, 3:6] = nrm[:, :n]
    o[:, 2 * n, 3:6] = nrm[:, n]
    o[:, 0:2 * n:2, 6] = 0.0
    o[:, 1:2 * n:2, 6] = 1.0
    o[:, 2 * n, 6] = 0.5
    vrow = np.concatenate([np.repeat(rows[:, :n], 2, axis=1), rows[:, n:]], axis=1)
    o[:, :, 7] = vrow
    o[:, :, 8] = vrow ** 2
    o[:, :, 9] = vrow
    o[:, :, 10] = blade[:, None, 13]
    o[:, :, 11:14] = blade[:, None, 0:3]
    return out
