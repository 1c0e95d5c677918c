"""The simulation state resident on the OpenCL device, and the kernel launches.

Only diagnostics (a few numbers per row, every few steps) and the final maps
are copied back to the host. Arrays carry a one-cell halo ring (see kernels.cl)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.opencl import CachedKernel, global_size, load_program, x86_avx512

from .physics import G, THERMAL_C, Physics, StepConstants, talus_thresholds
from .state import Diag

KERNELS = Path(__file__).parent / "kernels.cl"
KERNEL_NAMES = ("flux", "update", "boundary_out", "halo", "thermal_send", "thermal_apply", "diag_rows",
                "velocity")
X0 = 16  # padded column of cell column 0 (the west halo at X0 - 1): rows of cells start on 64 bytes
ALIGN = 16  # the pitch is a multiple of this many floats (64 bytes)
VW_THERMAL = 8  # cells per work-item of the talus rule (float8: the fastest on PoCL/AVX-512, bench/erosion.py)
DEFAULT_LOCAL = (8, 1)  # work-items per work-group: the fastest on PoCL; results do not depend on it


def step_vector_width(device) -> int:
    """Cells per vector of the storm kernels: 16 where the device prefers
    16-wide floats (AVX-512, where 16 lanes beat 8), else 8."""
    return 16 if device.preferred_vector_width_float >= 16 else 8


def storm_tile(device) -> tuple[int, int]:
    """The tile of one storm work-item (see kernels.cl): (rows, most vectors
    along a row; the tile is the grid's width up to this). On a CPU 16 rows,
    where cells share faces and sediment per discharge with the row above, by 128 vectors (2048
    cells: whole rows of the bench's grids; the AVX-512 body is a call whose
    ~30 arguments are paid once per tile); on a GPU, which wants many
    work-items, 1 by 1."""
    import pyopencl as cl

    return (16, 128) if device.type & cl.device_type.CPU else (1, 1)



def program(env, boundary_code: int, vw: int, nv: int = 1, avx512: bool = False, nr: int = 1):
    options = (f"-DBOUNDARY={boundary_code}", f"-DVW={vw}", f"-DNV={nv}", f"-DNR={nr}", f"-DX0={X0}")
    return load_program(env, KERNELS, options + (("-DX86_AVX512=1",) if avx512 else ()))


def pad(a: np.ndarray, periodic: bool, shape: tuple[int, int]) -> np.ndarray:
    """The array in the padded layout of `shape`: the cells at [1:rows+1, X0:X0+cols],
    the halo ring around them wrapped for periodic grids, zeros elsewhere."""
    a = np.asarray(a, np.float32)
    out = np.zeros(shape, np.float32)
    rows, cols = a.shape
    out[: rows + 2, X0 - 1: X0 + cols + 1] = np.pad(a, 1, mode="wrap" if periodic else "constant")
    return out


class DeviceSim:
    """One erosion simulation on the OpenCL device `env` (a
    pipeline.opencl.CL; the stage's ctx.cl). `local` is the work-group size
    (work-items along a row, rows) of the per-cell kernels, each work-item
    handling `vw` cells of a row (default: 16 or 8 for the storm, 8 for the
    talus rule), in the storm a tile of `nr` rows of up to `nv` vectors
    along a row (default 16 rows of 128 on a CPU, with one work-item per
    work-group along the row, 1 by 1 on a GPU); `avx512`
    compiles the storm for AVX-512 (default: where pipeline.opencl.x86_avx512
    allows). Results depend on none of these."""

    def __init__(self, env, height: np.ndarray, ph: Physics, *, local: tuple[int, int] | None = DEFAULT_LOCAL,
                 water: np.ndarray | None = None, sediment: np.ndarray | None = None,
                 change: np.ndarray | None = None, vw: int | None = None,
                 nv: int | None = None, avx512: bool | None = None, nr: int | None = None, thermal_only: bool = False):
        import pyopencl as cl

        self.cl = env
        self.ph = ph
        self.rows, self.cols = height.shape
        self.n = self.rows * self.cols
        self.periodic = ph.boundary == "periodic"
        self.open = ph.boundary == "open"
        self.local = tuple(local) if local is not None else DEFAULT_LOCAL
        # cells per work-item: vw for every kernel when given, else the device's best
        self.vw = vw if vw is not None else step_vector_width(self.cl.device)
        self.vw_thermal = vw if vw is not None else VW_THERMAL
        tile_rows, tile_vectors = storm_tile(self.cl.device)
        self.nv = nv if nv is not None else tile_vectors
        self.nr = nr if nr is not None else tile_rows
        self.avx512 = x86_avx512(self.cl.device) if avx512 is None else bool(avx512)
        # whole work-groups of work-items, each handling vw * nv (storm) or vw_thermal cells of a row
        # a storm work-item that is already a long loop runs alone in its work-group: the padding
        # of a row stays under one work-item (vw * nv cells)
        self.local_storm = self.local if self.nv == 1 else (1, self.local[1])
        self.tile_vectors = min(-(-self.cols // self.vw), self.nv)  # as TILE_VECTORS in kernels.cl
        self.gsize = global_size((-(-self.cols // (self.vw * self.tile_vectors)), -(-self.rows // self.nr)),
                                 self.local_storm)
        self.gsize_th = global_size((-(-self.cols // self.vw_thermal), self.rows), self.local)
        # padded layout: every lane of every work-item of both has its cell and its halo,
        # and every row of cells starts on 64 bytes (see kernels.cl)
        self.pitch = -(-(X0 + max(self.gsize[0] * self.vw * self.tile_vectors, self.gsize_th[0] * self.vw_thermal) + 1)
                       // ALIGN) * ALIGN
        self.prows = max(self.gsize[1] * self.nr, self.gsize_th[1]) + 2
        self.gsize1 = global_size((self.cols, self.rows), (16, 1))  # scalar 2-D kernels (guarded)
        prg = program(env, ph.boundary_code, self.vw, self.nv, self.avx512, self.nr)
        prg_th = program(env, ph.boundary_code, self.vw_thermal)
        # launched thousands of times with mostly the same arguments: set only what changed
        self.k = {name: CachedKernel(prg_th if name.startswith("thermal") else prg, name) for name in KERNEL_NAMES}
        ctx = self.cl.ctx
        self.queue = self.cl.queue
        mf = cl.mem_flags
        self.npad = self.prows * self.pitch

        def buf(a):
            return cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))

        shape = (self.rows, self.cols)
        zeros = np.zeros(shape, np.float32)
        w0 = zeros if water is None else np.asarray(water, np.float32)
        s0 = zeros if sediment is None else np.asarray(sediment, np.float32)
        P = lambda a: pad(a, self.periodic, (self.prows, self.pitch))  # noqa: E731
        pz = P(zeros)
        self.Tb = buf(P(height))
        # change: a run resumed from an earlier one's dT (the tiled talus rule's rounds)
        pd = pz if change is None else P(change)
        self.dT = [buf(pd), buf(pd)]
        pw = pz if water is None else P(w0)
        self.tmp = buf(pz)  # thermal send factors s
        self.tmp2 = buf(pz)  # thermal receiver shares r
        if thermal_only:  # the talus rule alone (the tiled rounds): no storm state
            self.W = [buf(pw)]
            self._scalars(ph)
            return
        self.W = [buf(pw), buf(pw)]
        ps = pz if sediment is None else P(s0)
        self.S = [buf(ps), buf(ps)]
        self.M = buf(pz)
        self.EA = buf(pz)
        self.Q = [buf(pz) for _ in range(4)]
        self.wave = buf(P(np.sqrt(np.float32(G) * w0).astype(np.float32)))  # CFL speed per cell
        self.nfaces = 2 * (self.rows + self.cols)
        self.bnd = buf(np.zeros(2 * self.nfaces, np.float64))
        self.sums = cl.Buffer(ctx, mf.READ_WRITE, 8 * 5 * self.rows)
        self.mx = cl.Buffer(ctx, mf.READ_WRITE, 4 * 5 * self.rows)
        self._scalars(ph)

    def _scalars(self, ph: Physics) -> None:
        self.cd = 0  # which dT buffer is current (thermal flips only this one)
        self.cw = 0  # which W and S buffers are current
        self.t_ax, self.t_dg = talus_thresholds(ph)
        self.R, self.C, self.P = np.int32(self.rows), np.int32(self.cols), np.int32(self.pitch)

    # -- kernels -----------------------------------------------------------
    def _run(self, name: str, *args) -> None:
        gsize = self.gsize_th if name.startswith("thermal") else self.gsize
        local = self.local if name.startswith("thermal") else self.local_storm
        self.k[name](self.queue, gsize, local, *args)

    def _halo(self, *bufs) -> None:
        if not self.periodic:
            return
        b = list(bufs) + [bufs[0]] * (4 - len(bufs))
        n = self.rows + self.cols + 2
        self.k["halo"](self.queue, (n,), None, *b, np.int32(len(bufs)), self.R, self.C, self.P)

    def _flux(self, k: StepConstants, Q, wave, want_wave: bool) -> None:
        """The flux kernel on the current state, updating the pipes Q in place."""
        self._run("flux", self.Tb, self.dT[self.cd], self.W[self.cw], *Q, wave, self.R, self.C, self.P,
                  k.g_dt_dx, k.fric_dt, k.dx_dt, np.int32(want_wave), np.float32(G))

    def _update(self, k: StepConstants, Q, M, EA, dT_out, W_out, S_out) -> None:
        """The update kernel on the current state and pipes Q, writing the new dT, W, S."""
        d, w = self.cd, self.cw
        self._run("update", self.Tb, self.dT[d], self.W[w], self.S[w], *Q, M, EA, dT_out, W_out, S_out,
                  self.R, self.C, self.P, k.c_dt_dx, k.kc, k.sin_min2, k.ks_f, k.kd_f, k.rain_dt, k.evap_dt,
                  k.inv_wet, k.am, k.four_dx2)

    def step(self, k: StepConstants, want_wave: bool = False) -> None:
        d, w = self.cd, self.cw
        R, C, P = self.R, self.C, self.P
        self._flux(k, self.Q, self.wave, want_wave)
        self._halo(*self.Q)
        self._update(k, self.Q, self.M, self.EA, self.dT[1 - d], self.W[1 - w], self.S[1 - w])
        if self.open:
            self.k["boundary_out"](self.queue, (self.nfaces,), None, self.W[w], self.S[w], *self.Q,
                                   self.bnd, R, C, P, k.c_dt_dx)
        self.cd, self.cw = 1 - d, 1 - w
        self._halo(self.dT[self.cd], self.W[self.cw], self.S[self.cw])

    def thermal(self, iterations: int, wet_min: float = -1.0, cfrac: float = THERMAL_C) -> None:
        """Iterations of the talus rule (Olsen's c = cfrac); with wet_min >= 0
        material only slides into cells holding more water than that (bank slumping)."""
        R, C, P = self.R, self.C, self.P
        wm = np.float32(wet_min)
        W = self.W[self.cw]
        for _ in range(iterations):
            a, b = self.cd, 1 - self.cd
            self._run("thermal_send", self.Tb, self.dT[a], W, self.tmp, self.tmp2, R, C, P, self.t_ax, self.t_dg,
                      np.float32(cfrac), wm)
            self._halo(self.tmp, self.tmp2)
            self._run("thermal_apply", self.Tb, self.dT[a], W, self.tmp, self.tmp2, self.dT[b], R, C, P,
                      self.t_ax, self.t_dg, wm)
            self.cd = b
            self._halo(self.dT[b])

    def diag(self) -> Diag:
        import pyopencl as cl

        self.k["diag_rows"](self.queue, (self.rows,), None, self.dT[self.cd], self.W[self.cw], self.S[self.cw],
                            *self.Q, self.EA, self.wave, self.sums, self.mx, self.R, self.C, self.P)
        sums = np.empty((self.rows, 5), np.float64)
        mx = np.empty((self.rows, 5), np.float32)
        bnd = np.empty(2 * self.nfaces, np.float64)
        cl.enqueue_copy(self.queue, sums, self.sums)
        cl.enqueue_copy(self.queue, mx, self.mx)
        cl.enqueue_copy(self.queue, bnd, self.bnd)
        return Diag.from_rows(sums, mx, bnd.reshape(2, self.nfaces))

    def finish(self) -> None:
        self.queue.finish()

    def index(self, r: int, c: int) -> int:
        """Position of cell (r, c) in a padded buffer (floats)."""
        return (r + 1) * self.pitch + X0 + c

    def _read(self, b) -> np.ndarray:
        import pyopencl as cl

        arr = np.empty(self.npad, np.float32)
        cl.enqueue_copy(self.queue, arr, b)
        return arr.reshape(self.prows, self.pitch)[1:self.rows + 1, X0:X0 + self.cols].copy()

    def change(self) -> np.ndarray:
        """dT alone: the terrain's change so far."""
        return self._read(self.dT[self.cd])

    def fields(self) -> dict[str, np.ndarray]:
        import pyopencl as cl

        out = {name: self._read(b) for name, b in
               (("dT", self.dT[self.cd]), ("W", self.W[self.cw]), ("S", self.S[self.cw]), ("M", self.M))}
        mf = cl.mem_flags
        VX = cl.Buffer(self.cl.ctx, mf.READ_WRITE, 4 * self.npad)
        VZ = cl.Buffer(self.cl.ctx, mf.READ_WRITE, 4 * self.npad)
        self.k["velocity"](self.queue, self.gsize1, (16, 1), *self.Q, self.W[self.cw], VX, VZ, self.R, self.C, self.P)
        out["vx"], out["vz"] = self._read(VX), self._read(VZ)
        out["F"] = np.stack([self._read(q) for q in self.Q], axis=-1)
        return out
