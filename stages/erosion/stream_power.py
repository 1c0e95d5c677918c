"""Geological time: stream-power fluvial erosion with uplift, solved with the
implicit O(n) scheme of Braun and Willett (2013), as fastscapelib does.

    dh/dt = U - K A^m S^n

A drainage area (m^2), S the slope to the D8 receiver. Each step:
1. uplift every cell that is not base level (map edge, no-data edge);
2. flow routing on the current surface with the hydrology stage's kernels:
   Priority-Flood+epsilon (so every cell reaches base level), D8 or Rho8
   (below), exact integer accumulation;
3. the implicit solve along the flow paths (stream_power.cl, one serial
   work-item, float64); no time-step limit. Cells draining less than the
   channel-initiation area are hillslopes: no river incision there;
4. hillslope diffusion, implicit and isotropic (hillslope.py), and
   threshold landsliding at a critical slope (hillslope.landslide).
With mfd routing the hillslope processes come first and the solve carries
deposition: dh/dt = U - K A^m S + (G / A) Qs (Yuan et al. 2019), Qs the
sediment flux from upstream with the landslides' material, by Gauss-Seidel
iterations (deposit_solve); the flux is routed to base level exactly.
Optional strata (Strata): hard beds with their own critical slope and K.

Grid marks: D8 sends every cell of a planar slope the same way, so rills
and valleys lock onto the 8 directions. Rho8 (Fairfield and Leymarie 1991)
draws the diagonal distance of each cell afresh every step (d = dx (2 - u),
u uniform from a counter-based hash of the cell and step): the steepest
receiver is then a diagonal or an axis in proportion to the true aspect,
and over the steps the valleys follow the terrain, not the grid. Flats are
avoided rather than routed: `breach` first carves each closed depression
out along its least-cost path (complete breaching, Lindsay 2016), and the
implicit solve never makes a cell lower than its receiver, so no filled
flat (whose epsilon routing draws parallel lines) forms afterwards.

The eroded volume leaves the map at base level: the step accumulates it down
the flow paths (exact integers) and checks that what arrives at base level
equals what was eroded (fastscapelib's mass-balance test). `reference_step`
is the same solve in pure Python for the tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.errors import StageError
from worldlib.flow import reference as flowref
from worldlib.flow.reference import DC, DR

KERNELS = Path(__file__).with_name("stream_power.cl")
NEWTON_TOL = 1e-10
NEWTON_MAX = 100
SECONDS_PER_YEAR = 365.25 * 86400.0


@dataclass
class StreamPowerResult:
    height: np.ndarray  # float64
    steps: int
    eroded_m3: float  # volume removed by rivers, summed over steps
    uplifted_m3: float  # volume added by uplift
    out_m3: float  # eroded volume that arrived at base level down the flow paths
    budget_relative_error: float  # |eroded - out| / eroded
    newton_iterations_max: int
    stats: dict = field(default_factory=dict)


def stack_order(code: np.ndarray) -> np.ndarray:
    """Cells with every receiver before its donors: base-level cells (code
    < 0) in index order, then breadth first up the tree, donors of a cell in
    index order (the kernel's order)."""
    rows, cols = code.shape
    c = code.ravel()
    n = c.size
    donors: list[list[int]] = [[] for _ in range(n)]
    for i in range(n):
        k = int(c[i])
        if k >= 0:
            donors[i + int(DR[k]) * cols + int(DC[k])].append(i)
    order = [i for i in range(n) if c[i] < 0]
    head = 0
    while head < len(order):
        order.extend(donors[order[head]])
        head += 1
    return np.array(order, np.int64)


def factors(code: np.ndarray, area_m2: np.ndarray, dx: float, k_dt: float, m: float, n_exp: float) -> np.ndarray:
    """F = K dt A^m / d^n per cell (d the distance to the D8 receiver), the
    one definition both solves use (vectorised: pow is costly per cell)."""
    dist = np.where(np.asarray(code) & 1, dx * math.sqrt(2.0), dx)
    return (k_dt * np.power(np.asarray(area_m2, np.float64), m) / np.power(dist, n_exp)).astype(np.float64)


def reference_step(h: np.ndarray, code: np.ndarray, area_m2: np.ndarray, dx: float, k_dt: float, m: float,
                   n_exp: float) -> tuple[np.ndarray, int]:
    """One implicit solve (heights already uplifted), the kernel's operations
    in pure Python float64; returns (new heights, most Newton iterations)."""
    rows, cols = code.shape
    z = np.asarray(h, np.float64).ravel().copy()
    c = code.ravel()
    fac = factors(code, area_m2, dx, k_dt, m, n_exp).ravel()
    worst = 0
    for i in stack_order(code).tolist():
        k = int(c[i])
        if k < 0:
            continue
        r = i + int(DR[k]) * cols + int(DC[k])
        hr = z[r]
        d0 = z[i] - hr
        if d0 <= 0.0:
            continue
        f = fac[i]
        if n_exp == 1.0:
            delta = d0 / (1.0 + f)
        else:
            delta = d0
            it = 0
            while it < NEWTON_MAX:
                p = delta ** (n_exp - 1.0)
                g = delta + f * p * delta - d0
                nxt = delta - g / (1.0 + f * n_exp * p)
                if nxt <= 0.0:
                    nxt = 0.5 * delta
                change = abs(nxt - delta)
                delta = nxt
                it += 1
                if change <= NEWTON_TOL * d0:
                    break
            worst = max(worst, it)
        z[i] = hr + delta
    return z.reshape(rows, cols), worst


class _DeviceSolver:
    """The serial solve on the OpenCL device `env`, buffers kept across steps."""

    def __init__(self, env, rows: int, cols: int):
        import pyopencl as cl

        from pipeline.opencl import load_program

        self.cl = cl
        self.prg = load_program(env, KERNELS)
        self.env = env
        if "cl_khr_fp64" not in self.env.device.extensions:
            raise StageError(f"erosion: stream power needs double precision, which {self.env.device.name} lacks")
        self.rows, self.cols = rows, cols
        n = rows * cols
        mf = cl.mem_flags
        self.d_h = cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 8)
        self.d_factor = cl.Buffer(self.env.ctx, mf.READ_ONLY, n * 8)
        self.d_code = cl.Buffer(self.env.ctx, mf.READ_ONLY, n)
        self.scratch = [cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 4) for _ in range(4)]  # ndon, first, donors, order
        self.d_iter = cl.Buffer(self.env.ctx, mf.READ_WRITE, 8)
        self.kernel = cl.Kernel(self.prg, "stream_power_step")

    def step(self, h: np.ndarray, code: np.ndarray, area_m2: np.ndarray, dx: float, k_dt: float, m: float,
             n_exp: float) -> tuple[np.ndarray, int]:
        cl, q = self.cl, self.env.queue
        h = np.ascontiguousarray(h, np.float64)
        cl.enqueue_copy(q, self.d_h, h)
        cl.enqueue_copy(q, self.d_factor, factors(code, area_m2, dx, k_dt, m, n_exp))
        cl.enqueue_copy(q, self.d_code, np.ascontiguousarray(code, np.int8))
        self.kernel.set_args(self.d_h, self.d_code, self.d_factor, *self.scratch, self.d_iter, np.int32(self.rows),
                             np.int32(self.cols), np.float64(n_exp))
        cl.enqueue_nd_range_kernel(q, self.kernel, (1,), None)
        out = np.empty_like(h)
        it = np.zeros(2, np.int32)
        cl.enqueue_copy(q, out, self.d_h)
        cl.enqueue_copy(q, it, self.d_iter)
        if int(it[1]) != h.size:
            raise StageError(f"erosion: the flow graph is not a tree ({int(it[1])} of {h.size} cells ordered)")
        return out, int(it[0])


