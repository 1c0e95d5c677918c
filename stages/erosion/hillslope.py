"""Hillslope transport for geological time: linear diffusion dh/dt = D lap(h),
solved implicitly (backward Euler, stable at any step) with the isotropic
9-point Laplacian, so that it smooths every direction alike and prints no
grid marks (the 5-point stencil, and split x-then-y sweeps even more, damp
the diagonals differently from the axes).

The map edge is base level: its heights stay fixed. The change
delta = h' - h is then zero on the edge and solves (I - dt D L) delta =
dt D L h on the interior, which the type-I discrete sine transform
diagonalises exactly (the 9-point stencil is L = Lx + Ly + dx^2/6 Lx Ly):
one forward and one inverse transform per step, O(n log n), float64.
`reference_step` is the same solve by dense linear algebra for tests.

Threshold landsliding (`landslide`): no slope steeper than a critical
gradient. First the lower envelope of cones over 32 lattice directions
(`cone_envelope`, exact for that polygon metric; `landslide_reference`,
brute force, and `landslide_dijkstra`, a limit per cell, are its references
for tests), then its cones rounded (`round_cones`, an OpenCL kernel in
hillslope.cl; `round_cones_reference` is its numpy twin).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

KERNELS = Path(__file__).with_name("hillslope.cl")


def laplacian9(h: np.ndarray, dx: float) -> np.ndarray:
    """Isotropic 9-point Laplacian of the interior cells (edge rows and
    columns give 0): (4 (N+S+E+W) + (NE+NW+SE+SW) - 20 h) / (6 dx^2)."""
    h = np.asarray(h, np.float64)
    out = np.zeros_like(h)
    c = h[1:-1, 1:-1]
    axes = h[:-2, 1:-1] + h[2:, 1:-1] + h[1:-1, :-2] + h[1:-1, 2:]
    diag = h[:-2, :-2] + h[:-2, 2:] + h[2:, :-2] + h[2:, 2:]
    out[1:-1, 1:-1] = (4.0 * axes + diag - 20.0 * c) / (6.0 * dx * dx)
    return out


def _eigenvalues(rows: int, cols: int, dx: float) -> np.ndarray:
    ky = -4.0 / dx ** 2 * np.sin(np.pi * np.arange(1, rows - 1) / (2.0 * (rows - 1))) ** 2
    kx = -4.0 / dx ** 2 * np.sin(np.pi * np.arange(1, cols - 1) / (2.0 * (cols - 1))) ** 2
    ly, lx = ky[:, None], kx[None, :]
    return lx + ly + dx * dx / 6.0 * lx * ly


def step(h: np.ndarray, dx: float, diffusivity_dt_m2: float) -> np.ndarray:
    """Heights after one implicit step of D dt (m^2) of diffusion; edges fixed."""
    from scipy.fft import dstn, idstn

    h = np.asarray(h, np.float64)
    rows, cols = h.shape
    if diffusivity_dt_m2 <= 0 or rows < 3 or cols < 3:
        return h.copy()
    rhs = diffusivity_dt_m2 * laplacian9(h, dx)[1:-1, 1:-1]
    lam = _eigenvalues(rows, cols, dx)
    delta = idstn(dstn(rhs, type=1) / (1.0 - diffusivity_dt_m2 * lam), type=1)
    out = h.copy()
    out[1:-1, 1:-1] += delta
    return out


def reference_step(h: np.ndarray, dx: float, diffusivity_dt_m2: float) -> np.ndarray:
    """The same backward-Euler step by a dense solve (small grids only)."""
    h = np.asarray(h, np.float64)
    rows, cols = h.shape
    n = rows * cols
    op = np.zeros((n, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1.0
        op[:, i] = laplacian9(e.reshape(rows, cols), dx).ravel()
    a = np.eye(n) - diffusivity_dt_m2 * op
    return np.linalg.solve(a, h.ravel()).reshape(rows, cols)


# Threshold landsliding: no slope may exceed the critical gradient Sc. Heights
# become h'(x) = min over y of h(y) + Sc d(x, y) (the lower envelope of cones of
# slope Sc standing on every cell), the material above that envelope sliding
# away. d is the shortest path over the 32 lattice directions below (axes,
# diagonals, and the steps (1, 2), (1, 3), (2, 3) in every orientation;
# neighbouring directions span a unit cell, so every lattice vector is a
# whole-step combination of two), a polygon metric within 1.3 % of the
# Euclidean distance. Fewer directions leave their creases on the landscape:
# 8 give octagonal cones (8 % off), and even 16 crease every cone along the
# axes and diagonals, which measurably raises the grid anisotropy.
CONE_DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1), (1, 2), (2, 1), (1, -2), (2, -1),
                   (1, 3), (3, 1), (1, -3), (3, -1), (2, 3), (3, 2), (2, -3), (3, -2))
CONE_ROUNDS_MAX = 64
CONE_TOLERANCE_M = 1e-9  # a step this far over the limit is round-off, not a slope to cut
CONE_CHUNK_CELLS = 1 << 15  # padded line cells per chunk of the envelope sweep (a few 256 kB temporaries)
_LINES: dict = {}


def _lines(rows: int, cols: int, dr: int, dc: int) -> tuple[np.ndarray, np.ndarray]:
    """(lines, line_of): the flat cell indices of the grid's lines along
    (dr, dc), each from the grid's edge onward, padded with -1, shape
    (lines, length), int32 while the cells fit (half the cache's memory);
    and each cell's line (cached per shape)."""
    key = (rows, cols, dr, dc)
    if key in _LINES:
        return _LINES[key]
    r, c = np.divmod(np.arange(rows * cols), cols)
    back = np.full(r.size, rows * cols)  # steps back along the line before leaving the grid
    if dr > 0:
        back = np.minimum(back, r // dr)
    if dc > 0:
        back = np.minimum(back, c // dc)
    elif dc < 0:
        back = np.minimum(back, (cols - 1 - c) // -dc)
    start = (r - back * dr) * cols + (c - back * dc)
    first = np.zeros(r.size + 1, np.int64)  # the line of each start cell in the order of the starts, O(cells)
    first[1:] = np.cumsum(np.bincount(start, minlength=r.size) > 0)
    line = first[start + 1] - 1
    out = np.full((int(line.max()) + 1, int(back.max()) + 1), -1, np.int32 if r.size < 2 ** 31 else np.int64)
    out[line, back] = np.arange(r.size)
    _LINES[key] = (out, line.reshape(rows, cols))
    return _LINES[key]


def _too_steep(z: np.ndarray, dr: int, dc: int, rise) -> np.ndarray:
    """Cells (rows, cols) whose step to the neighbour at (dr, dc) climbs or
    drops more than rise (a number, or per cell: the step's limit is the
    mean of its two cells')."""
    rows, cols = z.shape
    c0, c1 = max(0, -dc), cols - max(0, dc)
    a = z[:rows - dr, c0:c1]
    b = z[dr:, c0 + dc:c1 + dc]
    if np.ndim(rise):
        rise = 0.5 * (rise[:rows - dr, c0:c1] + rise[dr:, c0 + dc:c1 + dc])
    bad = np.zeros(z.shape, bool)
    bad[:rows - dr, c0:c1] = np.abs(a - b) > rise + CONE_TOLERANCE_M
    return bad


def _cone_along(z: np.ndarray, lines: np.ndarray, hit: np.ndarray, rise) -> None:
    """On the lines `hit` of `lines`: z <- min over the cells y on the same line of z(y) + the summed rise
    of the steps between x and y, in place; z flat; rise a number, or per
    cell (flat; a step's rise is the mean of its two cells'). Lines are
    independent: they go in chunks of about CONE_CHUNK_CELLS, so the sweep's
    temporaries stay in the cache on any grid (one pass over every line would
    run from memory on big grids, its cost per cell growing with the grid)."""
    step = max(1, CONE_CHUNK_CELLS // max(lines.shape[1], 1))
    for i in range(0, hit.size, step):
        _cone_chunk(z, lines[hit[i:i + step]], rise)


def _cone_chunk(z: np.ndarray, lines: np.ndarray, rise) -> None:
    """_cone_along on one chunk of lines."""
    valid = lines >= 0
    zl = np.where(valid, z[np.maximum(lines, 0)], np.inf)
    if np.ndim(rise):
        r = np.where(valid, rise[np.maximum(lines, 0)], 0.0)
        t = np.zeros(lines.shape)
        np.cumsum(0.5 * (r[:, 1:] + r[:, :-1]), axis=1, out=t[:, 1:])
    else:
        t = np.arange(lines.shape[1], dtype=np.float64) * rise
    fwd = np.minimum.accumulate(zl - t, axis=1) + t
    bwd = np.minimum.accumulate((zl + t)[:, ::-1], axis=1)[:, ::-1] - t
    z[lines[valid]] = np.minimum(fwd, bwd)[valid]


def landslide(h: np.ndarray, dx: float, critical_slope, env=None, round_sweeps: int = 0) -> np.ndarray:
    """Heights with no slope steeper than critical_slope (m/m, a number or
    one per cell), float64, h' <= h (the difference is the landslide's
    material): the 32-direction cone envelope; with round_sweeps, its cones
    then rounded by that many sweeps on the OpenCL device env (None: by the
    numpy reference), and the envelope once more (the rounding's
    discretisation leaves a few of the longest steps, (2, 3) and its kin, up
    to 0.4 % over the limit, and those alone are cut)."""
    z = cone_envelope(h, dx, critical_slope)
    if round_sweeps <= 0:
        return z
    rise = np.broadcast_to(np.asarray(critical_slope, np.float64) * dx, z.shape)
    if env is not None:
        z = round_cones(env, z, rise, round_sweeps)
    else:
        z = round_cones_reference(z, rise, round_sweeps)
    return cone_envelope(z, dx, critical_slope)


def cone_envelope(h: np.ndarray, dx: float, critical_slope) -> np.ndarray:
    """Heights with no step along the 32 directions steeper than
    critical_slope (m/m): the lower envelope h'(x) = min_y h(y) + Sc d(x, y),
    d the 32-direction path length (float64; h' <= h). Sweeps of
    one-dimensional cone envelopes along each line family (only the lines
    holding a step steeper than the limit), repeated until no step is: each
    sweep is exact along its lines and the repeats compose the paths.
    critical_slope may vary per cell (an array of h's shape: rock that
    stands steeper or gentler); a step between two cells may then rise the
    mean of their limits times its length."""
    sc = np.asarray(critical_slope, np.float64)
    if not np.isfinite(sc).all() or (sc <= 0).any() or (sc.ndim and sc.shape != np.shape(h)):
        raise ValueError("landslide: the critical slope must be positive and finite (a number or one per cell)")
    z = np.array(h, np.float64)
    rows, cols = z.shape
    flat = z.ravel()
    for _ in range(CONE_ROUNDS_MAX):
        changed = False
        for dr, dc in CONE_DIRECTIONS:
            if dr >= rows or abs(dc) >= cols:
                continue
            rise = sc * (dx * math.hypot(dr, dc))
            bad = _too_steep(z, dr, dc, rise)
            if not bad.any():
                continue
            lines, line_of = _lines(rows, cols, dr, dc)
            hit = np.flatnonzero(np.bincount(line_of[bad], minlength=lines.shape[0]))  # sorted, O(cells)
            _cone_along(flat, lines, hit, rise.ravel() if rise.ndim else float(rise))
            changed = True
        if not changed:
            break
    return z


# The cones' rounding (erosion.landslide_round_sweeps; off by default). The polygon metric's cones are pyramids
# of 32 planar faces; a landscape at its threshold slope is made of them, and on a close hillshade a big cone
# shows as a fan of facets whose creases run along the lattice directions. The envelope of round cones is the
# largest u <= h with |grad u| <= Sc, the viscosity solution of the eikonal equation with h as obstacle: Jacobi
# sweeps of the Godunov upwind update (axis and diagonal stencils, the lower), started from the polygon
# envelope (an upper bound within 1.3 %), lower it toward that, a cell further from each foot per sweep
# (converging takes as many sweeps as the longest hillslope has cells: 100 to 200 per geological step on the
# default world). Within the sweeps' reach a round cone lies within 0.8 % of Sc r and its slope points within
# 3 degrees of the radius (the polygon's: 1.3 % and 9 degrees; bench.landslide). What it does to the grid
# anisotropy of the 2-to-16-cell band is mixed, which is why it is off: the default world (8 m cells) goes from
# 0.92 to 1.17 after 32 sweeps (the edge of the rounded zone), 0.99 after 128, 1.06 converged; a 1 km world at
# 1 m under an 8 m geology from 1.35 to 1.05 after 32 (0.98 converged); the open world at 1 m from 1.63 to
# 1.54 after 32, while its 8 m block means go from 1.05 to 1.14. A cell's own limit bounds it above its lowest
# neighbours (the envelope's step limit is the mean of the step's two cells').
SQRT2 = 1.4142135623730951


def _eikonal_arm(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The Godunov update from the lower neighbours a and b of one stencil's two axes, step rise s."""
    with np.errstate(invalid="ignore"):
        d = np.abs(a - b)
        q = 0.5 * (a + b + np.sqrt(np.maximum(2.0 * s * s - d * d, 0.0)))
        out = np.where(d >= s, np.minimum(a, b) + s, q)
    return np.where(np.isinf(a) & np.isinf(b), np.inf, out)


def round_cones_reference(z: np.ndarray, rise: np.ndarray, sweeps: int) -> np.ndarray:
    """round_cones in numpy: z the cone envelope, rise Sc dx per cell."""
    u = np.array(z, np.float64)
    s = np.asarray(rise, np.float64)
    s2 = s * SQRT2
    for _ in range(sweeps):
        p = np.pad(u, 1, constant_values=np.inf)
        axis = _eikonal_arm(np.minimum(p[1:-1, :-2], p[1:-1, 2:]), np.minimum(p[:-2, 1:-1], p[2:, 1:-1]), s)
        diag = _eikonal_arm(np.minimum(p[:-2, :-2], p[2:, 2:]), np.minimum(p[:-2, 2:], p[2:, :-2]), s2)
        u = np.minimum(u, np.minimum(axis, diag))
    return u


def round_cones(env, z: np.ndarray, rise: np.ndarray, sweeps: int) -> np.ndarray:
    """The cone envelope z's cones rounded on the OpenCL device env (hillslope.cl), rise Sc dx per cell."""
    import pyopencl as cl

    from pipeline.opencl import load_program

    if "cl_khr_fp64" not in env.device.extensions:
        raise RuntimeError(f"landslide: rounding the cones needs double precision, which {env.device.name} lacks")
    kernel = cl.Kernel(load_program(env, KERNELS), "round_cones")
    rows, cols = z.shape
    mf, q = cl.mem_flags, env.queue
    padded = np.pad(np.asarray(z, np.float64), 1, constant_values=np.inf)  # both buffers keep the +inf border
    bufs = [cl.Buffer(env.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=padded) for _ in range(2)]
    d_rise = cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(rise, np.float64))
    for _ in range(sweeps):
        kernel.set_args(bufs[0], bufs[1], d_rise, np.int32(rows), np.int32(cols))
        cl.enqueue_nd_range_kernel(q, kernel, (cols, rows), None)
        bufs.reverse()
    cl.enqueue_copy(q, padded, bufs[0])
    return padded[1:-1, 1:-1].copy()


def cone_distance(vr: int, vc: int) -> float:
    """The 32-direction path length of the lattice step (vr, vc), in cells:
    the cheapest non-negative combination of two neighbouring directions."""
    dirs = [(a * sr, b * sc) for a, b in CONE_DIRECTIONS for sr, sc in ((1, 1), (-1, -1))]
    best = math.inf
    for i, (ar, ac) in enumerate(dirs):
        for br, bc in dirs[i:]:
            det = ar * bc - ac * br
            if det == 0:
                if vr * ac == vc * ar and vr * ar + vc * ac >= 0:
                    s = (vr * ar + vc * ac) / (ar * ar + ac * ac)
                    best = min(best, s * math.hypot(ar, ac))
                continue
            alpha = (vr * bc - vc * br) / det
            beta = (ar * vc - ac * vr) / det
            if alpha >= -1e-12 and beta >= -1e-12:
                best = min(best, alpha * math.hypot(ar, ac) + beta * math.hypot(br, bc))
    return best


def landslide_dijkstra(h: np.ndarray, dx: float, critical_slope: np.ndarray) -> np.ndarray:
    """The envelope for a limit per cell by Dijkstra's shortest paths (small
    grids): every cell starts at its height, each of the 32 lattice steps
    costs the mean of its two cells' limits times its length."""
    import heapq

    h = np.asarray(h, np.float64)
    sc = np.broadcast_to(np.asarray(critical_slope, np.float64), h.shape)
    rows, cols = h.shape
    best = h.copy()
    heap = [(best[r, c], r, c) for r in range(rows) for c in range(cols)]
    heapq.heapify(heap)
    steps = [(a * s, b * s) for a, b in CONE_DIRECTIONS for s in (1, -1)]
    while heap:
        v, r, c = heapq.heappop(heap)
        if v > best[r, c]:
            continue
        for dr, dc in steps:
            y, x = r + dr, c + dc
            if 0 <= y < rows and 0 <= x < cols:
                w = v + 0.5 * (sc[r, c] + sc[y, x]) * dx * math.hypot(dr, dc)
                if w < best[y, x]:
                    best[y, x] = w
                    heapq.heappush(heap, (w, y, x))
    return best


def landslide_reference(h: np.ndarray, dx: float, critical_slope: float) -> np.ndarray:
    """The same envelope by brute force over every pair of cells (small grids)."""
    h = np.asarray(h, np.float64)
    rows, cols = h.shape
    d = {}
    out = h.copy()
    for r in range(rows):
        for c in range(cols):
            for y in range(rows):
                for x in range(cols):
                    key = (r - y, c - x)
                    if key not in d:
                        d[key] = cone_distance(*key)
                    out[r, c] = min(out[r, c], h[y, x] + critical_slope * dx * d[key])
    return out
