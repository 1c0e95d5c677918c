"""The volume kernels in plain numpy (float64), for small meshes and grids:
the same sample positions, texel lookups, voxel indices, marching steps and
sums as kernels.cl, so the tests compare the two closely."""
from __future__ import annotations

import numpy as np

from worldlib.volumes.dense import LEAF_PROJECTION

from .samples import Grid3, Samples, SampleTable


def surface_samples(table: SampleTable, grid: Grid3, textures: np.ndarray, alpha_threshold: float) -> Samples:
    """kernels.cl surface_samples, triangle by triangle."""
    n = int(table.offset[-1]) if len(table.offset) else 0
    voxel = np.full(n, -1, np.int32)
    weight, rgb, normal = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3))
    _, th, tw, _ = textures.shape
    for t in range(len(table.m)):
        m = int(table.m[t])
        p, nr, w = table.pos[t].reshape(3, 3), table.nrm[t].reshape(3, 3), table.uv[t].reshape(3, 2)
        e1, e2 = p[1] - p[0], p[2] - p[0]
        c = np.array([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]])
        area = 0.5 * np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
        wt = area / (float(m) * float(m))
        k = int(table.tex[t])
        o = int(table.offset[t])
        for up in (1, 0):
            shift = 1.0 / 3.0 if up else 2.0 / 3.0
            rows = m if up else m - 1
            for i in range(rows):
                for j in range(rows - i):
                    b1, b2 = (i + shift) / m, (j + shift) / m
                    b0 = 1.0 - b1 - b2
                    col = table.tint[t].copy()
                    keep = True
                    if k >= 0:
                        u = b0 * w[0, 0] + b1 * w[1, 0] + b2 * w[2, 0]
                        v = b0 * w[0, 1] + b1 * w[1, 1] + b2 * w[2, 1]
                        fu, fv = u - np.floor(u), v - np.floor(v)
                        x = min(int(fu * tw), tw - 1)
                        y = min(int((1.0 - fv) * th), th - 1)
                        texel = textures[k, y, x].astype(np.float64)
                        col = col * texel[:3]
                        keep = texel[3] >= np.float64(np.float32(alpha_threshold))
                    q = b0 * p[0] + b1 * p[1] + b2 * p[2]
                    idx = [min(max(int(np.floor((q[a] - grid.origin[a]) / grid.voxel)), 0), grid.shape[a] - 1)
                           for a in range(3)]
                    qn = b0 * nr[0] + b1 * nr[1] + b2 * nr[2]
                    ql = np.sqrt(qn[0] * qn[0] + qn[1] * qn[1] + qn[2] * qn[2])
                    if ql > 0:
                        qn = qn / ql
                    voxel[o] = (idx[2] * grid.shape[1] + idx[1]) * grid.shape[0] + idx[0] if keep else -1
                    weight[o] = wt if keep else 0.0
                    rgb[o], normal[o] = col, qn
                    o += 1
    return Samples(voxel, weight, rgb, normal)


def _trilinear(g: np.ndarray, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """g (nz, ny, nx, c): trilinear samples at voxel coordinates, zero outside."""
    nz, ny, nx = g.shape[:3]
    fu, fv, fw = np.floor(u), np.floor(v), np.floor(w)
    i0, j0, k0 = fu.astype(np.int64), fv.astype(np.int64), fw.astype(np.int64)
    a, b, d = u - fu, v - fv, w - fw
    s = np.zeros((len(u), g.shape[3]))
    for dk in (0, 1):
        for dj in (0, 1):
            for di in (0, 1):
                i, j, k = i0 + di, j0 + dj, k0 + dk
                ok = (i >= 0) & (j >= 0) & (k >= 0) & (i < nx) & (j < ny) & (k < nz)
                wt = (a if di else 1 - a) * (b if dj else 1 - b) * (d if dk else 1 - d)
                val = np.zeros((len(u), g.shape[3]))
                val[ok] = g[k[ok], j[ok], i[ok]].astype(np.float64)
                s += np.where(ok, wt, 0.0)[:, None] * val
    return s


def composite(camera_record: np.ndarray, width: int, height: int, grid: np.ndarray, origin, voxel: float,
              step: float) -> tuple[np.ndarray, np.ndarray]:
    """kernels.cl composite for every pixel at once: (alpha (H, W), premultiplied rgb (H, W, 3))."""
    cam = camera_record.astype(np.float64)
    py, px = np.mgrid[0:height, 0:width]
    x = (2.0 * ((px.ravel() + 0.5) / width) - 1.0)[:, None]
    y = (1.0 - 2.0 * ((py.ravel() + 0.5) / height))[:, None]
    if camera_record[12] > 0.5:
        o = cam[0:3] + x * cam[6:9] + y * cam[9:12]
        d = np.broadcast_to(cam[3:6], o.shape).copy()
    else:
        o = np.broadcast_to(cam[0:3], (len(x), 3)).copy()
        d = cam[3:6] + x * cam[6:9] + y * cam[9:12]
    d = d / np.sqrt((d * d).sum(1))[:, None]
    nz, ny, nx = grid.shape[:3]
    lo = np.asarray(origin, np.float64)
    n = np.array([nx, ny, nz], np.float64)
    t0, t1 = np.zeros(len(o)), np.full(len(o), np.inf)
    for i in range(3):
        hi = lo[i] + n[i] * voxel
        zero = d[:, i] == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo[i] - o[:, i]) / d[:, i], (hi - o[:, i]) / d[:, i]
        ta, tb = np.minimum(ta, tb), np.maximum(ta, tb)
        t0 = np.where(zero, t0, np.maximum(t0, ta))
        t1 = np.where(zero, np.where((o[:, i] < lo[i]) | (o[:, i] > hi), -1.0, t1), np.minimum(t1, tb))
    T, rgb = np.ones(len(o)), np.zeros((len(o), 3))
    t = t0 + 0.5 * step
    while True:
        live = (t < t1) & (T >= 1e-4)
        if not live.any():
            break
        idx = np.nonzero(live)[0]
        p = o[idx] + t[idx, None] * d[idx]
        uvw = (p - lo) / voxel - 0.5
        s = _trilinear(grid, uvw[:, 0], uvw[:, 1], uvw[:, 2])
        dens, sn = s[:, 3], s[:, 4:7]
        hit = dens > 0
        sigma = np.maximum(dens + np.abs((sn * d[idx]).sum(1)) - LEAF_PROJECTION * np.sqrt((sn * sn).sum(1)), 0.0)
        a = np.where(hit, 1.0 - np.exp(-sigma * step), 0.0)
        k = np.where(hit, T[idx] * a / np.where(hit, dens, 1.0), 0.0)
        rgb[idx] += k[:, None] * s[:, 0:3]
        T[idx] *= 1.0 - a
        t[idx] += step
    alpha = (1.0 - T).astype(np.float32).reshape(height, width)
    return alpha, rgb.astype(np.float32).reshape(height, width, 3)