LAKE_FILL_MIN_M = 1e-3  # a cell this far below the routing surface is in a closed depression
FLAT_TILT_M_PER_CELL = 0.01  # tilt of a filled depression's routing surface toward its outlet


def routing_surface(env, h: np.ndarray, kind: np.ndarray, flat_routing: str) -> np.ndarray:
    """The float32 surface every interior cell descends on to base level,
    filled on the OpenCL device `env`.

    "epsilon": Priority-Flood+epsilon (Barnes 2014) of h: a filled
    depression drains along its flood order, rows, columns and diagonals.
    "distance": the filled level tilted down toward the depression's outlet
    by FLAT_TILT_M_PER_CELL times the Euclidean distance to it (scipy's exact
    distance transform), then Priority-Flood+epsilon to close what the
    straight-line distance leaves (a lake's bays behind a headland): the flow
    over the flat converges on the outlet from every direction, as water on
    a lake does, instead of along the grid (flat resolution toward lower
    terrain, Garbrecht and Martz 1997 / Barnes et al. 2014, with Euclidean
    rather than grid-step distances)."""
    from scipy import ndimage

    from worldlib.flow import device as flow

    h32 = flowref.canonical(np.asarray(h, np.float32))
    if flat_routing == "epsilon":
        return flow.fill(env, h32, kind, eps=True)
    filled = flow.fill(env, h32, kind, eps=False)
    lake = filled > h32
    if not lake.any():
        return flow.fill(env, h32, kind, eps=True)
    # outlets: dry cells beside a lake cell at or below that lake's level
    grown_level = ndimage.maximum_filter(np.where(lake, filled, -np.inf), size=3)
    outlet = ~lake & ndimage.binary_dilation(lake, structure=np.ones((3, 3), bool)) & (h32 <= grown_level)
    dist = ndimage.distance_transform_edt(~outlet)
    z = np.where(lake, filled + np.float32(FLAT_TILT_M_PER_CELL) * dist.astype(np.float32), h32).astype(np.float32)
    return flow.fill(env, flowref.canonical(z), kind, eps=True)


def counter_uniform(key: int, step: int, n: int) -> np.ndarray:
    """n uniform numbers in [0, 1) from a counter-based hash (splitmix64 of
    key, step and cell index): the same at any thread count or tiling."""
    with np.errstate(over="ignore"):
        x = (np.arange(n, dtype=np.uint64) + np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)
             + np.uint64(step) * np.uint64(0xD1B54A32D192ED03))
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def rho8(z: np.ndarray, interior: np.ndarray, dx: float, u: np.ndarray) -> np.ndarray:
    """Rho8 receivers (Fairfield and Leymarie 1991) on a surface where every
    interior cell has a strictly lower neighbour: the steepest descent with
    the diagonal distance dx (2 - u) per cell, u in [0, 1). Codes as D8;
    -1 off the interior (base level). Ties keep the first direction N, NE, ..."""
    rows, cols = z.shape
    zp = np.pad(np.asarray(z, np.float64), 1, constant_values=np.inf)
    best = np.zeros((rows, cols))
    code = np.full((rows, cols), -1, np.int8)
    diag = dx * (2.0 - u.reshape(rows, cols))
    for k in range(8):
        zn = zp[1 + DR[k]:1 + DR[k] + rows, 1 + DC[k]:1 + DC[k] + cols]
        s = (z - zn) / (diag if k & 1 else dx)
        steeper = s > best
        best = np.where(steeper, s, best)
        code[steeper] = k
    code[~interior] = -1
    return code


RHO8_KEY = 0x52686F38  # the hash key of Rho8's draws


