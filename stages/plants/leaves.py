"""Leaves: a template mesh per species (card, folded ellipse, needle bundle),
instanced at every `L` of the skeleton by the leaf_instances kernel, plus
the `{ f f f }` polygons of the string.

Template coordinates are metres in the leaf frame: x along the turtle's L
(across the blade), y along H (from the stalk to the tip), z along U (the
blade's face normal). Flutter weight runs 0 at the stalk to 1 at the tip.

Foliage LODs: LOD1 replaces each template by its bounding card (2
triangles); later levels keep a nested random subset of the leaves (half per
level), scaled up to keep the leaf area.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import geometry
from .mesh import Part
from .reference import LEAF, TMPL, VERT
from .turtle import Skeleton


@dataclass
class Template:
    rows: np.ndarray  # (n, TMPL)
    tris: np.ndarray  # (m, 3)

    @property
    def n_tris(self) -> int:
        return len(self.tris)


def finish_template(pos: np.ndarray, uv: np.ndarray, flutter: np.ndarray, tris: np.ndarray) -> Template:
    """Orient triangles to face +z (U) where the face has a z component,
    and give vertices area-weighted normals."""
    tris = np.asarray(tris, np.int64)
    a, b, c = pos[tris[:, 0]], pos[tris[:, 1]], pos[tris[:, 2]]
    fn = np.cross(b - a, c - a)
    flip = fn[:, 2] < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    fn[flip] = -fn[flip]
    vn = np.zeros_like(pos)
    for k in range(3):
        np.add.at(vn, tris[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-20)
    rows = np.zeros((len(pos), TMPL))
    rows[:, 0:3], rows[:, 3:6], rows[:, 6:8], rows[:, 8] = pos, vn, uv, flutter
    return Template(rows.astype(np.float32), tris)


def card_of(t: Template) -> Template:
    """The bounding card of a template in its x-y plane."""
    p = t.rows[:, 0:3].astype(np.float64)
    x0, x1 = float(p[:, 0].min()), float(p[:, 0].max())
    y0, y1 = float(p[:, 1].min()), float(p[:, 1].max())
    if x1 - x0 < 1e-9:
        x0, x1 = x0 - 1e-4, x1 + 1e-4
    pos = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    span = max(y1 - y0, 1e-9)
    return finish_template(pos, uv, (pos[:, 1] - y0) / span, [[0, 1, 2], [0, 2, 3]])


def make_template(leaf) -> Template | None:
    """The LOD0 template of a LeafSpec, or None for shape 'none'."""
    L, W, P = leaf.length, leaf.width, leaf.petiole
    if leaf.shape == "none":
        return None
    if leaf.shape == "card":
        pos = np.array([[-W / 2, P, 0], [W / 2, P, 0], [W / 2, P + L, 0], [-W / 2, P + L, 0]], float)
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
        return finish_template(pos, uv, (pos[:, 1] - P) / L, [[0, 1, 2], [0, 2, 3]])
    if leaf.shape == "ellipse":
        m = leaf.segments
        fold = math.tan(math.radians(leaf.fold))
        pos, uv, tris = [[0.0, P, 0.0]], [[0.5, 0.0]], []
        prev = [0]  # vertex ids of the previous row (left, mid, right) or the stalk point
        for i in range(1, m + 1):
            t = i / m
            y = P + t * L
            if i == m:
                pos.append([0.0, y, 0.0])
                uv.append([0.5, 1.0])
                cur = [len(pos) - 1]
            else:
                half = 0.5 * W * math.sin(math.pi * t ** 0.8) ** 0.7
                z = half * fold
                base = len(pos)
                pos += [[-half, y, z], [0.0, y, 0.0], [half, y, z]]
                uv += [[0.5 - half / W, t], [0.5, t], [0.5 + half / W, t]]
                cur = [base, base + 1, base + 2]
            if len(prev) == 1 and len(cur) == 3:
                tris += [[prev[0], cur[1], cur[0]], [prev[0], cur[2], cur[1]]]
            elif len(prev) == 3 and len(cur) == 3:
                tris += [[prev[0], prev[1], cur[1]], [prev[0], cur[1], cur[0]],
                         [prev[1], prev[2], cur[2]], [prev[1], cur[2], cur[1]]]
            elif len(prev) == 3 and len(cur) == 1:
                tris += [[prev[0], prev[1], cur[0]], [prev[1], prev[2], cur[0]]]
            else:  # m == 1: a single triangle-less leaf cannot happen (segments >= 2)
                pass
            prev = cur
        pos = np.asarray(pos, float)
        return finish_template(pos, np.asarray(uv, float), (pos[:, 1] - P) / L, tris)
    if leaf.shape == "needles":
        k = leaf.needles
        sp = math.radians(leaf.spread)
        pos, uv, tris = [], [], []
        golden = math.pi * (3 - math.sqrt(5))
        for i in range(k):
            phi = i * golden
            # needle direction on a cone about H; its width lies across, tangential to the cone
            d = np.array([math.sin(sp) * math.cos(phi), math.cos(sp), math.sin(sp) * math.sin(phi)])
            side = np.array([-math.sin(phi), 0.0, math.cos(phi)])
            base = np.array([0.0, P, 0.0]) + d * (0.15 * L * (i % 3) / 2)  # stagger along the twig
            b0, b1, tip = base - side * W / 2, base + side * W / 2, base + d * L
            n0 = len(pos)
            pos += [b0, b1, tip]
            uv += [[0, 0], [1, 0], [0.5, 1]]
            tris.append([n0, n0 + 1, n0 + 2])
        pos = np.asarray(pos, float)
        fl = np.tile([0.0, 0.0, 1.0], k)
        t = finish_template(pos, np.asarray(uv, float), fl, tris)
        return t
    raise ValueError(leaf.shape)


def leaf_records(sk: Skeleton, leaf, bw_of_segment: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, LEAF) records: frame, scale (with jitter), curl per metre, wind."""
    n = sk.n_leaves
    rec = np.zeros((n, LEAF), np.float64)
    if n == 0:
        return rec.astype(np.float32)
    jitter = 1.0 + leaf.size_jitter * (2.0 * rng.random(n) - 1.0)
    rec[:, 0:3], rec[:, 3:6], rec[:, 6:9], rec[:, 9:12] = sk.leaf_pos, sk.leaf_h, sk.leaf_l, sk.leaf_u
    rec[:, 12] = sk.leaf_scale * jitter
    rec[:, 14] = leaf.curl / max(leaf.length + leaf.petiole, 1e-9)
    par = sk.leaf_parent
    bw = np.ones(n)
    has = par >= 0
    if len(bw_of_segment):
        bw[has] = bw_of_segment[par[has]]
    rec[:, 15] = bw
    rec[:, 16] = rng.random(n)
    return rec.astype(np.float32)


