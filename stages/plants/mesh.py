"""Skeleton -> generalized cylinders -> one watertight, manifold woody solid.

Segments on one axis (no '[' between them, turns up to max_joint_angle) form
one tube: rings at every node, each ring in the plane of the bisector of the
two segments meeting there (radius widened by 1/cos(half the turn) so the
cross-section keeps its size), frames carried by parallel transport (no
twist), so the tube has no gaps or cracks at its joints and its v coordinate
(path length from the root / bark_uv_length) runs on continuously. A side
branch's tube starts inside its parent (pushed back along its own axis by
half the parent's radius); every tube is closed by a flat start cap and a
bulged end cap. manifold3d's batch union then makes all tubes one closed,
oriented 2-manifold, carrying uv, normal and wind data as vertex properties.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.errors import StageError

from . import geometry
from .reference import VERT
from .turtle import Skeleton, path_length


@dataclass
class Part:
    """A triangle mesh with split vertices: `verts` (n, VERT) rows of
    position, normal, uv, wind data; `tris` (m, 3) into verts; `weld` (n,)
    maps each vertex to its welded position index (seams share a position)."""

    verts: np.ndarray
    tris: np.ndarray
    weld: np.ndarray

    @staticmethod
    def empty() -> "Part":
        return Part(np.zeros((0, VERT), np.float32), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))

    @property
    def n_tris(self) -> int:
        return len(self.tris)

    def welded(self) -> tuple[np.ndarray, np.ndarray]:
        """(positions, faces) of the welded mesh (the topology)."""
        if len(self.verts) == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        n_pos = int(self.weld.max()) + 1 if len(self.weld) else 0
        pos = np.zeros((n_pos, 3), np.float64)
        pos[self.weld] = self.verts[:, 0:3]
        return pos, self.weld[self.tris]

    @staticmethod
    def concat(parts: list["Part"]) -> "Part":
        parts = [p for p in parts if len(p.verts)]
        if not parts:
            return Part.empty()
        verts, tris, weld = [], [], []
        vo = wo = 0
        for p in parts:
            verts.append(p.verts)
            tris.append(p.tris + vo)
            weld.append(p.weld + wo)
            vo += len(p.verts)
            wo += int(p.weld.max()) + 1
        return Part(np.concatenate(verts), np.concatenate(tris), np.concatenate(weld))


@dataclass
class Tubes:
    """All tubes of a plant before the union: ring records for the kernel
    and, per tube, its vertex and triangle ranges."""

    ring: np.ndarray  # (R, RING) float32
    sides: np.ndarray  # (R,) int32
    tube_rings: list[tuple[int, int, int]]  # per tube: first ring, ring count, sides
    n_tubes: int


def _perp(t: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    v = a - t * (a @ t)
    return v / np.linalg.norm(v)


def build_chains(sk: Skeleton, radius: np.ndarray, min_radius: float, max_joint_angle: float) -> list[list[int]]:
    """Group segments into tubes: a segment joins its parent's tube when it
    continues the parent's axis, the parent has not been continued yet and
    the turn is at most max_joint_angle. Segments thinner than min_radius are
    left out (they and their tubes' joints are not drawn)."""
    n = sk.n_segments
    chain_of = np.full(n, -1, np.int64)
    continued = np.zeros(n, bool)
    chains: list[list[int]] = []
    cos_max = math.cos(math.radians(max_joint_angle)) - 1e-9
    H = sk.heading
    par = sk.parent.tolist()
    cont = sk.cont.tolist()
    for s in range(n):
        if not radius[s] >= min_radius or radius[s] <= 0:
            continue
        p = par[s]
        if (cont[s] and p >= 0 and chain_of[p] >= 0 and not continued[p]
                and float(H[p] @ H[s]) >= cos_max):
            c = chain_of[p]
            chains[c].append(s)
            chain_of[s] = c
            continued[p] = True
        else:
            chain_of[s] = len(chains)
            chains.append([s])
    return chains


def build_tubes(sk: Skeleton, radius: np.ndarray, wood, min_radius: float, phase_rng: np.random.Generator) -> Tubes:
    """Ring records (reference.RING layout) for every tube."""
    chains = build_chains(sk, radius, min_radius, wood.max_joint_angle)
    start_len, end_len = path_length(sk)
    max_path = float(end_len.max()) if len(end_len) else 1.0
    max_path = max(max_path, 1e-9)
    drawn = np.zeros(sk.n_segments, bool)
    for ch in chains:
        drawn[ch] = True
    rings, sides_l, tube_rings = [], [], []
    phases = phase_rng.random(len(chains))
    r_first = 0
    for ci, ch in enumerate(chains):
        idx = np.asarray(ch)
        H = sk.heading[idx]
        p0, p1 = sk.p0[idx], sk.p1[idx]
        r = radius[idx]
        k = len(ch)
        centers = np.concatenate([p0[:1], p1], axis=0)  # k + 1 nodes
        T = np.empty((k + 1, 3))
        T[0], T[k] = H[0], H[-1]
        rr = np.empty(k + 1)
        rr[0], rr[k] = r[0], r[-1]
        if k > 1:
            bis = H[:-1] + H[1:]
            bn = np.linalg.norm(bis, axis=1)
            T[1:k] = bis / bn[:, None]
            miter = np.clip(2.0 / np.maximum(bn, 1e-9), 1.0, 1.6)  # 1 / cos(turn / 2)
            rr[1:k] = 0.5 * (r[:-1] + r[1:]) * miter
        vs = np.concatenate([[start_len[idx[0]]], end_len[idx]])
        # a side branch (or a tube restarted after a sharp turn) starts inside its parent
        p = int(sk.parent[idx[0]])
        if p >= 0 and drawn[p]:
            seg0 = float(np.linalg.norm(p1[0] - p0[0]))
            back = min(0.5 * float(radius[p]), 0.5 * seg0)
            centers[0] = centers[0] - H[0] * back
            vs[0] -= back
        # parallel transport of the normal
        N = np.empty((k + 1, 3))
        n0 = sk.left[idx[0]] - T[0] * (sk.left[idx[0]] @ T[0])
        nn = np.linalg.norm(n0)
        N[0] = n0 / nn if nn > 1e-9 else _perp(T[0])
        for j in range(1, k + 1):
            v = N[j - 1] - T[j] * (N[j - 1] @ T[j])
            nv = np.linalg.norm(v)
            N[j] = v / nv if nv > 1e-9 else _perp(T[j])
        B = np.cross(T, N)
        # slope of the tapering radius (tilts normals forward on a cone)
        dist = np.linalg.norm(np.diff(centers, axis=0), axis=1)
        slope = np.zeros(k + 1)
        if k >= 1:
            slope[0] = (rr[0] - rr[1]) / max(dist[0], 1e-9)
            slope[k] = (rr[k - 1] - rr[k]) / max(dist[-1], 1e-9)
        if k > 1:
            slope[1:k] = (rr[:-2] - rr[2:]) / np.maximum(dist[:-1] + dist[1:], 1e-9)
        slope = np.clip(slope, -2.0, 2.0)
        bw = np.clip(vs / max_path, 0.0, 1.0) ** 1.5
        s = int(np.clip(math.ceil(2 * math.pi * rr.max() / wood.max_edge), wood.sides_min, wood.sides_max))
        rec = np.zeros((k + 1, 20))
        rec[:, 0:3], rec[:, 3:6], rec[:, 6:9], rec[:, 9:12] = centers, N, B, T
        rec[:, 12], rec[:, 13], rec[:, 14] = rr, slope, vs / wood.bark_uv_length
        rec[:, 15], rec[:, 16], rec[:, 17:20] = bw, phases[ci], centers[0]
        rings.append(rec)
        sides_l.append(np.full(k + 1, s, np.int32))
        tube_rings.append((r_first, k + 1, s))
        r_first += k + 1
    if not rings:
        return Tubes(np.zeros((0, 20), np.float32), np.zeros(0, np.int32), [], 0)
    return Tubes(np.concatenate(rings).astype(np.float32), np.concatenate(sides_l), tube_rings, len(chains))


def tube_triangles(n_rings: int, s: int) -> np.ndarray:
    """Triangles of one tube in its local vertex numbering (tube_vertices):
    rings of s + 1 vertices, then the start cap (s ring copies, centre), then
    the end cap (s ring copies, centre). Outward-facing (counter-clockwise
    seen from outside)."""
    w = s + 1
    j = np.arange(n_rings - 1)[:, None]
    k = np.arange(s)[None, :]
    a = (j * w + k).ravel()
    b, c, d = a + 1, a + w, a + w + 1
    body = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    k = np.arange(s)
    k1 = (k + 1) % s
    s0 = n_rings * w
    cs = s0 + s
    e0 = cs + 1
    ce = e0 + s
    start = np.stack([np.full(s, cs), s0 + k1, s0 + k], 1)
    end = np.stack([np.full(s, ce), e0 + k, e0 + k1], 1)
    return np.concatenate([body, start, end]).astype(np.int64)


def tube_vertices(ring_verts: np.ndarray, rec: np.ndarray, s: int, bulge: float) -> tuple[np.ndarray, np.ndarray]:
    """One tube's vertices: its rings (from the kernel) plus the cap vertices
    (copies of the first and last ring with cap normals, and the two cap
    centres); and the weld map (seam and cap copies share positions)."""
    nr = len(rec)
    w = s + 1
    first, last = ring_verts[:s], ring_verts[(nr - 1) * w:(nr - 1) * w + s]
    T0, T1 = rec[0, 9:12], rec[-1, 9:12]
    r1 = max(float(rec[-1, 12]), 1e-12)
    start = first.copy()
    start[:, 3:6] = -T0
    ang = 2 * np.pi * np.arange(s) / s
    start[:, 6], start[:, 7] = 0.5 + 0.5 * np.cos(ang), 0.5 + 0.5 * np.sin(ang)
    end = last.copy()
    radial = (end[:, 0:3] - rec[-1, 0:3]) / r1
    en = radial * bulge + T1
    end[:, 3:6] = en / np.linalg.norm(en, axis=1, keepdims=True)
    end[:, 6], end[:, 7] = start[:, 6], start[:, 7]
    cs = first[0].copy()
    cs[0:3], cs[3:6], cs[6:8] = rec[0, 0:3], -T0, 0.5
    ce = last[0].copy()
    ce[0:3], ce[3:6], ce[6:8] = rec[-1, 0:3] + T1 * bulge * r1, T1, 0.5
    verts = np.concatenate([ring_verts, start, cs[None], end, ce[None]]).astype(np.float32)
    return verts, _tube_weld(nr, s)


def _tube_weld(nr: int, s: int) -> np.ndarray:
    """Welded position of every tube vertex: ring (j, k) -> j s + k mod s,
    start cap copies -> ring 0, its centre -> nr s, end cap copies -> the
    last ring, its centre -> nr s + 1."""
    k = np.arange(s + 1) % s
    rings = (np.arange(nr)[:, None] * s + k[None, :]).ravel()
    return np.concatenate([rings, np.arange(s), [nr * s], (nr - 1) * s + np.arange(s), [nr * s + 1]]).astype(np.int64)


def tube_parts(env, tubes: Tubes, bulge: float) -> list[Part]:
    """Vertices of all tubes (the tube_rings kernel on the OpenCL device
    `env`; None: its numpy reference), split per tube."""
    verts = geometry.tube_rings(env, tubes.ring, tubes.sides)
    parts = []
    vo = 0
    for r0, nr, s in tubes.tube_rings:
        nv = nr * (s + 1)
        v, weld = tube_vertices(verts[vo:vo + nv], tubes.ring[r0:r0 + nr], s, bulge)
        vo += nv
        parts.append(Part(v, tube_triangles(nr, s), weld))
    return parts


def union(parts: list[Part]) -> tuple[Part, dict]:
    """manifold3d batch union of closed tubes -> one solid; returns the part
    and diagnostics (status, genus, volume)."""
    import manifold3d as m3d

    solids = []
    for i, p in enumerate(parts):
        first = np.full(int(p.weld.max()) + 1, len(p.weld), np.int64)
        np.minimum.at(first, p.weld, np.arange(len(p.weld)))
        from_v = np.nonzero(first[p.weld] != np.arange(len(p.weld)))[0]
        to_v = first[p.weld[from_v]]
        mesh = m3d.Mesh(vert_properties=np.ascontiguousarray(p.verts, np.float32),
                        tri_verts=np.ascontiguousarray(p.tris, np.uint32),
                        merge_from_vert=from_v.astype(np.uint32), merge_to_vert=to_v.astype(np.uint32))
        s = m3d.Manifold(mesh)
        if s.status() != m3d.Error.NoError:
            raise StageError(f"plants: tube {i} is not a valid manifold ({s.status()}); this is a bug in the tube builder")
        solids.append(s)
    if not solids:
        return Part.empty(), {"status": "empty", "genus": 0, "volume": 0.0}
    solid = m3d.Manifold.batch_boolean(solids, m3d.OpType.Add)
    if solid.status() != m3d.Error.NoError:
        raise StageError(f"plants: the union of the branch tubes failed: {solid.status()}")
    out = solid.to_mesh()
    props = np.asarray(out.vert_properties, np.float32)
    tris = np.asarray(out.tri_verts, np.int64)
    weld = np.arange(len(props))
    mf, mt = np.asarray(out.merge_from_vert, np.int64), np.asarray(out.merge_to_vert, np.int64)
    weld[mf] = mt
    weld = weld[weld]  # in case of chains
    _, weld = np.unique(weld, return_inverse=True)
    info = {"status": "ok", "genus": int(solid.genus()), "volume": float(solid.volume())}
    return Part(props, tris, weld.astype(np.int64)), info


def check_solid(part: Part) -> dict:
    """Watertight / manifold / oriented / non-degenerate, from manifold3d and
    trimesh independently."""
    import manifold3d as m3d
    import trimesh

    pos, faces = part.welded()
    res = {"triangles": int(len(faces))}
    if len(faces) == 0:
        res.update(watertight=True, manifold=True, winding_consistent=True, min_area=0.0, volume=0.0, degenerate=0)
        return res
    tm = trimesh.Trimesh(vertices=pos, faces=faces, process=False)
    res["watertight"] = bool(tm.is_watertight)
    res["winding_consistent"] = bool(tm.is_winding_consistent)
    res["volume"] = float(tm.volume)
    area = tm.area_faces
    alt, _ = _altitudes(pos, faces)
    res["min_area"] = float(area.min())
    res["min_altitude"] = float(alt.min())
    # degenerate: a repeated vertex, or a triangle flatter than 10 nm (float32 cannot keep its normal)
    res["degenerate"] = int(((alt < 1e-8) | (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
                             | (faces[:, 0] == faces[:, 2])).sum())
    s = m3d.Manifold(m3d.Mesh(vert_properties=np.ascontiguousarray(pos, np.float32), tri_verts=np.ascontiguousarray(faces, np.uint32)))
    res["manifold"] = bool(s.status() == m3d.Error.NoError)
    res["manifold_volume"] = float(s.volume()) if res["manifold"] else 0.0
    # normals agree with the faces they belong to
    fn = tm.face_normals
    cn = part.verts[part.tris][:, :, 3:6].astype(np.float64)
    dots = np.einsum("fcj,fj->fc", cn, fn)
    res["normals_agree"] = float((dots > 0).mean())
    return res


def collapse_short_edges(part: Part, eps: float) -> tuple[Part, int]:
    """Weld positions closer than eps (the union leaves edges of 1e-10 m where
    three surfaces cut each other almost in one point) and drop the triangles
    that become degenerate. Returns the part and how many positions merged."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pos, faces = part.welded()
    if len(pos) == 0:
        return part, 0
    pairs = cKDTree(pos).query_pairs(eps, output_type="ndarray")
    if len(pairs) == 0:
        return part, 0
    n = len(pos)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(g, directed=False)
    # representative = lowest index in each class
    rep = np.full(label.max() + 1, n, np.int64)
    np.minimum.at(rep, label, np.arange(n))
    new_pos_index = rep[label]
    weld = new_pos_index[part.weld]
    t = weld[part.tris]
    keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    # a collapse can leave two opposite copies of one triangle (a fin): drop both
    key = np.sort(t, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    keep &= cnt[inv.ravel()] == 1
    tris = part.tris[keep]
    used = np.unique(tris)
    remap = np.full(len(part.verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    verts = part.verts[used].copy()
    w = weld[used]
    verts[:, 0:3] = pos[w]
    _, w = np.unique(w, return_inverse=True)
    return Part(verts, remap[tris], w.astype(np.int64)), int(n - len(np.unique(new_pos_index)))


def _altitudes(pos: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle: the smallest altitude and the index (0..2) of its longest edge (k -> k+1)."""
    tri = pos[faces]
    e = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], 1)
    ln = np.linalg.norm(e, axis=2)
    area2 = np.linalg.norm(np.cross(e[:, 0], -e[:, 2]), axis=1)
    k = ln.argmax(1)
    return area2 / np.maximum(ln.max(1), 1e-30), k