MFD_AXIS_CONTOUR, MFD_DIAG_CONTOUR = 0.5, 0.354


def ascending_order(z: np.ndarray) -> np.ndarray:
    """int32 cell indices by ascending float32 z, ties in index order (a
    stable argsort; here one sort of 64-bit keys z-bits : index, which is
    faster than numpy's stable argsort of floats)."""
    z32 = np.asarray(z, np.float32).ravel() + np.float32(0.0)  # -0 -> +0: they compare equal
    bits = z32.view(np.uint32).astype(np.uint64)
    # float bits -> unsigned keys in the same order: flip every bit of a negative, the sign bit of the rest
    neg = (bits >> np.uint64(31)) == 1
    bits = np.where(neg, bits ^ np.uint64(0xFFFFFFFF), bits | np.uint64(0x80000000))
    keys = (bits << np.uint64(32)) | np.arange(bits.size, dtype=np.uint64)
    keys.sort()
    return (keys & np.uint64(0xFFFFFFFF)).astype(np.int32)


def mfd_fractions(z: np.ndarray, interior: np.ndarray, dx: float, p_exp: float) -> np.ndarray:
    """(n, 8) shares of each cell's flow to its 8 neighbours (N, NE, ... NW):
    to every neighbour lower on the routing surface z, in proportion to
    slope^p times contour length (0.5 dx across an axis, 0.354 dx across a
    diagonal; Quinn et al. 1991). Rows of base-level cells are 0."""
    rows, cols = z.shape
    # slopes and slope^p in float32 (z is float32; numpy's float32 power is much faster than float64's), the
    # shares normalised in float64 so that they sum to 1 to round-off
    z32 = np.asarray(z, np.float32)
    zp = np.pad(z32, 1, constant_values=np.inf)
    p32 = np.float32(p_exp)
    w = np.empty((8, rows, cols), np.float32)
    for k in range(8):
        zn = zp[1 + DR[k]:1 + DR[k] + rows, 1 + DC[k]:1 + DC[k] + cols]
        d = dx * math.sqrt(2.0) if k & 1 else dx
        slope = np.maximum(z32 - zn, np.float32(0.0), out=w[k])  # 0 where the neighbour is not lower
        slope *= np.float32(1.0 / d)
        np.power(slope, p32, out=w[k])
        w[k] *= np.float32((MFD_DIAG_CONTOUR if k & 1 else MFD_AXIS_CONTOUR) * dx)
    w[:, ~np.asarray(interior, bool)] = 0.0
    w = w.reshape(8, rows * cols)
    total = w.sum(axis=0, dtype=np.float64)
    return np.multiply(w.T, (1.0 / np.where(total > 0, total, 1.0))[:, None], out=np.empty((rows * cols, 8)))


def mfd_plane_slope_ratio(aspect_rad: np.ndarray, p_exp: float) -> np.ndarray:
    """E(aspect): the slope the mfd solve sees on a plane (sum over the lower
    neighbours of share_j * drop_j / d_j) over the plane's true gradient,
    for a plane whose steepest descent points along aspect_rad (radians from
    a grid axis). With slope^1.1 shares and contour lengths 0.5 / 0.354 it is
    0.856 along an axis, 0.776 at 22.5 degrees and 0.807 along a diagonal:
    left alone, flow down an axis incises 10 % faster than flow between the
    axes, and valleys lock onto the grid directions (a broad excess of
    spectral power on them)."""
    ang = np.arange(8) * (np.pi / 4.0)
    contour = np.where(np.arange(8) & 1, MFD_DIAG_CONTOUR, MFD_AXIS_CONTOUR)
    s = np.cos(np.asarray(aspect_rad, np.float64)[..., None] - ang)
    s = np.where(s > 1e-12, s, 0.0)
    w = np.power(s, p_exp) * contour
    return (w * s).sum(axis=-1) / w.sum(axis=-1)


_ISOTROPY_TABLE_STEPS = 4096  # samples of E over 0 .. 45 degrees (E has the grid's 8-fold symmetry)


def mfd_isotropy(h: np.ndarray, dx: float, p_exp: float) -> np.ndarray:
    """Per cell 1 / E(aspect) (mfd_plane_slope_ratio), the aspect from the
    3x3 gradient of h (Horn 1981): scaling K dt A^m by it makes the mfd
    incision rate K A^m |grad h| on any plane, whatever its direction, so
    the solve has no preferred direction. The scale is taken from the
    heights at the start of the step and lies within 1 / max E .. 1 / min E
    (1.17 .. 1.29 at p = 1.1), so the solve stays implicit and stable."""
    z = np.pad(np.asarray(h, np.float64), 1, mode="edge")
    a, b, c = z[:-2, :-2], z[:-2, 1:-1], z[:-2, 2:]
    d, f = z[1:-1, :-2], z[1:-1, 2:]
    g, hh, i = z[2:, :-2], z[2:, 1:-1], z[2:, 2:]
    gx = (c + 2.0 * f + i) - (a + 2.0 * d + g)
    gy = (g + 2.0 * hh + i) - (a + 2.0 * b + c)
    phi = np.arctan2(np.abs(gy), np.abs(gx))  # 0 .. 90 degrees: E is symmetric about the axes
    phi = np.minimum(phi, np.pi / 2.0 - phi)  # 0 .. 45 degrees: and about the diagonals
    grid = np.linspace(0.0, np.pi / 4.0, _ISOTROPY_TABLE_STEPS + 1)
    return np.interp(phi, grid, 1.0 / mfd_plane_slope_ratio(grid, p_exp))


