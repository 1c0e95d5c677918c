"""Plain numpy implementation of kernels.cl, for tests on small grids.

Every function mirrors one kernel operation by operation in float32 (the
kernels switch fma contraction off), so on a conforming OpenCL device the
two agree to the bit; only slope and aspect use library functions (atan,
atan2) and agree within a few ulps. The functions have the same signatures
as the device versions in device.py, so the host code (ecosystem.py,
placement.py, grass.py) runs on either.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from worldlib.hashing import hash4, mix32, stream_key, uniform, unit  # noqa: F401 (the stage's callers use ref.*)

# Every function and class here has the signature of its twin in device.py,
# so a caller picks either module and calls it the same way; `local` (the
# work-group size) is accepted and means nothing here.

F = np.float32
U = np.uint32
RAD2DEG = F(57.29577951)
SPW = 12  # floats per species in the simulation table
NPREF = 5
PN = 3  # Poisson neighbourhood (cells) and phase period PN + 1


# hashing (hash4, unit, stream_key, uniform): worldlib.hashing, the twins of the kernels' hash4 and unit


# --------------------------------------------------------------------------- helpers

def clamp01(x):
    return np.minimum(np.maximum(x, F(0)), F(1))


def sstep(e0, inv, x):
    t = clamp01((x - F(e0)) * F(inv))
    return t * t * (F(3) - F(2) * t)


class Window(NamedTuple):
    """Where an array sits in the world grid, and which of its cells a
    kernel computes: the array's first cell is the world's (row0, col0), the
    world is wrows x wcols, and the orows x ocols cells from (orow, ocol) of
    the array are computed. A tile read with a halo (pipeline.tiles.Tile) is
    Window.of(tile, halo); kernels taking one clamp in world cells, so with a
    wide enough halo a tile gets the bits of the whole world's run."""
    row0: int
    col0: int
    wrows: int
    wcols: int
    orow: int
    ocol: int
    orows: int
    ocols: int

    @staticmethod
    def whole(shape) -> "Window":
        return Window(0, 0, int(shape[0]), int(shape[1]), 0, 0, int(shape[0]), int(shape[1]))

    @staticmethod
    def of(tile, halo: int) -> "Window":
        r0, c0, _, _ = tile.window(halo)
        rows, cols = tile.inner(halo)
        return Window(r0, c0, *tile.world_shape, rows.start, cols.start, tile.rows, tile.cols)

    def margin(self, shape) -> int:
        """The fewest cells the array holds beyond the output on a side
        where it stops short of the world's border (what a kernel may reach)."""
        sides = ((self.orow, self.row0 + self.orow), (self.ocol, self.col0 + self.ocol),
                 (shape[0] - self.orow - self.orows, self.wrows - (self.row0 + self.orow + self.orows)),
                 (shape[1] - self.ocol - self.ocols, self.wcols - (self.col0 + self.ocol + self.ocols)))
        return min((held for held, to_border in sides if held < to_border), default=1 << 30)

    def args(self, shape) -> tuple:
        """The kernels' WINDOW_ARGS and output window, as int32."""
        return tuple(np.int32(v) for v in (shape[0], shape[1], self.row0, self.col0, self.wrows, self.wcols,
                                           self.orow, self.ocol, self.orows, self.ocols))


def _world_at(h, w: Window, r, c):
    return h[np.clip(r, 0, w.wrows - 1) - w.row0, np.clip(c, 0, w.wcols - 1) - w.col0]


def _world_bilinear(h, w: Window, fr, fc):
    r0f, c0f = np.floor(fr), np.floor(fc)
    tr, tc = fr - r0f, fc - c0f
    r0, c0 = r0f.astype(np.int64), c0f.astype(np.int64)
    a = _world_at(h, w, r0, c0)
    b = _world_at(h, w, r0, c0 + 1)
    c = _world_at(h, w, r0 + 1, c0)
    d = _world_at(h, w, r0 + 1, c0 + 1)
    top = a + (b - a) * tc
    bot = c + (d - c) * tc
    return top + (bot - top) * tr


# --------------------------------------------------------------------------- attributes

