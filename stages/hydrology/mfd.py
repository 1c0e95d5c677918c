"""Multiple flow directions (Quinn et al. 1991 / Freeman 1991): each cell
sends its flow to every strictly lower neighbour of the routing surface in
proportion to (slope^p * contour length). The routing surface strictly
decreases along every edge, so the graph is acyclic; accumulation runs in
Kahn frontiers on the host (numpy, float64, a fixed order: deterministic).
"""
from __future__ import annotations

import numpy as np

from worldlib.flow import reference as ref


def edges(z: np.ndarray, kind: np.ndarray, dx: float, p: float):
    """(src, dst, fraction) of the MFD graph on surface z."""
    rows, cols = z.shape
    n = rows * cols
    zp = np.pad(z.astype(np.float64), 1, constant_values=np.inf)
    idx = np.arange(n).reshape(rows, cols)
    interior = kind == ref.INTERIOR
    srcs, dsts, ws = [], [], []
    for k in range(8):
        dr, dc = ref.DR[k], ref.DC[k]
        zn = zp[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]
        dist = dx * (np.sqrt(2.0) if k & 1 else 1.0)
        contour = dx * (0.354 if k & 1 else 0.5)
        with np.errstate(invalid="ignore"):
            s = (z - zn) / dist
        ok = interior & (s > 0)
        srcs.append(idx[ok])
        dsts.append(idx[ok] + dr * cols + dc)
        ws.append(s[ok] ** p * contour)
    src, dst, w = np.concatenate(srcs), np.concatenate(dsts), np.concatenate(ws)
    tot = np.bincount(src, weights=w, minlength=n)
    return src, dst, w / tot[src]


def accumulate(z: np.ndarray, kind: np.ndarray, dx: float, p: float, weights: np.ndarray) -> np.ndarray:
    """MFD accumulation of `weights` (float64)."""
    rows, cols = z.shape
    n = rows * cols
    src, dst, frac = edges(z, kind, dx, p)
    order = np.argsort(src, kind="stable")
    src, dst, frac = src[order], dst[order], frac[order]
    start = np.searchsorted(src, np.arange(n + 1))
    acc = np.asarray(weights, np.float64).ravel().copy()
    deg = np.bincount(dst, minlength=n)
    front = np.flatnonzero(deg == 0)
    while front.size:
        cnt = start[front + 1] - start[front]
        e = np.repeat(start[front], cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        if not e.size:
            break
        np.add.at(acc, dst[e], acc[src[e]] * frac[e])
        np.subtract.at(deg, dst[e], 1)
        t = np.unique(dst[e])
        front = t[deg[t] == 0]
    return acc.reshape(rows, cols)