def mfd_factor(area_m2: np.ndarray, interior: np.ndarray, k_dt: float, m: float, channel_area_m2: float,
               scale: np.ndarray | None = None) -> np.ndarray:
    """K dt A^m per cell (times `scale`, mfd_isotropy), 0 on hillslopes (A below channel_area_m2) and at base level."""
    a = np.asarray(area_m2, np.float64).ravel()
    on = np.asarray(interior, bool).ravel() & (a >= channel_area_m2)
    out = np.zeros_like(a)
    out[on] = k_dt * np.power(a[on], m)
    if scale is not None:
        out[on] *= np.asarray(scale, np.float64).ravel()[on]
    return out


@dataclass
class Sediment:
    """What one mfd step's sediment did (m^3 unless named): exported is the
    sum of every cell's net source (erosion less deposition, plus landslide
    material), out what the flux carried to base level (equal to round-off:
    the routing conserves it), deposited the volume the deposition term laid
    down; the Gauss-Seidel iterations taken and the last change of the
    deposition (m), and the least flux (negative would be sediment made)."""

    exported_m3: float = 0.0
    out_m3: float = 0.0
    deposited_m3: float = 0.0
    iterations: int = 0
    residual_m: float = 0.0
    flux_min_m3: float = 0.0
    deposit_m: np.ndarray | None = None  # the last deposition per cell (flat): the next step's first guess


DEPOSIT_ITERATIONS_MAX = 4  # each is two serial passes over the grid; the deposit carries over to the next step
DEPOSIT_TOLERANCE_M = 1e-3  # Gauss-Seidel stops once no cell's deposition changes by more


def deposit_solve(h: np.ndarray, solve: Callable, accumulate: Callable, area_m2: np.ndarray, interior: np.ndarray,
                  solve_factor: np.ndarray, cell_area: float, deposition_g: float,
                  source_m3: np.ndarray | None, deposit_start: np.ndarray | None = None,
                  iterations: int | None = None) -> tuple[np.ndarray, Sediment]:
    """The implicit stream-power solve with deposition (Yuan et al. 2019):
    dh/dt = U - K A^m S + (G / A) Qs, Qs the sediment flux arriving from
    upstream, by Gauss-Seidel iterations as fastscapelib does: solve with the
    deposition of the last flux (solve(h + deposit)), route the new net
    sources down the flow graph (accumulate), repeat until the deposition
    settles (at most `iterations` times, starting from deposit_start, the
    last step's deposit: the pattern moves slowly from step to step). The
    deposit per step is min(G / A, 1 / cell area) Qs: never more than
    arrives, so the flux stays non-negative at any G. Flat arrays."""
    src_extra = np.zeros_like(h) if source_m3 is None else np.asarray(source_m3, np.float64).ravel()
    # rivers deposit; on hillslopes (no incision there) the material passes on to the channel network
    river = interior & (solve_factor > 0)
    coef = np.where(river, np.minimum(deposition_g / np.maximum(area_m2, cell_area), 1.0 / cell_area), 0.0)
    # Deposition at a cell raises it, which slows the erosion just upstream and so the flux that made the
    # deposit: a negative feedback of gain about (cell area) coef per donor, which the plain iteration turns
    # into an oscillation that grows once the gain passes 1. Under-relaxing each cell by 1 / (1 + gain)
    # (gain taken for two donors) damps it at any G.
    relax = 1.0 / (1.0 + 2.0 * cell_area * coef)
    iterations = DEPOSIT_ITERATIONS_MAX if iterations is None else iterations
    dep = np.zeros_like(h) if deposit_start is None or deposition_g <= 0 else np.where(coef > 0, deposit_start, 0.0)
    iterations = max(1, iterations) if deposition_g > 0 else 1
    it = 0
    while True:
        new = solve(h + dep)
        src = (h - new) * cell_area + src_extra
        acc = accumulate(src)
        it += 1
        sed = Sediment(float(src.sum()), float(acc[~interior].sum()), float(dep.sum()) * cell_area, it, 0.0,
                       float(acc.min()) if acc.size else 0.0, dep)
        if deposition_g <= 0:
            return new, sed
        nxt = coef * np.maximum(acc - src, 0.0)
        sed.residual_m = float(np.abs(nxt - dep).max())
        if sed.residual_m <= DEPOSIT_TOLERANCE_M or it > iterations:
            return new, sed
        if it == iterations:
            # out of iterations: keep no deposit larger than what now arrives and solve once more. Less deposit
            # only lowers the cells, so every flux grows: no cell then keeps more than it receives.
            dep = np.minimum(dep, nxt)
        else:
            dep = dep + relax * (nxt - dep)


def _reference_solve(hf: np.ndarray, order: np.ndarray, frac: np.ndarray, factor: np.ndarray, cols: int,
                     dx: float) -> np.ndarray:
    """mfd_solve in pure Python (a copy of hf)."""
    hf = hf.copy()
    offset = (DR * cols + DC).tolist()
    for i in order.tolist():
        if factor[i] == 0.0:
            continue
        sum_f = sum_fh = 0.0
        for k in range(8):
            if frac[i, k] == 0.0:
                continue
            hj = hf[i + offset[k]]
            if hj >= hf[i]:
                continue
            fj = factor[i] * frac[i, k] / (dx * math.sqrt(2.0) if k & 1 else dx)
            sum_f += fj
            sum_fh += fj * hj
        hf[i] = (hf[i] + sum_fh) / (1.0 + sum_f)
    return hf


def _reference_accumulate(src: np.ndarray, order: np.ndarray, frac: np.ndarray, inside: np.ndarray,
                          cols: int) -> np.ndarray:
    """mfd_area / mfd_accumulate in pure Python: each cell's src plus what its donors pass on."""
    acc = np.array(src, np.float64)
    offset = (DR * cols + DC).tolist()
    for i in order[::-1].tolist():
        if not inside[i]:
            continue
        for k in range(8):
            if frac[i, k] > 0:
                acc[i + offset[k]] += acc[i] * frac[i, k]
    return acc


