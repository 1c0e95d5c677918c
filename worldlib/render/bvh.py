"""A bounding volume hierarchy over triangles, built in numpy, for the
renderer's kernel.

Binned surface-area heuristic (Wald 2007): a node's triangles are put in
BINS bins (half as many at levels of small nodes) by centroid along each
axis, and of the bins - 1 planes per axis the one with the least expected
cost (child box area x triangle count, summed) is taken; a node of at most
`leaf_size` triangles is a leaf (the kernel tests a leaf's four triangle
slots at once, so a full leaf costs no more than a single triangle). Plant
assets are thousands of crossed cards, twigs and needles overlapping in one
crown: a median split makes children whose boxes both span the crown, the
SAH makes tight ones, and every ray visits fewer nodes.

The build runs one level of the tree at a time: every node of a level is
binned, costed and partitioned by a few vectorised passes over all of the
level's triangles (a stable sort keeps the order, and so the tree,
deterministic), never one Python call per node. Nodes deeper than
MEDIAN_DEPTH are split at their median triangle instead, so the depth stays
bounded whatever the scene (the kernel's stack).

The binary tree (BVH) is then collapsed to four children per node (widen,
WideBVH), the layout the kernel reads. Binary node record (8 float32):
bmin.xyz, first (int bits), bmax.xyz, count (int bits): count = 0 marks an
inner node whose children are first and first+1; count > 0 a leaf of
triangles order[first .. first+count-1].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BINS = 16
MEDIAN_DEPTH = 30  # nodes this deep split at the median: 30 + log2(triangles) levels stay within the kernel's stack


@dataclass(frozen=True)
class BVH:
    nodes: np.ndarray  # (n_nodes, 8) float32 (ints stored bitwise)
    order: np.ndarray  # (m,) int32: triangle ids in leaf order
    depth: int = 0  # levels below the root

    @property
    def depth_bound(self) -> int:
        return self.depth + 1


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half the surface area of boxes whose coordinates are the first axis."""
    e = np.maximum(hi - lo, 0.0)
    return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]


