"""Host side of kernels.cl: the same functions and classes as reference.py,
run on the OpenCL device `env` (a pipeline.opencl.CL), which each takes
first; `on(env)` binds it, giving reference.py's signatures. Buffers of the
simulation and of the Poisson-disk sampler stay on the device across steps;
only results are copied back.

`local` is the work-group size (None: the runtime chooses); results do not
depend on it (the tests run several).
"""
from __future__ import annotations

import functools
import types
from pathlib import Path

import numpy as np

from pipeline.clhost import Buffers, kernel

from . import reference as ref

KERNELS = Path(__file__).with_name("kernels.cl")
F = np.float32


def on(env) -> types.SimpleNamespace:
    """This module's functions and classes on the device `env`, with the
    signatures of reference.py's (what the stage's backend is)."""
    names = ("attributes", "moisture_filter", "suitability", "splat", "Sim", "Poisson", "grass_tufts")
    return types.SimpleNamespace(**{n: functools.partial(globals()[n], env) for n in names})


def program(env, nb: int = 2):
    from pipeline.opencl import load_program

    return _Kernels(load_program(env, KERNELS, (f"-DNB={int(nb)}", f"-DPN={ref.PN}")))


class _Kernels:
    """Kernel objects of a program by attribute (pipeline.clhost.kernel)."""

    def __init__(self, prg):
        self.prg = prg

    def __getattr__(self, name):
        return kernel(self.prg, name)


def attributes(env, h, dx, kc, inv_kc2, dirs, steps, sun0, sun1, inv_direct, diffuse, local=None, window=None):
    b = Buffers(env)
    h = np.ascontiguousarray(h, F)
    w = ref.Window.whole(h.shape) if window is None else window
    win = w.args(h.shape)
    out_bytes = w.orows * w.ocols * 4
    nd = len(dirs)
    prg = program(env)
    hb = b.arr(h)
    sb = b.arr(np.ascontiguousarray(steps, F))
    hz = b.empty(nd * out_bytes)
    dirs = np.asarray(dirs, F)
    for d in range(nd):
        b.run(prg.horizon, (w.ocols, w.orows), local, hb, *win, F(dx), dirs[d, 0], dirs[d, 1],
              sb, np.int32(len(steps)), np.int32(d), hz)
    outs = [b.empty(out_bytes) for _ in range(6)]
    sun0 = np.ascontiguousarray(sun0, F).reshape(-1, 4)
    sun1 = np.ascontiguousarray(sun1, F).reshape(-1, 4)
    b.run(prg.shade, (w.ocols, w.orows), local, hb, *win, F(dx), np.int32(kc), F(inv_kc2), hz,
          np.int32(nd), b.arr(sun0), b.arr(sun1), np.int32(len(sun0)), F(inv_direct), F(diffuse), *outs)
    return tuple(b.get(o, (w.orows, w.ocols), F) for o in outs)


def moisture_filter(env, m, jitter, key, local=None, window=None):
    b = Buffers(env)
    m = np.ascontiguousarray(m, F)
    w = ref.Window.whole(m.shape) if window is None else window
    out = b.empty(w.orows * w.ocols * 4)
    b.run(program(env).moisture_filter, (w.ocols, w.orows), local, b.arr(m), *w.args(m.shape), F(jitter),
          np.uint32(key), out)
    return b.get(out, (w.orows, w.ocols), F)


def suitability(env, alt, slope, moist, sun, curv, blocked, prefs, local=None):
    b = Buffers(env)
    shape = np.shape(alt)
    n = int(np.prod(shape))
    prefs = np.ascontiguousarray(prefs, F).reshape(-1, 4)
    nsp = len(prefs) // ref.NPREF
    out = b.empty(max(nsp, 1) * n * 4)
    args = [b.arr(np.ascontiguousarray(a, F)) for a in (alt, slope, moist, sun, curv)]
    if nsp:
        b.run(program(env).suitability, (n,), local, *args, b.arr(np.ascontiguousarray(blocked, np.uint8)),
              np.int32(n), b.arr(prefs), np.int32(nsp), out)
    return b.get(out, (nsp,) + shape, F) if nsp else np.zeros((0,) + shape, F)


def splat(env, alt, slope, grad, moist, water, p, local=None):
    b = Buffers(env)
    shape = np.shape(alt)
    n = int(np.prod(shape))
    out = b.empty(n * 6 * 4)
    args = [b.arr(np.ascontiguousarray(a, F)) for a in (alt, slope, grad, moist)]
    b.run(program(env).splat, (n,), local, *args, b.arr(np.ascontiguousarray(water, np.uint8)), np.int32(n),
          b.arr(np.ascontiguousarray(p, F)), out)
    return b.get(out, shape + (6,), F)