def mfd_reference_step(h: np.ndarray, z: np.ndarray, interior: np.ndarray, dx: float, k_dt: float, m: float,
                       p_exp: float, channel_area_m2: float, scale: np.ndarray | None = None,
                       deposition_g: float = 0.0, source_m3: np.ndarray | None = None,
                       deposit_start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Sediment]:
    """The mfd step (fractions, area, factor, solve with deposition) with the
    serial passes in pure Python float64 (small grids): returns (new
    heights, MFD drainage area in m^2, Sediment). z is the float32 routing surface."""
    rows, cols = h.shape
    zf = np.asarray(z, np.float32)
    inside = np.asarray(interior, bool)
    frac = mfd_fractions(zf, inside, dx, p_exp)
    order = ascending_order(zf)
    flat_inside = inside.ravel()
    area = _reference_accumulate(np.full(rows * cols, dx * dx), order, frac, flat_inside, cols)
    factor = mfd_factor(area, inside, k_dt, m, channel_area_m2, scale)
    new, sed = deposit_solve(np.asarray(h, np.float64).ravel(),
                             lambda hf: _reference_solve(hf, order, frac, factor, cols, dx),
                             lambda src: _reference_accumulate(src, order, frac, flat_inside, cols),
                             area, flat_inside, factor, dx * dx, deposition_g, source_m3, deposit_start)
    return new.reshape(rows, cols), area.reshape(rows, cols), sed


class _DeviceMFDSolver:
    """The mfd_* kernels on the OpenCL device `env`, buffers kept across steps."""

    def __init__(self, env, rows: int, cols: int):
        import pyopencl as cl

        from pipeline.opencl import load_program

        self.cl = cl
        prg = load_program(env, KERNELS)
        self.env = env
        if "cl_khr_fp64" not in self.env.device.extensions:
            raise StageError(f"erosion: stream power needs double precision, which {self.env.device.name} lacks")
        self.k_area, self.k_solve = cl.Kernel(prg, "mfd_area"), cl.Kernel(prg, "mfd_solve")
        self.k_accumulate = cl.Kernel(prg, "mfd_accumulate")
        self.rows, self.cols = rows, cols
        n = rows * cols
        mf = cl.mem_flags
        self.d_h = cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 8)
        self.d_order = cl.Buffer(self.env.ctx, mf.READ_ONLY, n * 4)
        self.d_interior = cl.Buffer(self.env.ctx, mf.READ_ONLY, n)
        self.d_area = cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 8)
        self.d_factor = cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 8)
        self.d_frac = cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 8 * 8)
        self.d_src = cl.Buffer(self.env.ctx, mf.READ_WRITE, n * 8)

    def step(self, h: np.ndarray, z: np.ndarray, interior: np.ndarray, dx: float, k_dt: float, m: float,
             p_exp: float, channel_area_m2: float, scale: np.ndarray | None = None, deposition_g: float = 0.0,
             source_m3: np.ndarray | None = None,
             deposit_start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Sediment]:
        cl, q = self.cl, self.env.queue
        z = np.ascontiguousarray(z, np.float32)
        rows, cols = np.int32(self.rows), np.int32(self.cols)
        inside = np.asarray(interior, bool)
        cl.enqueue_copy(q, self.d_order, ascending_order(z))
        cl.enqueue_copy(q, self.d_interior, np.ascontiguousarray(inside, np.uint8))
        cl.enqueue_copy(q, self.d_frac, mfd_fractions(z, inside, dx, p_exp))
        self.k_area(q, (1,), None, self.d_order, self.d_interior, self.d_frac, self.d_area, rows, cols, np.float64(dx))
        area = np.empty((self.rows, self.cols), np.float64)
        cl.enqueue_copy(q, area, self.d_area)
        factor = mfd_factor(area, inside, k_dt, m, channel_area_m2, scale)
        cl.enqueue_copy(q, self.d_factor, factor)
        new, sed = deposit_solve(np.asarray(h, np.float64).ravel(), lambda hf: self._solve(hf, dx),
                                 self._accumulate, area.ravel(), inside.ravel(), factor, dx * dx, deposition_g, source_m3,
                                 deposit_start)
        return new.reshape(self.rows, self.cols), area, sed

    def _solve(self, hf: np.ndarray, dx: float) -> np.ndarray:
        cl, q = self.cl, self.env.queue
        cl.enqueue_copy(q, self.d_h, np.ascontiguousarray(hf, np.float64))
        self.k_solve(q, (1,), None, self.d_h, self.d_order, self.d_frac, self.d_factor, np.int32(self.rows),
                     np.int32(self.cols), np.float64(dx))
        out = np.empty(hf.size, np.float64)
        cl.enqueue_copy(q, out, self.d_h)
        return out

    def _accumulate(self, src: np.ndarray) -> np.ndarray:
        cl, q = self.cl, self.env.queue
        cl.enqueue_copy(q, self.d_src, np.ascontiguousarray(src, np.float64))
        self.k_accumulate(q, (1,), None, self.d_order, self.d_interior, self.d_frac, self.d_src, self.d_area,
                          np.int32(self.rows), np.int32(self.cols))
        out = np.empty(src.size, np.float64)
        cl.enqueue_copy(q, out, self.d_area)  # d_area is free once the factor is computed
        return out