def attributes(h, dx, kc, inv_kc2, dirs, steps, sun0, sun1, inv_direct, diffuse, local=None, window=None):
    """The attributes kernels: (slope deg, aspect deg, gradient m/m,
    curvature 1/m, sky view, sunlight), each float32 of the world `h`, or
    of the output cells of `window` (a Window; h its array)."""
    h = np.asarray(h, F)
    w = Window.whole(h.shape) if window is None else window
    dx = F(dx)
    r = w.row0 + w.orow + np.arange(w.orows)[:, None] + np.zeros((1, w.ocols), np.int64)  # world cells
    c = w.col0 + w.ocol + np.arange(w.ocols)[None, :] + np.zeros((w.orows, 1), np.int64)
    h0 = _world_at(h, w, r, c)
    cl, cr = np.maximum(c - 1, 0), np.minimum(c + 1, w.wcols - 1)
    ru, rd = np.maximum(r - 1, 0), np.minimum(r + 1, w.wrows - 1)
    gx = (_world_at(h, w, r, cr) - _world_at(h, w, r, cl)) / ((cr - cl).astype(F) * dx)
    gz = (_world_at(h, w, rd, c) - _world_at(h, w, ru, c)) / ((rd - ru).astype(F) * dx)
    g = np.sqrt(gx * gx + gz * gz)
    slope = np.arctan(g) * RAD2DEG
    asp = np.arctan2(-gx, gz) * RAD2DEG
    aspect = np.where(asp < F(0), asp + F(360), asp)
    lap = _world_at(h, w, r, c + kc) + _world_at(h, w, r, c - kc)
    lap = lap + _world_at(h, w, r + kc, c)
    lap = lap + _world_at(h, w, r - kc, c)
    lap = lap - F(4) * h0
    curv = lap * F(inv_kc2)

    nd = len(dirs)
    shape = (w.orows, w.ocols)
    hz = np.zeros((nd,) + shape, F)
    svf = np.zeros(shape, F)
    cf, rf = c.astype(F), r.astype(F)
    for d in range(nd):
        ex, ez = F(dirs[d][0]), F(dirs[d][1])
        tmax = np.zeros(shape, F)
        active = np.ones(shape, bool)
        for s in steps:
            s = F(s)
            fc = cf + s * ex
            fr = rf - s * ez
            active &= ~((fc < F(0)) | (fr < F(0)) | (fc > F(w.wcols - 1)) | (fr > F(w.wrows - 1)))
            if not active.any():
                break
            t = (_world_bilinear(h, w, np.where(active, fr, rf), np.where(active, fc, cf)) - h0) / (s * dx)  # in the window
            tmax = np.where(active, np.maximum(tmax, t), tmax)
        hz[d] = tmax
        svf = svf + F(1) / (F(1) + tmax * tmax)
    svf = svf / F(nd)

    nn = np.sqrt(gx * gx + gz * gz + F(1))
    nx, ny, nz = -gx / nn, F(1) / nn, -gz / nn
    direct = np.zeros(shape, F)
    for k in range(len(sun0)):
        s0, s1 = np.asarray(sun0[k], F), np.asarray(sun1[k], F)
        a0 = np.floor(s1[0])
        f = s1[0] - a0
        d0 = int(a0) % nd
        d1 = (d0 + 1) % nd
        th = hz[d0] + (hz[d1] - hz[d0]) * f
        cosi = nx * s0[0] + ny * s0[1]
        cosi = cosi + nz * s0[2]
        lit = (s1[1] > th) & (cosi > F(0))
        direct = np.where(lit, direct + s0[3] * cosi, direct)
    sunlight = (F(1) - F(diffuse)) * (direct * F(inv_direct)) + F(diffuse) * svf
    return slope, aspect, g, curv, svf, sunlight


