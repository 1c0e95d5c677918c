"""Host side of kernels.cl: depression filling, D8 directions, D8
accumulation and the wetness map on the OpenCL device `env` (a
pipeline.opencl.CL, every function's first argument).

Tile sizes are algorithm constants (not work-group sizes): one work-item
runs one tile sequentially, which is what a CPU device does best and what
keeps every result exact (min/max and integer sums only). The work-group
size (`local`) only changes scheduling, never a bit of the result.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import reference as ref

KERNELS = Path(__file__).with_name("kernels.cl")
FILL_TILE = 64
FILL_PLAIN_TILE = 128  # fewer perimeter cells for fill_levels' serial flood
ACC_TILE = 64
ACC_TILE_MAX = 128  # the tile's scratch lives in private memory: about 19 B per cell
FILL_TILE_MAX = 128  # the tile and its halo live in private memory: 8 B (fill_local 10 B and a hash) per cell


def _program(env, acc_type: str = "uint", extra: tuple[str, ...] = ()):
    from pipeline.opencl import load_program

    return load_program(env, KERNELS, (f"-DACC_T={acc_type}", *extra))


def _buf(env, a: np.ndarray, write: bool = False):
    from pipeline.clhost import Buffers

    # read-only inputs are used in place (no copy on a CPU device); the
    # buffer keeps a reference to the array, which nobody writes meanwhile
    return Buffers(env).arr(a, write=write, in_place=not write)


def _ceil(n: int, local: int | None) -> tuple[int, ...]:
    from pipeline.opencl import global_size

    return global_size((n,), (local,) if local else None)


def fill(env, h: np.ndarray, kind: np.ndarray, eps: bool, tile: int | None = None, local: int | None = None,
         stats: dict | None = None) -> np.ndarray:
    """The Priority-Flood fill (eps: Priority-Flood+epsilon) of canonical
    float32 heights on the OpenCL device `env` (pipeline.opencl.CL); no-data
    cells come back as NaN. The plain fill runs in three phases (kernels.cl
    fill_local, fill_levels, fill_combine; tiles of FILL_PLAIN_TILE), the
    epsilon fill by relaxation (fill_tiles, tiles of FILL_TILE): the
    epsilon's steps add up along a path, which the plain fill's spill levels
    cannot carry."""
    import pyopencl as cl

    tile = tile or (FILL_TILE if eps else FILL_PLAIN_TILE)
    if not 1 <= tile <= FILL_TILE_MAX:
        raise ValueError(f"fill tile {tile} outside 1..{FILL_TILE_MAX}")
    h = np.ascontiguousarray(h, np.float32)
    if not eps:
        for hcap in (_fill_hash(tile), 4 * _fill_hash(tile)):  # a tile with more label pairs: a larger hash
            W = _fill_plain(env, h, kind, tile, local, stats, hcap=hcap)
            if W is not None:
                return W
    prg = _program(env, extra=(f"-DFILL_T={tile}",))
    rows, cols = h.shape
    tiles_x, tiles_y = -(-cols // tile), -(-rows // tile)
    nt = tiles_x * tiles_y
    W0 = np.where(kind == ref.INTERIOR, np.float32(np.inf), np.where(kind == ref.EDGE, h, np.float32(-np.inf))).astype(np.float32)
    d_h, d_kind = _buf(env, h), _buf(env, kind)
    d_W, d_pub = _buf(env, W0, True), _buf(env, W0, True)
    active = np.ones(nt, np.uint8)
    changed = np.zeros(nt, np.uint8)
    d_active, d_changed = _buf(env, active, True), _buf(env, changed, True)
    k_fill = cl.Kernel(prg, "fill_tiles")
    k_pub = cl.Kernel(prg, "publish_tiles")
    i32 = np.int32
    k_fill.set_args(d_h, d_kind, d_W, d_pub, d_active, d_changed, i32(rows), i32(cols), i32(tile), i32(tiles_x),
                    i32(nt), i32(1 if eps else 0), i32(4 * tile * tile))
    k_pub.set_args(d_W, d_pub, d_changed, i32(rows), i32(cols), i32(tile), i32(tiles_x), i32(nt))
    # one tile per work-group unless asked otherwise: PoCL may keep the
    # private copies of every work-item of a group alive at once
    local = local or 1
    g = _ceil(nt, local)
    lw = (local,)
    passes = tiles_run = 0
    while True:
        cl.enqueue_nd_range_kernel(env.queue, k_fill, g, lw)
        cl.enqueue_copy(env.queue, changed, d_changed)
        passes += 1
        tiles_run += int(active.sum())
        if not changed.any():
            break
        cl.enqueue_nd_range_kernel(env.queue, k_pub, g, lw)
        c2 = changed.reshape(tiles_y, tiles_x).astype(bool)
        # the 8-neighbourhood dilation of c2, but a tile whose own cells changed is already converged
        dil = np.zeros_like(c2)
        p = np.pad(c2, 1)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr or dc:
                    dil |= p[1 + dr:1 + dr + tiles_y, 1 + dc:1 + dc + tiles_x]
        active[:] = (dil | c2).ravel()  # itself too: the sweep cap may have stopped it early
        cl.enqueue_copy(env.queue, d_active, active)
    W = np.empty_like(h)
    cl.enqueue_copy(env.queue, W, d_W)
    W[kind == ref.NODATA] = np.nan
    if stats is not None:
        stats.update(passes=passes, tiles_run=tiles_run, tiles=nt)
    return W


def _fill_hash(tile: int) -> int:
    """Slots of fill_local's label-pair hash: a power of two, 64 per tile side
    (the raw 8192^2 default world needs more than 32 in some tiles of 128^2)."""
    return 1 << (64 * tile - 1).bit_length()


def _fill_plain(env, h: np.ndarray, kind: np.ndarray, tile: int, local: int | None, stats: dict | None,
                parts: dict | None = None, hcap: int | None = None):
    """The plain fill by kernels.cl's three phases (fill_local, fill_levels,
    fill_combine); None when a tile's label pairs overflow its hash (the
    caller then relaxes instead). parts (tests): gets each phase's output,
    Wloc, label and level."""
    import pyopencl as cl

    hcap = hcap or _fill_hash(tile)
    prg = _program(env, extra=(f"-DFILL_T={tile}", f"-DFILL_HCAP={hcap}"))
    rows, cols = h.shape
    tiles_x, tiles_y = -(-cols // tile), -(-rows // tile)
    nt, pmax, n = tiles_x * tiles_y, 4 * tile, rows * cols
    mf = cl.mem_flags
    d_h, d_kind = _buf(env, h), _buf(env, kind)
    W = np.empty_like(h)  # Wloc, then the fill in place: the device writes it directly (no copy on a CPU device)
    d_wloc = cl.Buffer(env.ctx, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=W)
    d_label = cl.Buffer(env.ctx, mf.READ_WRITE, n * 4)
    off = np.empty((nt, pmax + 1), np.int32)
    d_off = _buf(env, off, True)
    d_adj_n = cl.Buffer(env.ctx, mf.READ_WRITE, nt * 2 * hcap * 2)
    d_adj_w = cl.Buffer(env.ctx, mf.READ_WRITE, nt * 2 * hcap * 4)
    d_init, d_level = (cl.Buffer(env.ctx, mf.READ_WRITE, nt * pmax * 4) for _ in range(2))
    d_xoff = cl.Buffer(env.ctx, mf.READ_WRITE, nt * (pmax + 1) * 4)
    d_xn, d_xw = (cl.Buffer(env.ctx, mf.READ_WRITE, nt * 3 * pmax * 4) for _ in range(2))  # edges to other tiles
    overflow = np.zeros(nt, np.uint8)
    d_over = _buf(env, overflow, True)
    i32 = np.int32
    geo = (i32(rows), i32(cols), i32(tiles_x), i32(nt))
    local = local or 1  # private copies of a tile per work-item: one per group
    k1 = cl.Kernel(prg, "fill_local")
    k1.set_args(d_h, d_kind, d_wloc, d_label, d_off, d_adj_n, d_adj_w, d_init, d_xoff, d_xn, d_xw, d_over, *geo)
    cl.enqueue_nd_range_kernel(env.queue, k1, _ceil(nt, local), (local,))
    cl.enqueue_copy(env.queue, overflow, d_over)
    cl.enqueue_copy(env.queue, off, d_off)
    if overflow.any():
        return None
    heap = nt * pmax * 4 + int(off[:, -1].astype(np.int64).sum())  # nodes, cross-tile and tile edges
    d_hk, d_hi = (cl.Buffer(env.ctx, mf.READ_WRITE, max(heap, 1) * 4) for _ in range(2))
    k2 = cl.Kernel(prg, "fill_levels")
    k2.set_args(d_off, d_adj_n, d_adj_w, d_xoff, d_xn, d_xw, d_init, d_level, d_hk, d_hi, i32(nt))
    cl.enqueue_nd_range_kernel(env.queue, k2, (1,), None)
    if parts is not None:
        for name, buf, dt, size in (("Wloc", d_wloc, np.float32, n), ("label", d_label, np.int32, n),
                                    ("level", d_level, np.float32, nt * pmax)):
            parts[name] = np.empty(size, dt)
            cl.enqueue_copy(env.queue, parts[name], buf)
        parts["Wloc"], parts["label"] = parts["Wloc"].reshape(rows, cols), parts["label"].reshape(rows, cols)
    k3 = cl.Kernel(prg, "fill_combine")  # in place: Wloc becomes the fill
    k3.set_args(d_wloc, d_label, d_level, i32(n))
    cl.enqueue_nd_range_kernel(env.queue, k3, _ceil(n, 256), (256,))
    mapped, _ = cl.enqueue_map_buffer(env.queue, d_wloc, cl.map_flags.READ, 0, W.shape, W.dtype, is_blocking=True)
    mapped.base.release(env.queue).wait()  # mapping a USE_HOST_PTR buffer makes W hold the device's result
    d_wloc.release()
    if kind.max(initial=0) == ref.NODATA:  # most worlds have none: skip the masked pass
        W[kind == ref.NODATA] = np.nan
    if stats is not None:
        stats.update(passes=1, tiles_run=nt, tiles=nt, method="labels", label_edges=int(off[:, -1].sum()) // 2)
    return W


def breach(env, h: np.ndarray, kind: np.ndarray) -> np.ndarray:
    """Complete breaching (reference.breach, bit for bit) as one serial
    work-item: the priority queue is inherently serial, and compiled it runs
    far faster than the pure-Python heap. No-data cells come back NaN."""
    import pyopencl as cl

    prg = _program(env)
    rows, cols = h.shape
    n = rows * cols
    h = np.ascontiguousarray(h, np.float32)
    pit = ref.pits(h, kind)
    mf = cl.mem_flags
    d_z = _buf(env, h, True)
    scratch = [cl.Buffer(env.ctx, mf.READ_WRITE, n * size) for size in (4, 1, 4, 4)]  # back, done, heap keys, ids
    d_kind, d_pit = _buf(env, kind), _buf(env, pit.astype(np.uint8))  # held until the kernel has run
    k = cl.Kernel(prg, "breach_serial")
    k.set_args(d_z, d_kind, d_pit, *scratch, np.int32(rows), np.int32(cols))
    cl.enqueue_nd_range_kernel(env.queue, k, (1,), None)
    out = np.empty_like(h)
    cl.enqueue_copy(env.queue, out, d_z)
    out[kind == ref.NODATA] = np.nan
    return out


def merge_sweep(env, order: np.ndarray, h: np.ndarray, term: np.ndarray, nbr: np.ndarray):
    """The depressions' union-find sweep (reference.merge_tree_reference,
    node for node) as one serial work-item: inherently serial, and far
    faster compiled than the Python loop. Every argument and buffer is per
    depression cell (sparse indices, int32: fewer than 2**31 cells)."""
    import pyopencl as cl

    prg = _program(env)
    m = max(int(order.size), 1)
    mf = cl.mem_flags
    d_order = _buf(env, np.ascontiguousarray(order, np.int32))
    d_h = _buf(env, np.ascontiguousarray(h, np.float32).ravel())
    d_term = _buf(env, np.ascontiguousarray(term, np.int32))
    d_nbr = _buf(env, np.ascontiguousarray(nbr, np.int32).ravel())
    uf, comp, cell_node = (cl.Buffer(env.ctx, mf.READ_WRITE, m * 4) for _ in range(3))
    node_bufs = [cl.Buffer(env.ctx, mf.READ_WRITE, 2 * m * 4) for _ in range(6)]  # at most 2 nodes per cell
    d_count = cl.Buffer(env.ctx, mf.READ_WRITE, 4)
    k = cl.Kernel(prg, "merge_sweep")
    k.set_args(d_order, np.int32(order.size), d_h, d_term, d_nbr, uf, comp, cell_node, *node_bufs, d_count)
    cl.enqueue_nd_range_kernel(env.queue, k, (1,), None)
    count = np.zeros(1, np.int32)
    cl.enqueue_copy(env.queue, count, d_count)
    nodes = int(count[0])
    out = []
    for b, dt in zip(node_bufs, (np.int32, np.int32, np.int32, np.float32, np.int32, np.int32)):
        a = np.empty(2 * m, dt)
        cl.enqueue_copy(env.queue, a, b)
        out.append(a[:nodes])
    cn = np.empty(m, np.int32)
    cl.enqueue_copy(env.queue, cn, cell_node)
    parent, child_a, child_b, birth, entry_a, entry_b = out
    i64 = np.int64
    return ref.MergeTree(parent.astype(i64), child_a.astype(i64), child_b.astype(i64), birth.astype(np.float64),
                         entry_a.astype(i64), entry_b.astype(i64), cn[:order.size].astype(i64))


def d8(env, z: np.ndarray, kind: np.ndarray, dx: float, local: tuple[int, int] | None = None) -> np.ndarray:
    """D8 codes of a surface (see kernels.cl)."""
    import pyopencl as cl

    from pipeline.opencl import global_size

    prg = _program(env)
    rows, cols = z.shape
    code = np.empty((rows, cols), np.int8)
    d_z, d_kind = _buf(env, np.ascontiguousarray(z, np.float32)), _buf(env, kind)
    d_code = cl.Buffer(env.ctx, cl.mem_flags.WRITE_ONLY, code.nbytes)
    k = cl.Kernel(prg, "d8")
    k.set_args(d_z, d_kind, d_code, np.int32(rows), np.int32(cols), np.float32(dx), np.float32(dx * np.sqrt(2.0)))
    cl.enqueue_nd_range_kernel(env.queue, k, global_size((cols, rows), local), local)
    cl.enqueue_copy(env.queue, code, d_code)
    return code


def accumulate(env, code: np.ndarray, weights: np.ndarray | None = None, tile: int = ACC_TILE,
               local: int | None = None) -> np.ndarray:
    """Exact D8 accumulation: uint32 cell counts (weights None) or int64 sums
    of integer weights. Codes < 0 end a path (outlet, no-data, pit); the
    receiver graph must be a forest, which codes from d8 are (receivers are
    strictly lower)."""
    import pyopencl as cl

    if not 1 <= tile <= ACC_TILE_MAX:
        raise ValueError(f"accumulation tile {tile} outside 1..{ACC_TILE_MAX}")
    unit = weights is None
    dtype = np.uint32 if unit else np.int64
    prg = _program(env, "uint" if unit else "long", (f"-DACC_TILE={tile}",))
    rows, cols = code.shape
    tiles_x, tiles_y = -(-cols // tile), -(-rows // tile)
    nt = tiles_x * tiles_y
    slots = nt * 4 * tile  # PMAX per tile
    mf = cl.mem_flags
    code = np.ascontiguousarray(code, np.int8)
    d_code = _buf(env, code)
    d_w = _buf(env, np.ascontiguousarray(weights, dtype)) if not unit else cl.Buffer(env.ctx, mf.READ_ONLY, 8)
    isz = np.dtype(dtype).itemsize
    d_exit = cl.Buffer(env.ctx, mf.READ_WRITE, slots * 4)
    d_sum = cl.Buffer(env.ctx, mf.READ_WRITE, slots * isz)
    d_in = cl.Buffer(env.ctx, mf.READ_WRITE, slots * isz)
    d_entry = cl.Buffer(env.ctx, mf.READ_WRITE, slots * 4)
    d_gdeg = cl.Buffer(env.ctx, mf.READ_WRITE, slots * 4)
    d_merge = cl.Buffer(env.ctx, mf.READ_WRITE, slots * 4)
    out = np.empty((rows, cols), dtype)
    d_A = cl.Buffer(env.ctx, mf.READ_WRITE, out.nbytes)
    i32 = np.int32
    geo = (i32(rows), i32(cols), i32(tiles_x), i32(nt))
    # one tile per work-group unless asked otherwise: PoCL may keep the
    # private scratch of every work-item of a group alive at once
    local = local or 1
    if local > 16:
        raise ValueError(f"accumulation work-group size {local} above 16 (each work-item holds a tile's scratch)")
    g = _ceil(nt, local)
    lw = (local,)
    k1 = cl.Kernel(prg, "acc_local")
    k1.set_args(d_code, d_w, d_exit, d_sum, d_in, d_merge, d_A, *geo, i32(unit))  # zeroes d_in
    cl.enqueue_nd_range_kernel(env.queue, k1, g, lw)
    k2 = cl.Kernel(prg, "acc_global")
    k2.set_args(d_code, d_exit, d_sum, d_in, d_entry, d_gdeg, *geo)
    cl.enqueue_nd_range_kernel(env.queue, k2, (1,), None)
    k3 = cl.Kernel(prg, "acc_final")
    k3.set_args(d_code, d_in, d_merge, d_A, *geo)
    cl.enqueue_nd_range_kernel(env.queue, k3, g, lw)
    cl.enqueue_copy(env.queue, out, d_A)
    return out


def first_scale(total: float) -> float:
    """quantize's scale before its round-up check: the largest power of two
    that keeps the total weight at or below 2^62."""
    if total <= 0:
        return 1.0
    return float(2.0 ** np.floor(np.log2(2.0 ** 62 / total)))


def quantize(weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Non-negative float weights as int64 fixed point whose total fits in
    2^62, and the scale (value = integer / scale). Integer sums are exact and
    associative, so accumulation does not depend on any order."""
    import math

    w = np.nan_to_num(np.asarray(weights, np.float64), nan=0.0, posinf=0.0)
    w = np.maximum(w, 0.0)
    # the correctly rounded total (tiled_accum.exact_total's), so a tiled run finds the same scale
    total = math.fsum(w.ravel())
    if total <= 0:
        return np.zeros(w.shape, np.int64), 1.0
    scale = first_scale(total)
    q = np.rint(w * scale).astype(np.int64)
    while q.sum() >= 2 ** 62:  # round-up slack
        scale /= 2
        q = np.rint(w * scale).astype(np.int64)
    return q, scale