def instance(env, tmpl: Template, rec: np.ndarray) -> Part:
    """The template at every leaf record, on the OpenCL device `env` (None: the numpy reference)."""
    verts = geometry.leaf_instances(env, rec, tmpl.rows)
    nl, nt = len(rec), len(tmpl.rows)
    tris = (tmpl.tris[None, :, :] + (np.arange(nl) * nt)[:, None, None]).reshape(-1, 3)
    return Part(verts, facing_normals(verts, tris), np.arange(len(verts), dtype=np.int64))


def facing_normals(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The triangles wound (counter-clockwise, USD's rightHanded) toward
    their vertices' normals. The template's x-y-z (L, H, U) is a left-handed
    frame, so placing it mirrors every leaf's winding: a DCC whose shading
    normal then points behind the face sees a leaf lit from its front as
    lit from behind (Cycles renders such foliage black), and worldlib.render,
    which turns the normal with the face, shades it from the wrong side and
    finds its AO rays blocked by the leaf itself."""
    p = verts[:, 0:3].astype(np.float64)
    face = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
    flip = (face * verts[:, 3:6].astype(np.float64)[tris].sum(1)).sum(1) < 0
    out = tris.copy()
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


def polygon_part(sk: Skeleton, bw_of_segment: np.ndarray) -> Part:
    """The `{ . f . }` polygons as triangle fans (Lparser leaves)."""
    parts = []
    for poly, par in zip(sk.polygons, sk.polygon_parent):
        k = len(poly)
        c = poly.mean(axis=0)
        n = np.zeros(3)
        for i in range(k):
            n += np.cross(poly[i] - c, poly[(i + 1) % k] - c)
        area2 = np.linalg.norm(n)
        if area2 < 1e-12:
            continue
        n /= area2
        v = np.zeros((k, VERT), np.float32)
        v[:, 0:3], v[:, 3:6] = poly, n
        # planar uv in the polygon's plane
        e1 = poly[1] - poly[0]
        e1 /= max(np.linalg.norm(e1), 1e-12)
        e2 = np.cross(n, e1)
        uv = np.stack([(poly - poly[0]) @ e1, (poly - poly[0]) @ e2], 1)
        span = np.maximum(uv.max(0) - uv.min(0), 1e-9)
        v[:, 6:8] = (uv - uv.min(0)) / span
        v[:, 8] = bw_of_segment[par] if par >= 0 and len(bw_of_segment) else 1.0
        v[:, 9] = np.linalg.norm(poly - poly[0], axis=1) / max(np.linalg.norm(poly - poly[0], axis=1).max(), 1e-9)
        v[:, 11:14] = poly[0]
        tris = np.stack([np.zeros(k - 2, np.int64), np.arange(1, k - 1), np.arange(2, k)], 1)
        parts.append(Part(v, tris, np.arange(k, dtype=np.int64)))
    return Part.concat(parts)


def subset(rec: np.ndarray, keep: float, rank: np.ndarray, area_comp: float = 1.0) -> np.ndarray:
    """The leaves whose rank falls below keep * n (nested across levels),
    scaled by keep^(-area_comp / 2) so the kept leaves carry the area."""
    if keep >= 1.0:
        return rec
    n = len(rec)
    k = int(math.floor(keep * n))
    sel = rec[rank < k].copy()
    sel[:, 12] *= keep ** (-0.5 * area_comp)
    return sel