def moisture_filter(m, jitter, key, local=None, window=None):
    """The filtered moisture of the world `m`, or of the output cells of
    `window` (a Window; m its array): the jitter and the clamping are the
    world cell's."""
    m = np.asarray(m, F)
    w = Window.whole(m.shape) if window is None else window
    r = w.row0 + w.orow + np.arange(w.orows, dtype=np.int64)[:, None]  # world cells
    c = w.col0 + w.ocol + np.arange(w.ocols, dtype=np.int64)[None, :]
    i = r * w.wcols + c
    jx = (uniform(key, i, 0, 0) - F(0.5)) * F(2) * F(jitter)
    jz = (uniform(key, i, 1, 0) - F(0.5)) * F(2) * F(jitter)
    fr = r.astype(F) + jz
    fc = c.astype(F) + jx
    one = F(1)
    diag = _world_bilinear(m, w, fr - one, fc - one)
    diag = diag + _world_bilinear(m, w, fr - one, fc + one)
    diag = diag + _world_bilinear(m, w, fr + one, fc - one)
    diag = diag + _world_bilinear(m, w, fr + one, fc + one)
    axial = _world_bilinear(m, w, fr - one, fc)
    axial = axial + _world_bilinear(m, w, fr + one, fc)
    axial = axial + _world_bilinear(m, w, fr, fc - one)
    axial = axial + _world_bilinear(m, w, fr, fc + one)
    return (F(4) * _world_at(m, w, r, c) + F(2) * diag + axial) * F(0.0625)


def moisture_filter_halo(jitter: float) -> int:
    """The cells around a tile the moisture filter reads: the jitter (cells)
    and the neighbour's bilinear."""
    return int(np.ceil(jitter)) + 2


# --------------------------------------------------------------------------- suitability and splat

def _ramp(d, inv):
    if inv > 0:
        t = clamp01(d * F(inv))
        return t * t * (F(3) - F(2) * t)
    return np.where(d > F(0), F(1), F(0)).astype(F)


def suitability(alt, slope, moist, sun, curv, blocked, prefs, local=None):
    """prefs: (nsp, NPREF, 4) float32 (min, max, inv_edge, 0). Returns (nsp, ...)."""
    v = [np.asarray(a, F) for a in (alt, slope, moist, sun, curv)]
    out = np.zeros((len(prefs),) + v[0].shape, F)
    for s, sp in enumerate(np.asarray(prefs, F)):
        f = np.ones(v[0].shape, F)
        for k in range(NPREF):
            lo, hi, inv = sp[k, 0], sp[k, 1], sp[k, 2]
            f = f * (_ramp(v[k] - lo, inv) * _ramp(hi - v[k], inv))
        out[s] = np.where(blocked != 0, F(0), f)
    return out


def splat(alt, slope, grad, moist, water, p, local=None):
    """p: 19 float32 (see kernels.cl). Returns (..., 6): rock, scree, grass, dry_grass, mud, snow."""
    a, s, m, g = (np.asarray(x, F) for x in (alt, slope, moist, grad))
    p = np.asarray(p, F)
    ny = F(1) / np.sqrt(F(1) + g * g)
    melt = np.maximum(m * p[4] - (F(1) - ny), F(0))
    f_snow = clamp01(sstep(p[0], p[1], a) * (F(1) - sstep(p[2], p[3], s)) - melt)
    f_rock = clamp01(sstep(p[5], p[6], s) + sstep(p[7], p[8], a))
    f_scree = sstep(p[9], p[10], s)
    f_mud = np.maximum(sstep(p[11], p[12], m) * (F(1) - sstep(p[13], p[14], s)) - F(0.5) * f_rock, F(0))
    green = np.maximum(sstep(p[15], p[16], m), sstep(p[17], p[18], a))
    rem = np.ones_like(a)
    snow = f_snow * rem
    rem = rem - snow
    rock = f_rock * rem
    rem = rem - rock
    scree = f_scree * rem
    rem = rem - scree
    mud = f_mud * rem
    rem = rem - mud
    grass = green * rem
    rem = rem - grass
    dry = rem
    out = np.stack([rock, scree, grass, dry, mud, snow], axis=-1)
    w = np.asarray(water) != 0
    out[w] = np.array([0, 0, 0, 0, 1, 0], F)
    return out


