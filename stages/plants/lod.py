"""LOD chain tools: pymeshlab quadric edge-collapse for the woody solid,
vertex data carried over from LOD0, and pymeshlab's Hausdorff distance to
measure every level.

The error of a level is the symmetric Hausdorff distance between it and
LOD0 (the max of both one-sided distances, each sampled on vertices and
faces), stored in metres and as a fraction of LOD0's bounding-box diagonal.
"""
from __future__ import annotations

import numpy as np

from .mesh import Part


def _meshset(pos, faces):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(pos, np.float64), face_matrix=np.asarray(faces, np.int32)))
    return ms


def decimate(part: Part, target: int) -> Part:
    """Quadric edge collapse of the welded mesh to at most `target`
    triangles, keeping topology (so a closed manifold stays closed); uv,
    wind data come from the nearest LOD0 corner, normals are recomputed."""
    import pymeshlab

    pos, faces = part.welded()
    if len(faces) <= target or len(faces) == 0:
        return part
    ms = _meshset(pos, faces)
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target), qualitythr=0.3, preserveboundary=True, boundaryweight=1.0, preservenormal=True,
        preservetopology=True, optimalplacement=True, planarquadric=True, autoclean=True)
    m = ms.current_mesh()
    npos = np.asarray(m.vertex_matrix(), np.float64)
    nf = np.asarray(m.face_matrix(), np.int64)
    # drop unreferenced vertices
    used = np.unique(nf)
    remap = np.full(len(npos), -1, np.int64)
    remap[used] = np.arange(len(used))
    npos, nf = npos[used], remap[nf]
    return transfer(part, npos, nf)


def vertex_normals(pos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    fn = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
    vn = np.zeros_like(pos)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)


def _corner_samples(pos: np.ndarray, faces: np.ndarray, t: float = 0.1) -> np.ndarray:
    """Each corner pulled a little into its triangle: tells apart the two
    sides of a uv seam, where welded vertices have two uv values."""
    tri = pos[faces]
    c = tri.mean(axis=1, keepdims=True)
    return (tri + t * (c - tri)).reshape(-1, 3)


def transfer(src: Part, pos: np.ndarray, faces: np.ndarray) -> Part:
    """A Part on (pos, faces) with uv and wind data from the nearest corner
    of `src` and smooth normals of the new surface."""
    from scipy.spatial import cKDTree

    spos, sfaces = src.welded()
    tree = cKDTree(_corner_samples(spos, sfaces))
    _, idx = tree.query(_corner_samples(pos, faces))
    src_rows = src.verts[src.tris.reshape(-1)][idx]  # (3 nf, VERT)
    rows = src_rows.copy()
    corner_v = faces.reshape(-1)
    rows[:, 0:3] = pos[corner_v]
    rows[:, 3:6] = vertex_normals(pos, faces)[corner_v]
    # one split vertex per distinct (position, row)
    key = np.concatenate([corner_v[:, None].astype(np.float64), rows[:, 6:].astype(np.float64)], 1)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    verts = rows[first].astype(np.float32)
    tris = inv.reshape(-1, 3).astype(np.int64)
    weld = corner_v[first].astype(np.int64)
    return Part(verts, tris, weld)


def bbox_diagonal(pos: np.ndarray) -> float:
    if len(pos) == 0:
        return 0.0
    return float(np.linalg.norm(pos.max(0) - pos.min(0)))


def surface_samples(pos: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """The vertices plus n points spread over the faces by area, from a fixed
    seed (pymeshlab's own Monte Carlo face sampling is not seeded, so its
    Hausdorff figures change from run to run; ours must not)."""
    pos = np.asarray(pos, np.float64)
    tri = pos[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if n <= 0 or area.sum() <= 0:
        return pos
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(faces), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[idx]
    return np.concatenate([pos, t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])])


def hausdorff(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], samples: int) -> dict:
    """Symmetric Hausdorff distance between two (positions, faces) meshes:
    pymeshlab's exact point-to-surface distance from every vertex and from
    `samples` area-weighted surface points of each mesh to the other mesh."""
    import pymeshlab

    if len(a[1]) == 0 or len(b[1]) == 0:
        return {"max": 0.0 if len(a[1]) == len(b[1]) else float("inf"), "mean": 0.0, "a_to_b": 0.0, "b_to_a": 0.0}
    diag = max(bbox_diagonal(a[0]), bbox_diagonal(b[0]), 1e-12)
    res = []
    for src, dst in ((a, b), (b, a)):
        pts = surface_samples(src[0], src[1], samples)
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts))
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(dst[0], np.float64), face_matrix=np.asarray(dst[1], np.int32)))
        res.append(ms.get_hausdorff_distance(sampledmesh=0, targetmesh=1, samplevert=True, sampleface=False, sampleedge=False,
                                             samplenum=len(pts), maxdist=pymeshlab.PureValue(2.0 * diag)))
    ab, ba = res
    return {"max": float(max(ab["max"], ba["max"])), "mean": float(max(ab["mean"], ba["mean"])),
            "a_to_b": float(ab["max"]), "b_to_a": float(ba["max"])}
