"""Grass tufts: Bezier blades (seed 000, Jahrmann and Wimmer 2013) and the
slice-card tuft of seed 001.

Per blade (seed 000 eq. 2.1-2.6, with the sensible reading of its code):
  R ~ U[0,1] drives width and height together (w, h perfectly correlated);
  the root lies uniformly in a disc of radius tuft_radius;
  the tip is offset by b h (2 R1 - 1, 2 R2 - 1) with R1, R2 ~ U[0,1]: the
  thesis code computed g (b (2 r1) - 1) with r1 in [-1, 1], which made every
  blade lean toward -x/-z; here the lean is symmetric about the root (the
  bug fixed), plus an optional share pointing away from the tuft centre;
  the control point sits nearly above the root at (0.75 .. 1.0) h, displaced
  horizontally by +-25 % of the root-to-tip offset, so the blade leaves the
  ground upright and bends toward its tip;
  the width tapers as 1 - v^1.5 (the alpha silhouette of the thesis' blade).
A blade of n segments has 2n + 1 vertices and 2n - 1 triangles (a one-column
strip with a single tip vertex: no zero-area triangle at the tip).
"""
from __future__ import annotations


import numpy as np

from . import geometry
from .mesh import Part
from .reference import BLADE, VERT


def blade_records(g, rng: np.random.Generator) -> np.ndarray:
    n = g.blades
    R = rng.random(n)
    w = g.width_min + R * (g.width_max - g.width_min)
    h = g.height_min + R * (g.height_max - g.height_min)
    rad = g.tuft_radius * np.sqrt(rng.random(n))
    ang = 2 * np.pi * rng.random(n)
    root = np.stack([rad * np.cos(ang), np.zeros(n), rad * np.sin(ang)], 1)
    outward = np.stack([np.cos(ang), np.zeros(n), np.sin(ang)], 1)
    R1, R2, R3 = rng.random(n), rng.random(n), rng.random(n)
    sym = np.stack([2 * R1 - 1, np.zeros(n), 2 * R2 - 1], 1)  # symmetric lean: the fix of seed 000's bug
    off = (g.bend * h)[:, None] * ((1 - g.outward) * sym + g.outward * R3[:, None] * outward)
    tip = root + off + np.stack([np.zeros(n), h, np.zeros(n)], 1)
    r3x = g.control_xz * (2 * rng.random(n) - 1)
    r3z = g.control_xz * (2 * rng.random(n) - 1)
    r4 = g.control_y_min + rng.random(n) * (g.control_y_max - g.control_y_min)
    ctrl = root + np.stack([r3x * off[:, 0], r4 * h, r3z * off[:, 2]], 1)
    # the blade's width direction: horizontal, across its lean, twisted by up to +-30 degrees
    lean = np.arctan2(off[:, 2], off[:, 0])
    twist = np.radians(30.0) * (2 * rng.random(n) - 1)
    a = lean + np.pi / 2 + twist
    side = np.stack([np.cos(a), np.zeros(n), np.sin(a)], 1)
    phase = rng.random(n)
    rec = np.zeros((n, BLADE))
    rec[:, 0:3], rec[:, 3:6], rec[:, 6:9], rec[:, 9:12] = root, ctrl, tip, side
    rec[:, 12], rec[:, 13] = w, phase
    return rec.astype(np.float32)


def blade_triangles(n_blades: int, n: int) -> np.ndarray:
    """2n - 1 triangles per blade, facing along side x tangent."""
    per = 2 * n + 1
    tris = []
    for j in range(n - 1):
        l0, r0, l1, r1 = 2 * j, 2 * j + 1, 2 * j + 2, 2 * j + 3
        tris += [[l0, r0, r1], [l0, r1, l1]]
    tris.append([2 * n - 2, 2 * n - 1, 2 * n])
    t = np.asarray(tris, np.int64)
    return (t[None] + (np.arange(n_blades) * per)[:, None, None]).reshape(-1, 3)