def seed004_sum(alt, slope, grad, moist, p):
    """The thesis's own coefficients (seed 004 algorithm 3, unperturbed
    normals), before any fix: their sum, which can exceed 1 (mud is never
    limited by snow). For the diagnostics only."""
    a, s, m, g = (np.asarray(x, np.float64) for x in (alt, slope, moist, grad))
    p = np.asarray(p, np.float64)

    def ss(e0, inv, x):
        t = np.clip((x - e0) * inv, 0, 1)
        return t * t * (3 - 2 * t)
    ny = 1 / np.sqrt(1 + g * g)
    f_snow = np.clip(ss(p[0], p[1], a) - (1 - (1 - ss(p[2], p[3], s))) - np.maximum(m * p[4] - (1 - ny), 0), 0, 1)
    f_rock = np.clip(ss(p[5], p[6], s) + ss(p[7], p[8], a), 0, 1)
    f_mud = np.maximum(np.clip(m * 0.7 * 2.0 - (1 - ny), 0, 1) - 0.5 * f_rock, 0)
    f_rock = np.clip(f_rock - (f_snow + f_mud), 0, 1)
    f_gl = np.clip(1 - (np.clip(10 * m - f_rock, 0, 1) ** 2 + f_rock + f_snow + f_mud + ss(p[17], p[18], a)), 0, 1)
    f_gh = np.clip(1 - (f_rock + f_snow + f_mud + f_gl), 0, 1)
    return f_snow + f_rock + f_mud + f_gl + f_gh


# --------------------------------------------------------------------------- ecosystem

def _tab(tab, s, k):
    return F(tab[s * SPW + k])


def _key(tab, s) -> int:
    return int(np.asarray(tab[s * SPW + 9], F).view(U))


def plant_life(tab, s, cell, birth):
    spread = _tab(tab, s, 3)
    return _tab(tab, s, 2) * (F(1) - spread + F(2) * spread * uniform(_key(tab, s), cell, birth, 3))


