"""A bounding volume hierarchy over triangles, built in numpy, for the
renderer's kernel.

Median split on the longest axis of the node's centroid bounds, built one
level at a time: every node of a level is split by one lexsort over
(node, centroid along its axis), so the build is a few dozen vectorised
passes and not one Python call per node. Leaves hold at most `leaf_size`
triangles. Children of a node are stored next to each other.

Node record (8 float32): bmin.xyz, first (int bits), bmax.xyz, count (int
bits): count = 0 marks an inner node whose children are first and first+1;
count > 0 a leaf of triangles order[first .. first+count-1].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BVH:
    nodes: np.ndarray  # (n_nodes, 8) float32 (ints stored bitwise)
    order: np.ndarray  # (m,) int32: triangle ids in leaf order

    @property
    def depth_bound(self) -> int:
        return int(self.nodes.shape[0]).bit_length() + 2


def build(positions: np.ndarray, triangles: np.ndarray, leaf_size: int = 4) -> BVH:
    tri = np.asarray(positions, np.float32)[np.asarray(triangles, np.int64)]
    m = len(tri)
    if m == 0:
        nodes = np.zeros((1, 8), np.float32)
        nodes[0, 0:3], nodes[0, 4:7] = 1.0, -1.0  # an empty box no ray enters
        return BVH(nodes, np.zeros(0, np.int32))
    lo, hi = tri.min(1), tri.max(1)
    cen = 0.5 * (lo.astype(np.float64) + hi)
    order = np.arange(m, dtype=np.int64)
    # node table grown level by level: start, count, first child
    starts, counts, child, depth = [0], [m], [-1], [0]
    level = [0]
    while level:
        lv = np.asarray(level)
        st = np.asarray(starts)[lv]
        ct = np.asarray(counts)[lv]
        split = lv[ct > leaf_size]
        if len(split) == 0:
            break
        s_st = np.asarray(starts)[split]
        s_ct = np.asarray(counts)[split]
        # element -> its node among the split ones
        idx = np.repeat(np.arange(len(split)), s_ct)
        pos = np.arange(s_ct.sum()) - np.repeat(np.cumsum(s_ct) - s_ct, s_ct) + np.repeat(s_st, s_ct)
        c = cen[order[pos]]
        bounds_lo = np.full((len(split), 3), np.inf)
        bounds_hi = np.full((len(split), 3), -np.inf)
        np.minimum.at(bounds_lo, idx, c)
        np.maximum.at(bounds_hi, idx, c)
        axis = np.argmax(bounds_hi - bounds_lo, axis=1)
        key = c[np.arange(len(c)), axis[idx]]
        perm = np.lexsort((order[pos], key, idx))  # ties by triangle id: deterministic
        order[pos] = order[pos][perm]
        new_level = []
        for j, node in enumerate(split.tolist()):
            a, n = int(s_st[j]), int(s_ct[j])
            half = n // 2
            child[node] = len(starts)
            starts += [a, a + half]
            counts += [half, n - half]
            child += [-1, -1]
            depth += [depth[node] + 1] * 2
            new_level += [len(starts) - 2, len(starts) - 1]
        level = new_level
    starts_a, counts_a, child_a = np.asarray(starts), np.asarray(counts), np.asarray(child)
    n_nodes = len(starts_a)
    # bounds: leaves from their triangles, inner nodes from their children (bottom up: children have larger ids)
    blo = np.full((n_nodes, 3), np.inf, np.float32)
    bhi = np.full((n_nodes, 3), -np.inf, np.float32)
    leaf = child_a < 0
    lid = np.nonzero(leaf)[0]
    elem_node = np.repeat(lid, counts_a[lid])
    elem_pos = np.arange(counts_a[lid].sum()) - np.repeat(np.cumsum(counts_a[lid]) - counts_a[lid], counts_a[lid]) + \
        np.repeat(starts_a[lid], counts_a[lid])
    np.minimum.at(blo, elem_node, lo[order[elem_pos]])
    np.maximum.at(bhi, elem_node, hi[order[elem_pos]])
    depth_a = np.asarray(depth)
    for d in range(int(depth_a.max()), -1, -1):
        inner = np.nonzero(~leaf & (depth_a == d))[0]
        c0 = child_a[inner]
        blo[inner] = np.minimum(blo[c0], blo[c0 + 1])
        bhi[inner] = np.maximum(bhi[c0], bhi[c0 + 1])
    nodes = np.zeros((n_nodes, 8), np.float32)
    nodes[:, 0:3], nodes[:, 4:7] = blo, bhi
    ints = nodes.view(np.int32)
    ints[:, 3] = np.where(leaf, starts_a, child_a)
    ints[:, 7] = np.where(leaf, counts_a, 0)
    return BVH(nodes, order.astype(np.int32))