def _sweep_areas(blo: np.ndarray, bhi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half areas of the boxes of bins [0, p) and [p, BINS) for p = 1 .. BINS-1
    (blo, bhi: (3, BINS, ...) per-bin bounds, +-inf where empty)."""
    n = blo.shape[1]
    left = np.empty((n - 1,) + blo.shape[2:], np.float32)
    right = np.empty_like(left)
    lo, hi = blo[:, 0].copy(), bhi[:, 0].copy()
    for p in range(1, n):
        left[p - 1] = _half_area(lo, hi)
        np.minimum(lo, blo[:, p], out=lo)
        np.maximum(hi, bhi[:, p], out=hi)
    lo, hi = blo[:, n - 1].copy(), bhi[:, n - 1].copy()
    for p in range(n - 1, 0, -1):
        right[p - 1] = _half_area(lo, hi)
        np.minimum(lo, blo[:, p - 1], out=lo)
        np.maximum(hi, bhi[:, p - 1], out=hi)
    return left, right


def _segments(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ranges [starts, starts + counts) in increasing order: each
    element's range index and its position."""
    idx = np.repeat(np.arange(len(starts)), counts)
    pos = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(starts, counts)
    return idx, pos


def build(positions: np.ndarray, triangles: np.ndarray, leaf_size: int = 4) -> BVH:
    tri = np.asarray(positions, np.float32)[np.asarray(triangles, np.int64)]
    m = len(tri)
    if m == 0:
        nodes = np.zeros((1, 8), np.float32)
        nodes[0, 0:3], nodes[0, 4:7] = 1.0, -1.0  # an empty box no ray enters
        return BVH(nodes, np.zeros(0, np.int32))
    lo, hi = tri.min(1), tri.max(1)
    cen = 0.5 * (lo + hi)
    order = np.arange(m, dtype=np.int64)
    # node table, grown a level at a time; a level's nodes are in increasing start order
    starts, counts = [np.array([0])], [np.array([m])]
    level_ids, level_st, level_ct = np.array([0]), np.array([0]), np.array([m])
    n_nodes, depth = 1, 0
    child_of = {}  # level -> (split node ids, their first child)
    while len(level_ids):
        split, left_n = _split_level(level_st, level_ct, cen, lo, hi, order, depth, leaf_size)
        # children of this level's split nodes, two by two, in the level's order
        s_ids = level_ids[split]
        first_child = n_nodes + 2 * np.arange(len(s_ids))
        child_of[depth] = (s_ids, first_child)
        n_nodes += 2 * len(s_ids)
        st, ln, ct = level_st[split], left_n[split], level_ct[split]
        new_st = np.stack([st, st + ln], 1).ravel()
        new_ct = np.stack([ln, ct - ln], 1).ravel()
        starts.append(new_st)
        counts.append(new_ct)
        level_ids = np.arange(first_child[0], n_nodes) if len(s_ids) else np.zeros(0, np.int64)
        level_st, level_ct = new_st, new_ct
        depth += 1
    nodes = _node_table(lo, hi, order, np.concatenate(starts), np.concatenate(counts), child_of, n_nodes)
    return BVH(nodes, order.astype(np.int32), depth - 1)


def _split_level(level_st: np.ndarray, level_ct: np.ndarray, cen: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 order: np.ndarray, depth: int, leaf_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Split one level's nodes (triangles order[start:start + count]): by the
    SAH's binned plane, or at the median below MEDIAN_DEPTH or where no plane
    separates. Reorders `order` in place, each node's left side first;
    returns which nodes split and their left sides' triangle counts."""
    idx, pos = _segments(level_st, level_ct)
    tris = order[pos]
    c = cen[tris]
    k = len(level_ct)
    offsets = np.cumsum(level_ct) - level_ct
    cmin = np.minimum.reduceat(c, offsets, axis=0)
    cmax = np.maximum.reduceat(c, offsets, axis=0)
    extent = cmax - cmin
    # fine bins while nodes are large; deep levels hold many small nodes, where the per-bin arrays
    # (nodes x bins) outweigh the triangles and coarse bins choose nearly as well
    bins = BINS if level_ct.mean() > 64 else BINS // 2
    # bin of every triangle along every axis (3 columns)
    scale = np.where(extent > 0, bins / np.where(extent > 0, extent, 1.0), 0.0)
    b = np.clip(((c - cmin[idx]) * scale[idx]).astype(np.int64), 0, bins - 1)
    best_cost, axis, plane = _sah_planes(b, idx, lo[tris], hi[tris], k, bins)
    sah = np.isfinite(best_cost) & (level_ct > leaf_size)  # a leaf costs one 4-wide test: fill it
    if depth >= MEDIAN_DEPTH:
        sah[:] = False
    median = ~sah & (level_ct > leaf_size)
    # partition: SAH nodes by their plane, median nodes by the longest centroid axis at the middle triangle
    side = np.zeros(len(pos), np.int64)
    s_el = sah[idx]
    side[s_el] = (b[s_el, axis[idx[s_el]]] >= plane[idx[s_el]]).astype(np.int64)
    _median_sides(side, median, idx, tris, c, extent, level_ct)
    key2 = idx * 2 + side
    perm = np.argsort(key2, kind="stable")
    order[pos] = tris[perm]
    left_n = np.bincount(idx, weights=(side == 0), minlength=k).astype(np.int64)
    return sah | median, left_n


def _sah_planes(b: np.ndarray, idx: np.ndarray, lo_t: np.ndarray, hi_t: np.ndarray, k: int,
                bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per node the cheapest binned plane by the surface area heuristic:
    its cost (inf where no plane has triangles on both sides), axis and
    plane (left side = bins [0, plane))."""
    # per (coordinate, bin, node, axis) triangle bounds: 1-D scatters (numpy's fast path)
    blo = np.full((3, bins * k * 3), np.inf, np.float32)
    bhi = np.full((3, bins * k * 3), -np.inf, np.float32)
    keys = (b * k + idx[:, None]) * 3 + np.arange(3)  # (n, axis)
    for ax in range(3):
        for co in range(3):
            np.minimum.at(blo[co], keys[:, ax], lo_t[:, co])
            np.maximum.at(bhi[co], keys[:, ax], hi_t[:, co])
    cnt = np.bincount(keys.ravel(), minlength=bins * k * 3).reshape(bins, k, 3)
    blo, bhi = blo.reshape(3, bins, k, 3), bhi.reshape(3, bins, k, 3)
    # sweep: left side = bins [0, p), right side = bins [p, bins), p = 1 .. bins-1
    l_cnt = np.cumsum(cnt, axis=0)[:-1]
    r_cnt = np.cumsum(cnt[::-1], axis=0)[::-1][1:]
    l_area, r_area = _sweep_areas(blo, bhi)
    cost = np.where((l_cnt > 0) & (r_cnt > 0), l_area * l_cnt + r_area * r_cnt, np.inf)  # (plane, node, axis)
    cost = cost.transpose(1, 2, 0).reshape(k, -1)
    best = np.argmin(cost, axis=1)  # first minimum: deterministic
    best_cost = cost[np.arange(k), best]
    return best_cost, best // (bins - 1), best % (bins - 1) + 1


def _median_sides(side: np.ndarray, median: np.ndarray, idx: np.ndarray, tris: np.ndarray, c: np.ndarray,
                  extent: np.ndarray, level_ct: np.ndarray) -> None:
    """Into `side` (changed): the lower half of each median node's triangles
    along its longest centroid axis (ties by triangle id) goes left (0)."""
    m_el = median[idx]
    if not m_el.any():
        return
    k = len(level_ct)
    sub = np.nonzero(m_el)[0]
    along = c[sub, np.argmax(extent, axis=1)[idx[sub]]]
    ranked = sub[np.lexsort((tris[sub], along, idx[sub]))]  # grouped by node, increasing idx
    med = np.nonzero(median)[0]
    first_rank = np.zeros(k, np.int64)
    first_rank[med] = np.cumsum(level_ct[med]) - level_ct[med]
    local = np.empty(len(idx), np.int64)
    local[ranked] = np.arange(len(ranked)) - first_rank[idx[ranked]]
    side[sub] = (local[sub] >= level_ct[idx[sub]] // 2).astype(np.int64)


def _node_table(lo: np.ndarray, hi: np.ndarray, order: np.ndarray, starts_a: np.ndarray, counts_a: np.ndarray,
                child_of: dict, n_nodes: int) -> np.ndarray:
    """(n_nodes, 8) float32: bounds min, then the first triangle (leaf) or
    child (inner node) as int32; bounds max, then the triangle count (0 inner)."""
    child_a = np.full(n_nodes, -1, np.int64)
    for s_ids, first_child in child_of.values():
        child_a[s_ids] = first_child
    leaf = child_a < 0
    # bounds: leaves from their triangles, inner nodes from their children (bottom up: children have larger ids)
    blo = np.full((n_nodes, 3), np.inf, np.float32)
    bhi = np.full((n_nodes, 3), -np.inf, np.float32)
    lid = np.nonzero(leaf)[0]
    lid = lid[np.argsort(starts_a[lid], kind="stable")]
    _, elem_pos = _segments(starts_a[lid], counts_a[lid])
    off = np.cumsum(counts_a[lid]) - counts_a[lid]
    blo[lid] = np.minimum.reduceat(lo[order[elem_pos]], off, axis=0)
    bhi[lid] = np.maximum.reduceat(hi[order[elem_pos]], off, axis=0)
    for d in sorted(child_of, reverse=True):
        s_ids, c0 = child_of[d]
        blo[s_ids] = np.minimum(blo[c0], blo[c0 + 1])
        bhi[s_ids] = np.maximum(bhi[c0], bhi[c0 + 1])
    nodes = np.zeros((n_nodes, 8), np.float32)
    nodes[:, 0:3], nodes[:, 4:7] = blo, bhi
    ints = nodes.view(np.int32)
    ints[:, 3] = np.where(leaf, starts_a, child_a)
    ints[:, 7] = np.where(leaf, counts_a, 0)
    return nodes


@dataclass(frozen=True)
class WideBVH:
    """The binary tree collapsed to four children per node, for the kernel:
    one ray tests a node's four boxes with float4 operations.

    Node record (32 float32, 128 bytes): min x, min y, min z, max x, max y,
    max z of the four children (a float4 each, child per lane), then per
    lane `ref` and `count` (int bits): count = 0 an inner child (ref: its
    node), count > 0 a leaf (ref: its block of four triangle slots, the
    kernel tests the four at once; slots[4 ref .. 4 ref + 3], count of them
    used), count < 0 no child. Node 0 is the root."""

    nodes: np.ndarray  # (n, 32) float32
    order: np.ndarray  # (m,) int32
    depth: int  # levels below the root
    slots: np.ndarray  # (4 b,) int64: the scene triangle in each of the leaves' 4-triangle blocks, -1 none


def widen(tree: BVH) -> WideBVH:
    """Each wide node starts from a binary node's two children, and twice the
    inner child of largest box area gives way to its two children (Wald et
    al. 2008): four lanes wherever the tree has them. A breadth-first pass,
    one level of wide nodes at a time."""
    ints = tree.nodes.view(np.int32)
    child, count = ints[:, 3].astype(np.int64), ints[:, 7].astype(np.int64)
    inner = count == 0
    records = []
    level = np.array([0])  # binary nodes that become wide nodes
    if len(tree.order) == 0:  # no triangles: a root without children
        nodes = np.zeros((1, 32), np.float32)
        nodes[:, 0:12], nodes[:, 12:24] = np.inf, -np.inf
        nodes.view(np.int32)[:, 28:32] = -1
        return WideBVH(nodes, tree.order, 0, np.full(4, -1, np.int64))
    if not inner[0]:  # a single leaf (or the empty box): a root with one lane
        lanes = np.array([[0, -1, -1, -1]])
        records.append(lanes)
        level = np.zeros(0, np.int64)
    n_wide, depth = (1 if len(records) else 0), 0
    lo, hi = tree.nodes[:, 0:3].astype(np.float64), tree.nodes[:, 4:7].astype(np.float64)
    area = _half_area(lo.T, hi.T)
    while len(level):
        lanes = np.full((len(level), 4), -1, np.int64)
        lanes[:, 0], lanes[:, 1] = child[level], child[level] + 1
        for free in (2, 3):  # the inner lane of largest box area gives way to its two children
            src = np.maximum(lanes, 0)
            score = np.where((lanes >= 0) & inner[src], area[src], -1.0)
            pick = np.argmax(score, axis=1)
            rows = np.nonzero(score[np.arange(len(lanes)), pick] >= 0)[0]
            node = lanes[rows, pick[rows]]
            lanes[rows, pick[rows]] = child[node]
            lanes[rows, free] = child[node] + 1
        records.append(lanes)
        n_wide += len(level)
        nxt = lanes[(lanes >= 0) & inner[np.maximum(lanes, 0)]]
        level = nxt
        depth += 1
    lanes = np.concatenate(records)  # (n_wide, 4) binary node per lane, -1 none
    valid = lanes >= 0
    src = np.maximum(lanes, 0)
    lane_inner = valid & inner[src]
    # wide ids of inner lanes: breadth-first, in lane order (as they were queued)
    wide_id = np.full(lanes.shape, -1, np.int64)
    wide_id[lane_inner] = np.arange(1, 1 + int(lane_inner.sum()))
    nodes = np.zeros((len(lanes), 32), np.float32)
    box = tree.nodes[src]  # (n, 4, 8)
    for c in range(3):
        nodes[:, 4 * c:4 * c + 4] = np.where(valid, box[..., c], np.inf)
        nodes[:, 12 + 4 * c:16 + 4 * c] = np.where(valid, box[..., 4 + c], -np.inf)
    # leaves: one block of four slots each, in leaf order
    if count.max() > 4:
        raise ValueError("wide BVH leaves hold at most 4 triangles")
    leaves = np.nonzero(~inner)[0]
    leaves = leaves[np.argsort(child[leaves], kind="stable")]
    block = np.zeros(len(count), np.int64)
    block[leaves] = np.arange(len(leaves))
    slots = np.full((len(leaves), 4), -1, np.int64)
    for i in range(4):
        has = count[leaves] > i
        slots[has, i] = tree.order[child[leaves[has]] + i]
    ni = nodes.view(np.int32)
    ni[:, 24:28] = np.where(lane_inner, wide_id, np.where(valid, block[src], 0))
    ni[:, 28:32] = np.where(valid, np.where(lane_inner, 0, count[src]), -1)
    return WideBVH(nodes, tree.order, max(depth - 1, 0), slots.ravel())