class Sim:
    """The simulation state and kernels on numpy arrays (device.DeviceSim is
    the same on the OpenCL device). sp, birth: int32 (nz, nx); suit:
    float32 (nsp, nz, nx)."""

    def __init__(self, sp, birth, suit, tab, nb: int, local=None):
        self.sp = np.array(sp, np.int32)
        self.birth = np.array(birth, np.int32)
        self.suit = np.asarray(suit, F)
        self.tab = np.asarray(tab, F)
        self.nsp = self.suit.shape[0]
        self.nz, self.nx = self.sp.shape
        self.nb = nb
        self.cell = np.arange(self.nx * self.nz, dtype=np.int64).reshape(self.nz, self.nx)

    def seed_counts(self, t):
        """sim_sources then box_sum along x and z: mature plants of each
        species within its seed window, kept for update()."""
        age = (t - self.birth).astype(F)
        src = np.stack([((self.sp == s) & (age >= _tab(self.tab, s, 0))).astype(np.int32) for s in range(self.nsp)])
        out = np.zeros_like(src)
        for s in range(self.nsp):
            w = int(_tab(self.tab, s, 8))
            cs = np.cumsum(np.pad(src[s], ((0, 0), (1, 0))), axis=1)
            x = np.arange(self.nx)
            lo, hi = np.maximum(x - w, 0), np.minimum(x + w, self.nx - 1)
            row = cs[:, hi + 1] - cs[:, lo]
            cs = np.cumsum(np.pad(row, ((1, 0), (0, 0))), axis=0)
            z = np.arange(self.nz)
            lo, hi = np.maximum(z - w, 0), np.minimum(z + w, self.nz - 1)
            out[s] = cs[hi + 1, :] - cs[lo, :]
        self.count = out

    def update(self, t, stress, key):
        count = self.count
        sp, birth, tab = self.sp, self.birth, self.tab
        occ = sp >= 0
        new_sp = sp.copy()
        age = (t - birth).astype(F)
        life = np.zeros(sp.shape, F)
        suit_own = np.zeros(sp.shape, F)
        for s in range(self.nsp):
            m = sp == s
            life[m] = plant_life(tab, s, self.cell[m], birth[m])
            suit_own[m] = self.suit[s][m]
        u = uniform(key, self.cell, t, 12)
        dies = occ & ((age > life) | (u < F(stress) * (F(1) - suit_own)))
        new_sp[dies] = -1
        best = np.full(sp.shape, -1, np.int32)
        best_score = np.full(sp.shape, 2.0, F)
        for s in range(self.nsp):
            lam = _tab(tab, s, 6) * count[s].astype(F) + _tab(tab, s, 7)
            pr = self.suit[s] * lam / (F(1) + lam)
            u = uniform(_key(tab, s), self.cell, t, 13)
            with np.errstate(divide="ignore", invalid="ignore"):
                score = u / pr
            better = (~occ) & (u < pr) & (score < best_score)
            best = np.where(better, s, best)
            best_score = np.where(better, score, best_score)
        est = (~occ) & (best >= 0)
        new_sp[est] = best[est]
        self.birth = np.where(est, np.int32(t), birth).astype(np.int32)
        self.sp = new_sp

    def thin_init(self, t):
        sp, birth, tab = self.sp, self.birth, self.tab
        rec = np.zeros(sp.shape + (4,), F)
        st = np.zeros(sp.shape, np.uint8)
        xs = np.arange(self.nx, dtype=F)[None, :] + np.zeros((self.nz, 1), F)
        zs = np.arange(self.nz, dtype=F)[:, None] + np.zeros((1, self.nx), F)
        for s in range(self.nsp):
            m = sp == s
            if not m.any():
                continue
            cell, b = self.cell[m], birth[m]
            key = _key(tab, s)
            jx = uniform(key, cell, b, 1)
            jz = uniform(key, cell, b, 2)
            age = (t - b).astype(F)
            grown = np.minimum(F(1), age * _tab(tab, s, 1))
            R = _tab(tab, s, 4) * np.minimum(F(1), F(0.1) + F(0.9) * (age * _tab(tab, s, 1)))
            height = _tab(tab, s, 10) + _tab(tab, s, 11) * grown
            a = age / plant_life(tab, s, cell, b)
            tent = np.maximum(F(1) - np.abs(F(2) * a - F(1)), F(0))
            strength = height * (F(0.5) + F(0.5) * tent) * (F(0.25) + F(0.75) * self.suit[s][m])
            rec[m] = np.stack([xs[m] + jx, zs[m] + jz, R, strength], -1)
            st[m] = 1
        self.rec, self.st = rec, st

    def _neighbours(self):
        nb = self.nb
        for dz in range(-nb, nb + 1):
            for dx in range(-nb, nb + 1):
                if dx == 0 and dz == 0:
                    continue
                yield dz, dx

    def _shift(self, a, dz, dx, fill):
        """b[z, x] = a[z + dz, x + dx], `fill` outside the grid."""
        out = np.full_like(a, fill)
        nz, nx = a.shape[:2]
        zs, ze = max(0, -dz), min(nz, nz - dz)
        xs, xe = max(0, -dx), min(nx, nx - dx)
        if zs < ze and xs < xe:
            out[zs:ze, xs:xe] = a[zs + dz:ze + dz, xs + dx:xe + dx]
        return out

    @staticmethod
    def _overlap(p, q):
        ddx, ddz = p[..., 0] - q[..., 0], p[..., 1] - q[..., 1]
        rr = p[..., 2] + q[..., 2]
        return ddx * ddx + ddz * ddz < rr * rr

    def thin_round(self, t, rnd) -> int:
        """One round of thin_mark then thin_resolve; returns the contestants left."""
        rec, st = self.rec, self.st
        con = st == 1
        top = con.copy()
        for dz, dx in self._neighbours():
            q = self._shift(rec, dz, dx, 0)
            qst = self._shift(st, dz, dx, 0)
            qi = self._shift(self.cell, dz, dx, -1)
            ov = (qst == 1) & self._overlap(rec, q)
            stronger = (q[..., 3] > rec[..., 3]) | ((q[..., 3] == rec[..., 3]) & (qi > self.cell))
            top &= ~(ov & stronger)
        mark = top
        dominated = np.zeros(st.shape, bool)
        for dz, dx in self._neighbours():
            q = self._shift(rec, dz, dx, 0)
            qst = self._shift(st, dz, dx, 0)
            qm = self._shift(mark, dz, dx, False)
            dominated |= (qst == 1) & qm & self._overlap(rec, q)
        out = st.copy()
        out[con & mark] = 2
        dom = con & ~mark & dominated
        for s in range(self.nsp):
            m = dom & (self.sp == s)
            if not m.any():
                continue
            u = uniform(_key(self.tab, s), self.cell[m], t, 100 + rnd)
            survive = u < _tab(self.tab, s, 5)
            vals = np.where(survive, 3, 0).astype(np.uint8)
            out[m] = vals
            spm = self.sp[m]
            spm[~survive] = -1
            self.sp[m] = spm
        self.st = out
        return int((out == 1).sum())

    def read(self):
        return self.sp.copy(), self.birth.copy()