def flip_needles(part: Part, eps: float, passes: int = 8) -> tuple[Part, int]:
    """Flip the longest edge of every needle triangle (altitude < eps, its
    third vertex almost on that edge): the two triangles on the edge become
    two well-shaped ones. Keeps the mesh closed and oriented; a flip that
    would duplicate an edge, fold a triangle over or not improve the worse
    altitude is skipped."""
    tris = part.tris.copy()
    n_pos = int(part.weld.max()) + 1 if len(part.weld) else 0
    pos = np.zeros((n_pos, 3))
    pos[part.weld] = part.verts[:, 0:3]
    total = 0
    for _ in range(passes):
        W = part.weld[tris]
        alt, kmax = _altitudes(pos, W)
        needles = np.nonzero(alt < eps)[0]
        if len(needles) == 0:
            break
        # directed edges (a -> b) of all triangles, sorted for lookup
        a = W.ravel()
        b = W[:, [1, 2, 0]].ravel()
        keys = a * n_pos + b
        order = np.argsort(keys)
        skeys = keys[order]

        def lookup(x, y):
            q = x * n_pos + y
            i = np.searchsorted(skeys, q)
            return order[i] // 3 if i < len(skeys) and skeys[i] == q else -1

        touched = set()
        flips = 0
        for t in needles.tolist():
            if t in touched:
                continue
            k = int(kmax[t])
            wa, wb, wc = int(W[t, k]), int(W[t, (k + 1) % 3]), int(W[t, (k + 2) % 3])
            u = lookup(wb, wa)
            if u < 0 or u in touched:
                continue
            ku = [i for i in range(3) if W[u, i] == wb][0]  # u = (b, a, d) up to rotation
            wd = int(W[u, (ku + 2) % 3])
            if wd == wc or lookup(wc, wd) >= 0 or lookup(wd, wc) >= 0:
                continue
            n_old = np.cross(pos[wb] - pos[wa], pos[wc] - pos[wa]) + np.cross(pos[wa] - pos[wb], pos[wd] - pos[wb])
            n1 = np.cross(pos[wd] - pos[wa], pos[wc] - pos[wa])
            n2 = np.cross(pos[wb] - pos[wd], pos[wc] - pos[wd])
            if n1 @ n_old <= 0 or n2 @ n_old <= 0:
                continue
            new_alt = _altitudes(pos, np.array([[wa, wd, wc], [wd, wb, wc]]))[0]
            if new_alt.min() <= alt[t]:
                continue
            sa, sc = tris[t, k], tris[t, (k + 2) % 3]
            sb_u, sd = tris[u, ku], tris[u, (ku + 2) % 3]
            tris[t] = [sa, sd, sc]
            tris[u] = [sd, sb_u, sc]
            touched.update((t, u))
            flips += 1
        total += flips
        if flips == 0:
            break
    return Part(part.verts, tris, part.weld), total


def fix_corner_normals(part: Part, min_dot: float = 0.2) -> tuple[Part, int]:
    """Where the union interpolated a normal across a crease (a corner whose
    normal leans away from its face), give that corner its face's normal."""
    pos, faces = part.welded()
    if len(faces) == 0:
        return part, 0
    fn = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    cn = part.verts[part.tris][:, :, 3:6].astype(np.float64)
    bad = np.einsum("fcj,fj->fc", cn, fn) < min_dot
    if not bad.any():
        return part, 0
    fi, ci = np.nonzero(bad)
    verts = np.concatenate([part.verts, part.verts[part.tris[fi, ci]]])
    verts[len(part.verts):, 3:6] = fn[fi]
    tris = part.tris.copy()
    tris[fi, ci] = len(part.verts) + np.arange(len(fi))
    weld = np.concatenate([part.weld, part.weld[part.tris[fi, ci]]])
    return Part(verts, tris, weld), int(len(fi))