def run(env, height: np.ndarray, dx: float, years: float, dt_years: float, k: float, m: float, n_exp: float,
        uplift_m_per_year: float, progress: Callable[[float, str], None] | None = None,
        step_fn: Callable | None = None, routing: str = "d8", channel_area_m2: float = 0.0,
        diffusivity_m2_per_year: float = 0.0, breach: bool = False, mfd_exponent: float = 1.1,
        mfd_step_fn: Callable | None = None, flat_routing: str = "epsilon",
        fill_lakes: bool = False, mfd_isotropic: bool = True, critical_slope: float = 0.0,
        deposition_g: float = 0.0, strata: Strata | None = None, incision_width_m: float = 0.0,
        round_sweeps: int = 0) -> StreamPowerResult:
    """Erode `height` (m, finite) for `years` on the OpenCL device `env`
    (pipeline.opencl.CL); k in m^(1-2m)/year, uplift in m/year. step_fn
    replaces the device solve (tests pass reference_step).
    routing "d8", "rho8" or "mfd" (n = 1 only: multiple flow directions,
    slope^mfd_exponent; detachment-limited, so the eroded volume leaves the
    map and the check is the volume budget); channel_area_m2: no incision below this drainage
    area; diffusivity: hillslope diffusion (m^2/year, implicit, isotropic);
    breach: carve the closed depressions out first (complete breaching);
    mfd_isotropic: scale the mfd incision so that it is the same on a plane
    of any direction (mfd_isotropy); critical_slope (m/m, 0 off): threshold
    landsliding, no slope steeper (hillslope.landslide) after each step's
    diffusion and once at the end; deposition_g (mfd only, dimensionless):
    sediment settles at (G / A) Qs (Yuan et al. 2019; deposit_solve), the
    landslides' material included in Qs; strata: bands of hard rock (Strata);
    incision_width_m (mfd only, 0 off): incise by the flow per metre of
    contour, K (w A / dx)^m S (incision_k); round_sweeps: the landslides'
    cones rounded by that many sweeps (hillslope.landslide).

    Steps: check and breach the start (_start); per step, uplift, then the
    mfd step (_mfd_step) or the single-receiver one (_tree_step); the
    budgets (_result)."""
    h, kind, breached_m3 = _start(env, height, dx, years, breach)
    steps = max(1, math.ceil(years / dt_years - 1e-9)) if years > 0 else 0
    dt = years / steps if steps else 0.0
    if deposition_g > 0 and routing != "mfd":
        raise StageError(f"erosion: deposition (G = {deposition_g:g}) needs mfd routing, got {routing}")
    k = incision_k(k, m, dx, incision_width_m) if routing == "mfd" else k
    options = _Options(routing, channel_area_m2, diffusivity_m2_per_year, mfd_exponent, flat_routing, fill_lakes,
                       mfd_isotropic, critical_slope, deposition_g, strata, uplift_m_per_year, round_sweeps)
    solver = _Solver(env, kind, dx, _Law(k, m, n_exp, dt), options,
                     _solve_function(env, h.shape, n_exp, options, step_fn, mfd_step_fn))
    height_start = h.copy()
    volumes = _Volumes()
    uplift_step = np.where(kind != flowref.INTERIOR, 0.0, uplift_m_per_year * dt)  # m per step, 0 at base level
    uplift_step_m3 = float(uplift_step.sum()) * solver.cell_area
    for s in range(steps):
        h_up = h + uplift_step
        volumes.uplifted += uplift_step_m3
        h = _mfd_step(solver, h_up, s, volumes) if routing == "mfd" else _tree_step(solver, h_up, s, volumes)
        if progress and (s % max(1, steps // 20) == 0 or s == steps - 1):
            progress((s + 1) / steps, f"stream power {s + 1}/{steps} ({(s + 1) * dt:.3g} years)")
    if steps and critical_slope > 0:
        # the last step's rivers may leave banks steeper than the limit: they slide, their material leaves
        h, slid = _landslide(solver, h, uplift_m_per_year * dt * steps)
        volumes.add_direct_landslide(float(slid.sum()))
    return _result(h, height_start, solver, steps, volumes, breached_m3)


def incision_k(k: float, m: float, dx: float, width_m: float) -> float:
    """K of K A^m S on cells of dx metres when rivers incise by the flow per
    metre of contour: K (w A / dx)^m S = K (w / dx)^m A^m S. Multiple flow
    directions spread a valley's flow over the cells across its floor, so a
    cell's own A falls as the cells get finer (the floor holds more of them)
    while A / dx, the flow per metre of width, stays the same; w (a channel
    width, m) turns it back into an area. At dx = w this is K itself; width_m
    0 keeps the cell's own A (incision then weakens at finer cells: a finer
    grid's valleys cut less, stand higher and have less floor)."""
    return k * (width_m / dx) ** m if width_m > 0 else k


def _start(env, height: np.ndarray, dx: float, years: float, breach: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """The float64 heights to erode (breached on the OpenCL device `env` when
    asked), the cell kinds (map edges are base level, fixed) and the volume
    breaching carved out (m^3)."""
    from worldlib.flow import device as flow

    h = np.asarray(height, np.float64).copy()
    if not np.isfinite(h).all():
        raise StageError("erosion: stream power got non-finite heights")
    kind = flowref.cell_kinds(h.astype(np.float32))
    breached_m3 = 0.0
    if breach and years > 0:
        carved = flow.breach(env, flowref.canonical(h.astype(np.float32)), kind).astype(np.float64)
        breached_m3 = float((h - carved).sum()) * dx * dx
        h = carved
    return h, kind, breached_m3


@dataclass(frozen=True)
class Strata:
    """Horizontal beds of hard rock in the uplifting block: a bed of
    thickness_m * hard_fraction in every thickness_m of rock, fixed to the
    rock (so it rises with the uplift), where the rock stands at
    critical_slope (m/m, cliffs) and erodes at k_factor times K; the soft
    rock between keeps the run's limit and K, so benches form on it."""

    thickness_m: float
    hard_fraction: float
    critical_slope: float
    k_factor: float

    def hard(self, h: np.ndarray, rock_uplift_m: float) -> np.ndarray:
        """Cells in a hard bed: the rock now at height h was rock_uplift_m lower when the beds were laid."""
        return np.mod((np.asarray(h, np.float64) - rock_uplift_m) / self.thickness_m, 1.0) < self.hard_fraction


@dataclass(frozen=True)
class _Law:
    """The stream-power law dh/dt = U - K A^m S^n and the step it is solved over."""

    k: float  # m^(1-2m)/year
    m: float
    n_exp: float
    dt: float  # years per step


@dataclass(frozen=True)
class _Options:
    """How the flow is routed and what else shapes the land (run's arguments of the same names)."""

    routing: str  # "d8", "rho8" or "mfd"
    channel_area_m2: float
    diffusivity_m2_per_year: float
    mfd_exponent: float
    flat_routing: str
    fill_lakes: bool
    mfd_isotropic: bool
    critical_slope: float = 0.0  # m/m, 0: no landsliding
    deposition_g: float = 0.0
    strata: Strata | None = None
    uplift_m_per_year: float = 0.0
    round_sweeps: int = 0  # the landslides' cones rounded by this many sweeps (0: the 32-direction envelope)


@dataclass(frozen=True)
class _Solver:
    """What every step reads: the OpenCL device `env`, the grid, the law, the
    options and the implicit solve (the device's, or the test's reference)."""

    env: object
    kind: np.ndarray  # worldlib.flow.reference.cell_kinds: interior cells erode, the rest is base level
    dx: float
    law: _Law
    options: _Options
    solve: Callable

    @property
    def cell_area(self) -> float:
        return self.dx * self.dx

    @property
    def interior(self) -> np.ndarray:
        return self.kind == flowref.INTERIOR


@dataclass
class _Volumes:
    """The volumes (m^3) the budgets add up over the steps."""

    eroded: float = 0.0
    uplifted: float = 0.0
    out: float = 0.0  # what arrived at base level
    diffusion_out: float = 0.0
    lake_fill: float = 0.0
    worst_newton: int = 0
    landslide: float = 0.0  # material above the critical slope, sent down the flow paths
    deposited: float = 0.0
    exported: float = 0.0  # the net sources of sediment (mfd): what should arrive at base level
    deposit_iterations: int = 0
    deposit_residual_m: float = 0.0
    flux_min: float = 0.0
    landslide_direct: float = 0.0  # landslide material counted out at once, not routed (the final pass, d8/rho8)
    deposit_last: np.ndarray | None = None  # the last step's deposit per cell (m), the next one's first guess

    def add_direct_landslide(self, m3: float) -> None:
        self.landslide += m3
        self.landslide_direct += m3
        self.out += m3


def _solve_function(env, shape: tuple[int, int], n_exp: float, options: _Options, step_fn: Callable | None,
                    mfd_step_fn: Callable | None) -> Callable:
    """The implicit solve of the chosen routing: the test's function, or the device's on `env`."""
    rows, cols = shape
    if options.routing == "mfd":
        if n_exp != 1.0:
            raise StageError(f"erosion: mfd routing solves stream power with n = 1 only (got n = {n_exp:g})")
        return mfd_step_fn or _DeviceMFDSolver(env, rows, cols).step
    return step_fn or _DeviceSolver(env, rows, cols).step


def _tree_step(solver: _Solver, h_up: np.ndarray, s: int, volumes: _Volumes) -> np.ndarray:
    """Step s (0-based) with one receiver per cell (D8 or Rho8) on uplifted
    heights: routing, the implicit solve, the eroded volume carried down the
    flow paths to base level, then hillslope diffusion."""
    from worldlib.flow import device as flow

    env, law, options, cell_area = solver.env, solver.law, solver.options, solver.cell_area
    R = routing_surface(env, h_up, solver.kind, options.flat_routing)
    if options.routing == "rho8":
        code = rho8(R, solver.interior, solver.dx, counter_uniform(RHO8_KEY, s, h_up.size))
    else:
        code = flow.d8(env, R, solver.kind, solver.dx)
    area = flow.accumulate(env, code).astype(np.float64) * cell_area
    channel_area_m2 = options.channel_area_m2
    river_area = np.where(area >= channel_area_m2, area, 0.0) if channel_area_m2 > 0 else area
    new, it = solver.solve(h_up, code, river_area, solver.dx, law.k * law.dt, law.m, law.n_exp)
    volumes.worst_newton = max(volumes.worst_newton, it)
    e = np.maximum(_erosion(h_up, new, s), 0.0) * cell_area
    q, scale = flow.quantize(e)
    arrived = flow.accumulate(env, code, q)
    volumes.eroded += float(q.sum()) / scale
    volumes.out += float(arrived[code < 0].sum()) / scale
    if options.diffusivity_m2_per_year > 0:
        new = _diffuse(solver, new, s, volumes)
    if options.critical_slope > 0:
        new, slid = _landslide(solver, new, options.uplift_m_per_year * law.dt * (s + 1))
        volumes.add_direct_landslide(float(slid.sum()))
    return new


def _mfd_step(solver: _Solver, h_up: np.ndarray, s: int, volumes: _Volumes) -> np.ndarray:
    """Step s (0-based) with multiple flow directions on uplifted heights:
    hillslope diffusion, landslides, the routing surface (closed depressions
    filled with sediment when asked), the implicit solve with deposition (the
    landslides' material in its flux); the flux carries the rest to base level."""
    law, options = solver.law, solver.options
    # hillslopes creep and slide first, so the rivers' solve has the last word in the channels
    if options.diffusivity_m2_per_year > 0:
        h_up = _diffuse(solver, h_up, s, volumes)
    slid = None
    rock_up = options.uplift_m_per_year * law.dt * (s + 1)
    if options.critical_slope > 0:
        h_up, slid = _landslide(solver, h_up, rock_up)
        volumes.landslide += float(slid.sum())
    R = routing_surface(solver.env, h_up, solver.kind, options.flat_routing)
    if options.fill_lakes:
        # sediment settles in every closed depression up to the (tilted) routing surface
        lake = R.astype(np.float64) > h_up + LAKE_FILL_MIN_M
        volumes.lake_fill += float((R[lake] - h_up[lake]).sum()) * solver.cell_area
        h_up = np.where(lake, R.astype(np.float64), h_up)
    scale = mfd_isotropy(h_up, solver.dx, options.mfd_exponent) if options.mfd_isotropic else None
    if options.strata is not None and options.strata.k_factor != 1.0:
        k_scale = np.where(options.strata.hard(h_up, rock_up), options.strata.k_factor, 1.0)
        scale = k_scale if scale is None else scale * k_scale
    new, _, sed = solver.solve(h_up, R, solver.interior, solver.dx, law.k * law.dt, law.m, options.mfd_exponent,
                               options.channel_area_m2, scale=scale, deposition_g=options.deposition_g,
                               source_m3=slid, deposit_start=volumes.deposit_last)
    volumes.deposit_last = sed.deposit_m
    e = _erosion(h_up, new, s, allow_raise=options.deposition_g > 0)
    volumes.eroded += float(np.maximum(e, 0.0).sum()) * solver.cell_area
    volumes.deposited += sed.deposited_m3
    volumes.exported += sed.exported_m3
    volumes.out += sed.out_m3
    volumes.deposit_iterations = max(volumes.deposit_iterations, sed.iterations)
    volumes.deposit_residual_m = max(volumes.deposit_residual_m, sed.residual_m)
    volumes.flux_min = min(volumes.flux_min, sed.flux_min_m3)
    return new


def _landslide(solver: _Solver, h: np.ndarray, rock_uplift_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Heights cut to the critical slope (the hard beds' where strata are
    given), and the material cut per cell (m^3)."""
    from . import hillslope

    sc = solver.options.critical_slope
    strata = solver.options.strata
    if strata is not None:
        sc = np.where(strata.hard(h, rock_uplift_m), strata.critical_slope, sc)
    cut = hillslope.landslide(h, solver.dx, sc, solver.env, solver.options.round_sweeps)
    slid = (h - cut) * solver.cell_area
    return cut, slid


def _erosion(h_up: np.ndarray, new: np.ndarray, s: int, allow_raise: bool = False) -> np.ndarray:
    """h_up - new after checking the solve (finite, no cell raised unless deposition may raise it)."""
    if not np.isfinite(new).all():
        raise StageError(f"erosion: stream power blew up at step {s + 1} (non-finite heights)")
    e = h_up - new
    if not allow_raise and (e < -1e-9 * (1.0 + np.abs(h_up))).any():
        raise StageError(f"erosion: stream power raised a cell at step {s + 1} (broken invariant)")
    return e


def _diffuse(solver: _Solver, h: np.ndarray, s: int, volumes: _Volumes) -> np.ndarray:
    """One implicit hillslope-diffusion step; what crossed the fixed edge is counted out."""
    from . import hillslope

    diffused = hillslope.step(h, solver.dx, solver.options.diffusivity_m2_per_year * solver.law.dt)
    if not np.isfinite(diffused).all():
        raise StageError(f"erosion: hillslope diffusion blew up at step {s + 1} (non-finite heights)")
    volumes.diffusion_out -= float((diffused - h).sum()) * solver.cell_area
    return diffused


def _result(h: np.ndarray, height_start: np.ndarray, solver: _Solver, steps: int, volumes: _Volumes,
            breached_m3: float) -> StreamPowerResult:
    """The result and its stats: the mass balance down the flow paths and the volume budget."""
    v = volumes
    if solver.options.routing == "mfd":  # the net sources against what the flux carried to base level
        err = abs(v.exported - (v.out - v.landslide_direct)) / abs(v.exported) if v.exported else 0.0
    else:
        err = abs(v.eroded - (v.out - v.landslide_direct)) / v.eroded if v.eroded > 0 else 0.0
    dvol = float((h - height_start).sum()) * solver.cell_area
    vol_err = abs(dvol - (v.uplifted - v.out - v.diffusion_out + v.lake_fill)) / max(v.uplifted, v.out, 1e-300)
    return StreamPowerResult(h, steps, v.eroded, v.uplifted, v.out, err, v.worst_newton,
                             {"stream_power_steps": steps, "stream_power_dt_years": solver.law.dt,
                              "stream_power_volume_budget_relative_error": vol_err,
                              "stream_power_eroded_m3": v.eroded, "stream_power_uplifted_m3": v.uplifted,
                              "stream_power_out_m3": v.out, "stream_power_budget_relative_error": err,
                              "stream_power_newton_iterations_max": v.worst_newton,
                              "stream_power_routing": solver.options.routing, "stream_power_breached_m3": breached_m3,
                              "stream_power_k_used": solver.law.k,
                              "hillslope_diffusion_out_m3": v.diffusion_out, "lake_fill_m3": v.lake_fill,
                              "landslide_m3": v.landslide, "deposited_m3": v.deposited,
                              "deposition_iterations_max": v.deposit_iterations,
                              "deposition_residual_max_m": v.deposit_residual_m,
                              "sediment_flux_min_m3": v.flux_min})