# --------------------------------------------------------------------------- Poisson disk

class PointWindow(NamedTuple):
    """A window of a grid of points (a species' Poisson grid, the grass
    tufts' grid) and of the terrain: the point cells [x0, x0 + wnx) x [z0,
    z0 + wnz) of the world's, and the terrain field's array (radius,
    density) from terrain cell (trow0, tcol0) of a wrows x wcols world.
    Points are hashed and placed by world cell. Poisson: cells outside the
    window count as free, so a window's cells k cells from its edge are the
    world's after k / PN phases."""
    x0: int
    z0: int
    wnx: int
    wnz: int
    trow0: int
    tcol0: int
    wrows: int
    wcols: int

    @staticmethod
    def whole(nx: int, nz: int, rad_shape) -> "PointWindow":
        return PointWindow(0, 0, nx, nz, 0, 0, int(rad_shape[0]), int(rad_shape[1]))

    def first(self, px: int, pz: int) -> tuple[int, int]:
        """The window's first world cells of phase (px, pz)."""
        P = PN + 1
        return self.x0 + (px - self.x0) % P, self.z0 + (pz - self.z0) % P


class Poisson:
    """Dart throwing by grid phases on numpy (device.DevicePoisson is the same
    on the OpenCL device). pts: (wnz, wnx, 4) float32 (x, z, r, key) of the
    window (PointWindow; default the world's nx x nz), starting from `pts`
    (default: free)."""

    def __init__(self, nx, nz, c, wdom, ddom, rad, dx, margin, obs_start, obs, onx, onz, oc, ox0=0, oz0=0,
                 onwx=None, onwz=None, local=None, window=None, pts=None):
        self.nx, self.nz, self.c = nx, nz, F(c)
        self.wdom, self.ddom = F(wdom), F(ddom)
        self.rad = np.asarray(rad, F)
        self.win = PointWindow.whole(nx, nz, self.rad.shape) if window is None else window
        self.dx, self.margin = F(dx), F(margin)
        self.obs_start, self.obs = np.asarray(obs_start, np.int64), np.asarray(obs, F)
        self.onx, self.onz, self.oc = onx, onz, F(oc)
        # obs_start covers onwx x onwz cells from (ox0, oz0): the grid, or the part a tile's darts reach
        self.ox0, self.oz0 = ox0, oz0
        self.onwx, self.onwz = onx if onwx is None else onwx, onz if onwz is None else onwz
        shape = (self.win.wnz, self.win.wnx, 4)
        self.pts = np.zeros(shape, F) if pts is None else np.array(pts, F).reshape(shape)

    def phase(self, px, pz, pss, key):
        P = PN + 1
        w = self.win
        xf, zf = w.first(px, pz)
        zs = np.arange(zf, w.z0 + w.wnz, P)
        xs = np.arange(xf, w.x0 + w.wnx, P)
        if not len(zs) or not len(xs):
            return
        Z, X = np.meshgrid(zs, xs, indexing="ij")  # world cells
        i = Z * self.nx + X
        free = self.pts[Z - w.z0, X - w.x0, 2] <= F(0)
        u1 = uniform(key, i, pss, 1)
        u2 = uniform(key, i, pss, 2)
        fx = (X.astype(F) + u1) * self.c
        fz = (Z.astype(F) + u2) * self.c
        ok = free & (fx <= self.wdom) & (fz <= self.ddom)
        rows, cols = self.rad.shape
        tc = np.minimum(np.floor(fx / self.dx + F(0.5)).astype(np.int64), w.wcols - 1) - w.tcol0
        tr = np.minimum(np.floor(fz / self.dx + F(0.5)).astype(np.int64), w.wrows - 1) - w.trow0
        r = self.rad[np.clip(tr, 0, rows - 1), np.clip(tc, 0, cols - 1)]
        ok &= r > F(0)
        if self.onx > 0:
            ox = np.minimum((fx / self.oc).astype(np.int64), self.onx - 1)
            oz = np.minimum((fz / self.oc).astype(np.int64), self.onz - 1)
            for dz in (-1, 0, 1):
                for ddx in (-1, 0, 1):
                    zz, xx = oz + dz, ox + ddx
                    inside = ok & (zz >= 0) & (zz < self.onz) & (xx >= 0) & (xx < self.onx) & (zz >= self.oz0) \
                        & (zz < self.oz0 + self.onwz) & (xx >= self.ox0) & (xx < self.ox0 + self.onwx)
                    cell = np.where(inside, (zz - self.oz0) * self.onwx + (xx - self.ox0), 0)
                    lo, hi = self.obs_start[cell], self.obs_start[cell + 1]
                    for k in range(int((hi - lo).max()) if inside.any() else 0):
                        has = inside & (lo + k < hi)
                        q = self.obs[np.where(has, lo + k, 0)]
                        ex, ez = fx - q[..., 0], fz - q[..., 1]
                        cl = q[..., 2] + self.margin
                        ok &= ~(has & (ex * ex + ez * ez < cl * cl))
        for dz in range(-PN, PN + 1):
            for ddx in range(-PN, PN + 1):
                zz, xx = Z + dz, X + ddx
                inside = (zz >= w.z0) & (zz < w.z0 + w.wnz) & (xx >= w.x0) & (xx < w.x0 + w.wnx)
                q = self.pts[np.clip(zz - w.z0, 0, w.wnz - 1), np.clip(xx - w.x0, 0, w.wnx - 1)]
                occ = inside & (q[..., 2] > F(0))
                ex, ez = fx - q[..., 0], fz - q[..., 1]
                rr = np.maximum(r, q[..., 2]) + self.margin
                ok &= ~(occ & (ex * ex + ez * ez < rr * rr))
        key3 = uniform(key, i, pss, 3)
        self.pts[Z[ok] - w.z0, X[ok] - w.x0] = np.stack([fx[ok], fz[ok], r[ok], key3[ok]], -1)

    def read(self):
        return self.pts.reshape(-1, 4).copy()