class Sim:
    """reference.Sim on the device."""

    def __init__(self, env, sp, birth, suit, tab, nb: int, local=None):
        self.b = b = Buffers(env)
        sp = np.ascontiguousarray(sp, np.int32)
        self.nz, self.nx = sp.shape
        self.n = n = self.nx * self.nz
        suit = np.ascontiguousarray(suit, F)
        self.nsp = suit.shape[0]
        self.local = local
        self.local1 = None if local is None else (int(np.prod(local)),)
        self.prg = program(env, nb=nb)
        self.sp = b.arr(sp, True)
        self.birth = b.arr(np.ascontiguousarray(birth, np.int32), True)
        self.suit = b.arr(suit)
        self.tab = b.arr(np.ascontiguousarray(tab, F))
        self.mature = b.empty(self.nsp * n * 4)
        self.tmp = b.empty(self.nsp * n * 4)
        self.count = b.empty(self.nsp * n * 4)
        self.rec = b.empty(n * 16)
        self.st = [b.empty(n), b.empty(n)]
        self.mark = b.empty(n)
        self.cur = 0

    def seed_counts(self, t):
        b, p, n = self.b, self.prg, self.n
        b.run(p.sim_sources, (n,), self.local1, self.sp, self.birth, np.int32(n), np.int32(t), self.tab,
              np.int32(self.nsp), self.mature)
        # one work-item per line and species (the runtime picks the group: sums do not depend on it)
        b.run(p.box_sum, (self.nz, self.nsp), None, self.mature, np.int32(self.nx), np.int32(self.nz),
              np.int32(0), self.tab, np.int32(self.nsp), self.tmp)
        b.run(p.box_sum, (self.nx, self.nsp), None, self.tmp, np.int32(self.nx), np.int32(self.nz),
              np.int32(1), self.tab, np.int32(self.nsp), self.count)

    def update(self, t, stress, key):
        self.b.run(self.prg.sim_update, (self.n,), self.local1, self.sp, self.birth, self.suit, self.count,
                   np.int32(self.n), np.int32(t), F(stress), np.uint32(key), self.tab, np.int32(self.nsp))

    def thin_init(self, t):
        self.cur = 0
        self.b.run(self.prg.thin_init, (self.nx, self.nz), self.local, self.sp, self.birth, self.suit,
                   np.int32(self.nx), np.int32(self.nz), np.int32(t), self.tab, self.rec, self.st[0])

    def thin_round(self, t, rnd) -> int:
        b, p = self.b, self.prg
        st_in, st_out = self.st[self.cur], self.st[1 - self.cur]
        b.run(p.thin_mark, (self.nx, self.nz), self.local, self.rec, st_in, np.int32(self.nx), np.int32(self.nz),
              self.mark)
        b.run(p.thin_resolve, (self.nx, self.nz), self.local, self.rec, st_in, self.mark, np.int32(self.nx),
              np.int32(self.nz), np.int32(t), np.int32(rnd), self.tab, self.sp, st_out)
        self.cur = 1 - self.cur
        st = b.get(st_out, (self.n,), np.uint8)
        return int(np.count_nonzero(st == 1))

    def read(self):
        return (self.b.get(self.sp, (self.nz, self.nx), np.int32),
                self.b.get(self.birth, (self.nz, self.nx), np.int32))


class Poisson:
    """reference.Poisson on the device."""

    def __init__(self, env, nx, nz, c, wdom, ddom, rad, dx, margin, obs_start, obs, onx, onz, oc, ox0=0, oz0=0,
                 onwx=None, onwz=None, local=None, window=None, pts=None):
        self.b = b = Buffers(env)
        self.nx, self.nz = nx, nz
        self.local = local
        self.prg = program(env)
        rad = np.ascontiguousarray(rad, F)
        self.rows, self.cols = rad.shape
        self.win = ref.PointWindow.whole(nx, nz, rad.shape) if window is None else window
        start = np.zeros((self.win.wnz * self.win.wnx, 4), F) if pts is None else np.array(pts, F).reshape(-1, 4)
        self.pts = b.arr(start, True)
        self.rad = b.arr(rad)
        self.obs_start = b.arr(np.ascontiguousarray(obs_start, np.int32))
        self.obs = b.arr(np.ascontiguousarray(obs, F).reshape(-1, 4))
        self.fixed = (F(c), F(wdom), F(ddom))
        i32 = np.int32
        self.tail = (F(dx), F(margin), self.obs_start, self.obs, i32(onx), i32(onz), F(oc), i32(ox0), i32(oz0),
                     i32(onx if onwx is None else onwx), i32(onz if onwz is None else onwz))

    def phase(self, px, pz, pss, key):
        P = ref.PN + 1
        w = self.win
        xf, zf = w.first(px, pz)
        gx, gz = -(-(w.x0 + w.wnx - xf) // P), -(-(w.z0 + w.wnz - zf) // P)
        if gx <= 0 or gz <= 0:
            return
        c, wd, d = self.fixed
        i32 = np.int32
        self.b.run(self.prg.poisson_phase, (gx, gz), self.local, self.pts, i32(self.nx), i32(self.nz), i32(w.x0),
                   i32(w.z0), i32(w.wnx), i32(w.wnz), i32(xf), i32(zf), c, wd, d, np.uint32(pss), np.uint32(key),
                   self.rad, i32(self.rows), i32(self.cols), i32(w.trow0), i32(w.tcol0), i32(w.wrows),
                   i32(w.wcols), *self.tail)

    def read(self):
        pts = self.b.get(self.pts, (self.win.wnz * self.win.wnx, 4), F)
        pts[pts[:, 2] < 0] = 0.0  # cells the kernel marked as unusable are free cells
        return pts


def grass_tufts(env, dens, dx, nx, nz, sp, jitter, wdom, ddom, key, local=None, window=None):
    b = Buffers(env)
    dens = np.ascontiguousarray(dens, F)
    rows, cols = dens.shape
    w = ref.PointWindow.whole(nx, nz, dens.shape) if window is None else window
    out = b.empty(w.wnx * w.wnz * 16)
    i32 = np.int32
    b.run(program(env).grass_tufts, (w.wnx, w.wnz), local, b.arr(dens), i32(rows), i32(cols), i32(w.trow0),
          i32(w.tcol0), i32(w.wrows), i32(w.wcols), F(dx), i32(nx), i32(nz), i32(w.x0), i32(w.z0), i32(w.wnx),
          i32(w.wnz), F(sp), F(jitter), F(wdom), F(ddom), np.uint32(key), out)
    return b.get(out, (w.wnz * w.wnx, 4), F)