def row_parameters(rec: np.ndarray, segments: int, dense: int = 128) -> np.ndarray:
    """Curve parameters of the n + 1 rows of every blade, spaced so each
    segment takes an equal share of the integral of sqrt(curvature) ds (the
    node density that minimises the chord error of a polyline): a blade that
    bends sharply near its tip gets its rows there."""
    rec = np.asarray(rec, np.float64)
    nb = len(rec)
    if nb == 0:
        return np.zeros((0, segments + 1), np.float32)
    v = np.linspace(0.0, 1.0, dense + 1)
    b, h, t = rec[:, None, 0:3], rec[:, None, 3:6], rec[:, None, 6:9]
    vv = v[None, :, None]
    c = (1 - vv) ** 2 * b + 2 * vv * (1 - vv) * h + vv ** 2 * t
    d = np.diff(c, axis=1)
    ds = np.maximum(np.linalg.norm(d, axis=2), 1e-12)
    tn = d / ds[..., None]
    turn = np.arccos(np.clip((tn[:, 1:] * tn[:, :-1]).sum(2), -1.0, 1.0))
    turn = np.concatenate([turn[:, :1], 0.5 * (turn[:, 1:] + turn[:, :-1]), turn[:, -1:]], 1)
    w = np.sqrt(turn * ds) + 1e-6 * ds  # the small arc-length term keeps straight blades uniform
    cum = np.concatenate([np.zeros((nb, 1)), np.cumsum(w, 1)], 1)
    cum /= cum[:, -1:]
    target = np.linspace(0.0, 1.0, segments + 1)
    rows = np.stack([np.interp(target, cum[i], v) for i in range(nb)])
    rows[:, 0], rows[:, -1] = 0.0, 1.0
    return rows.astype(np.float32)


def blades(env, rec: np.ndarray, segments: int, taper: float) -> Part:
    """The blades' strips, made on the OpenCL device `env` (None: the numpy reference)."""
    verts = geometry.grass_blades(env, rec, row_parameters(rec, segments), taper)
    return Part(verts, blade_triangles(len(rec), segments), np.arange(len(verts), dtype=np.int64))


def slice_cards(rec: np.ndarray) -> Part:
    """Seed 001's low-poly tuft: 4 vertical quads (two parallel planes per
    axis, at +-1/3 of the footprint) and one horizontal quad at half height;
    10 triangles. UVs follow its atlas: the vertical quads take the four
    quarters of a 4:1 strip (front/front, front/back, side/front, side/back),
    the horizontal quad its own square (v offset by 1, so v in [1, 2])."""
    pts = np.concatenate([rec[:, 0:3], rec[:, 6:9]])
    ext = float(np.abs(pts[:, [0, 2]]).max()) if len(pts) else 0.1
    H = float(pts[:, 1].max()) if len(pts) else 0.1
    d = ext / 3.0
    quads = []
    for i, (axis, off) in enumerate((("z", -d), ("z", d), ("x", -d), ("x", d))):
        if axis == "z":
            q = [[-ext, 0, off], [ext, 0, off], [ext, H, off], [-ext, H, off]]
        else:
            q = [[off, 0, ext], [off, 0, -ext], [off, H, -ext], [off, H, ext]]
        uv = [[i / 4, 0], [(i + 1) / 4, 0], [(i + 1) / 4, 1], [i / 4, 1]]
        quads.append((np.asarray(q, float), np.asarray(uv, float)))
    y = 0.5 * H
    quads.append((np.asarray([[-ext, y, ext], [ext, y, ext], [ext, y, -ext], [-ext, y, -ext]], float),
                  np.asarray([[0, 1], [1, 1], [1, 2], [0, 2]], float)))
    verts, tris = [], []
    for qi, (q, uv) in enumerate(quads):
        n = np.cross(q[1] - q[0], q[2] - q[0])
        n /= np.linalg.norm(n)
        v = np.zeros((4, VERT))
        v[:, 0:3], v[:, 3:6], v[:, 6:8] = q, n, uv
        v[:, 8] = (q[:, 1] / max(H, 1e-9)) ** 2
        v[:, 9] = q[:, 1] / max(H, 1e-9)
        v[:, 10] = 0.25 * qi
        verts.append(v)
        b = 4 * qi
        tris += [[b, b + 1, b + 2], [b, b + 2, b + 3]]
    verts = np.concatenate(verts).astype(np.float32)
    return Part(verts, np.asarray(tris, np.int64), np.arange(len(verts), dtype=np.int64))


def grass_plan(segments: int, levels: int, ratio: float) -> list[tuple[str, int, float]]:
    """Per LOD: ('blades', n, keep) or ('cards', 0, 0). Segments halve while
    that at least halves the triangles (2n - 1 per blade); the last level of a
    chain of three or more is the slice-card tuft."""
    plan = [("blades", segments, 1.0)]
    n, keep = segments, 1.0
    for lvl in range(1, levels):
        if lvl == levels - 1 and levels >= 3:
            plan.append(("cards", 0, 0.0))
            break
        m = n
        while m > 1 and (2 * m - 1) > ratio * (2 * n - 1):
            m -= 1
        if (2 * m - 1) <= ratio * (2 * n - 1):
            n = m
        else:
            keep *= ratio
        plan.append(("blades", n, keep))
    return plan