# --------------------------------------------------------------------------- grass tufts

def grass_tufts(dens, dx, nx, nz, sp, jitter, wdom, ddom, key, local=None, window=None):
    """(wnz * wnx, 4) float32 of the window's cells (PointWindow; default
    the world's nx x nz, dens the world's): x, z, random, kept."""
    dens = np.asarray(dens, F)
    rows, cols = dens.shape
    w = PointWindow.whole(nx, nz, dens.shape) if window is None else window
    Z, X = np.meshgrid(np.arange(w.z0, w.z0 + w.wnz), np.arange(w.x0, w.x0 + w.wnx), indexing="ij")
    i = Z * nx + X
    jitter = F(jitter)
    lo = F(0.5) - F(0.5) * jitter
    fx = (X.astype(F) + (lo + jitter * uniform(key, i, 1, 0))) * F(sp)
    fz = (Z.astype(F) + (lo + jitter * uniform(key, i, 2, 0))) * F(sp)
    inside = (fx <= F(wdom)) & (fz <= F(ddom))
    tc = np.minimum(np.floor(fx / F(dx) + F(0.5)).astype(np.int64), w.wcols - 1) - w.tcol0
    tr = np.minimum(np.floor(fz / F(dx) + F(0.5)).astype(np.int64), w.wrows - 1) - w.trow0
    d = dens[np.clip(tr, 0, rows - 1), np.clip(tc, 0, cols - 1)]
    kept = inside & (uniform(key, i, 3, 0) < d)
    out = np.stack([fx, fz, uniform(key, i, 4, 0), kept.astype(F)], -1)
    return out.reshape(-1, 4)