def wetness(env, h, kind, acc_m2, water, ext, dx, tan_min, twi_dry, twi_wet, local=None):
    import pyopencl as cl

    from pipeline.opencl import global_size

    prg = _program(env)
    rows, cols = h.shape
    f = lambda a: _buf(env, np.ascontiguousarray(a, np.float32))
    d_twi = cl.Buffer(env.ctx, cl.mem_flags.WRITE_ONLY, rows * cols * 4)
    d_m = cl.Buffer(env.ctx, cl.mem_flags.WRITE_ONLY, rows * cols * 4)
    k = cl.Kernel(prg, "wetness")
    f32 = np.float32
    keep = (f(h), _buf(env, kind), f(acc_m2), f(water), f(ext))  # the kernel does not hold references
    k.set_args(*keep, d_twi, d_m, np.int32(rows), np.int32(cols),
               f32(dx), f32(dx), f32(dx * np.sqrt(2.0)), f32(tan_min), f32(twi_dry), f32(twi_wet))
    cl.enqueue_nd_range_kernel(env.queue, k, global_size((cols, rows), local), local)
    twi = np.empty((rows, cols), np.float32)
    m = np.empty((rows, cols), np.float32)
    cl.enqueue_copy(env.queue, twi, d_twi)
    cl.enqueue_copy(env.queue, m, d_m)
    return twi, m
