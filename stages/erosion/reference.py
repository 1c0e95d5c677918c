"""Plain numpy implementation of every erosion kernel (kernels.cl), small and
obviously right, operation for operation in float32 so the two agree to the
last bit where the arithmetic allows. It runs the same steps through the same
driver (simulate.run) on small grids; tests compare the two.

Also here: `synthetic_world`, an analytic terrain that can be sampled at any
resolution (tests and the benchmark compare resolutions on it)."""
from __future__ import annotations

import numpy as np

from .physics import G, THERMAL_C, Physics, StepConstants, talus_thresholds
from .state import Diag

f32 = np.float32
HMIN = f32(1e-6)
VEL_HMIN = f32(1e-3)
TINY = f32(1e-30)
DIRS = ((0, 1), (1, 0), (0, -1), (-1, 0))  # (dr, dc): east, south, west, north
MOORE = DIRS + ((1, 1), (1, -1), (-1, -1), (-1, 1))  # then SE, SW, NW, NE


def MAX(a, b):
    """The kernels' MAX(a, b) = a > b ? a : b (not fmax: PoCL's fmax is a scalar call)."""
    return np.where(a > b, a, b)


def MIN(a, b):
    return np.where(a < b, a, b)


def sqrt_v(x: np.ndarray) -> np.ndarray:
    """The kernels' sqrt: correctly rounded float32 (vsqrtps on x86, the exact builtin elsewhere)."""
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.asarray(x, f32))


def shifted(a: np.ndarray, dr: int, dc: int, boundary: str, fill=0.0) -> tuple[np.ndarray, np.ndarray]:
    """out[r, c] = a[r + dr, c + dc] and whether that neighbour exists."""
    if boundary == "periodic":
        out = np.roll(a, shift=(-dr, -dc), axis=(0, 1))
        return out, np.ones(a.shape[:2], bool)
    rows, cols = a.shape[:2]
    out = np.full_like(a, fill)
    exists = np.zeros((rows, cols), bool)
    r0, r1 = max(0, -dr), min(rows, rows - dr)
    c0, c1 = max(0, -dc), min(cols, cols - dc)
    out[r0:r1, c0:c1] = a[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
    exists[r0:r1, c0:c1] = True
    return out, exists


def flux(Tb, dT, W, F, k: StepConstants, boundary: str) -> tuple[np.ndarray, np.ndarray]:
    """New pipe outflows F (rows, cols, 4: E, S, W, N), and the CFL speed per
    cell (max over faces of q/hf + sqrt(g hf), at least sqrt(g W))."""
    h = Tb + dT
    q = F.copy()
    hfs = np.zeros_like(F)
    for d, (dr, dc) in enumerate(DIRS):
        hj, ex = shifted(h, dr, dc, boundary)
        wj, _ = shifted(W, dr, dc, boundary)
        dh = np.where(ex, h - hj, f32(0))  # outside an open grid: a dry ghost at the same height
        wj = np.where(ex, wj, f32(0))
        hf = np.where(dh >= 0, MAX(W, wj - dh), MAX(W + dh, wj))
        deta = dh + (W - wj)
        h2 = np.where(hf > HMIN, hf * hf, f32(0))  # a dry face: qn is 0 or 0 / 0, and MAX(NaN, 0) is 0
        with np.errstate(divide="ignore", invalid="ignore"):
            qn = ((q[..., d] + k.g_dt_dx * hf * deta) * h2) / (h2 + k.fric_dt * q[..., d])
        qn = MAX(qn, f32(0))
        if boundary == "closed":
            qn = np.where(ex, qn, f32(0))  # a wall
        q[..., d] = qn
        hfs[..., d] = hf
    s = ((q[..., 0] + q[..., 1]) + q[..., 2]) + q[..., 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        kk = MIN(f32(1), (W * k.dx_dt) / s)  # s = 0: 1 or 0 / 0, scaling four zeros
    kk = np.where(W > TINY, kk, f32(0))  # subnormal water: W dx/dt has too few bits to bound sum q
    q = q * kk[..., None]
    g = f32(G)
    sp = sqrt_v(g * W)
    with np.errstate(divide="ignore", invalid="ignore"):
        for d in range(4):
            sp = np.where(q[..., d] > 0, MAX(sp, q[..., d] / hfs[..., d] + sqrt_v(g * hfs[..., d])), sp)
    return q.astype(f32), sp


def sed_out(S, W, q, c):
    """Sediment leaving with the water through one face: S (q c) / W, as
    q spq with the cell's sediment per unit discharge spq = (S c) (1 / W).
    `flux` leaves every cell more water than sum q c, so the faces never carry
    off more than S."""
    return q * ((S * c) * (f32(1) / MAX(W, TINY)))


def update(Tb, dT, W, S, F, M, EA, k: StepConstants, boundary: str):
    """Returns dT', W', S', M', EA' and the water and sediment that left
    through each side (east, south, west, north) as float64 per cell."""
    c = k.c_dt_dx
    h = Tb + dT
    qin, sin_, hn, sout, exs = [], [], [], [], []
    for d, (dr, dc) in enumerate(DIRS):
        sout.append(sed_out(S, W, F[..., d], c))
        Fj, ex = shifted(F, dr, dc, boundary)
        Sj, _ = shifted(S, dr, dc, boundary)
        Wj, _ = shifted(W, dr, dc, boundary)
        hj, _ = shifted(h, dr, dc, boundary)
        qj = np.where(ex, Fj[..., (d + 2) % 4], f32(0))  # the neighbour sends through its opposite face
        qin.append(qj)
        sin_.append(np.where(ex, sed_out(Sj, Wj, qj, c), f32(0)))
        hn.append(np.where(ex, hj, h))
        exs.append(ex)
    out_w, out_s = [], []
    for d in range(4):
        leaving = ~exs[d] if boundary == "open" else np.zeros_like(exs[d])
        out_w.append(np.where(leaving, (F[..., d] * c).astype(np.float64), 0.0))
        out_s.append(np.where(leaving, sout[d].astype(np.float64), 0.0))
    qin_sum = ((qin[0] + qin[1]) + qin[2]) + qin[3]
    qout_sum = ((F[..., 0] + F[..., 1]) + F[..., 2]) + F[..., 3]
    w1 = MAX(W + (qin_sum - qout_sum) * c, f32(0))
    s_in = ((sin_[0] + sin_[1]) + sin_[2]) + sin_[3]
    s_out = ((sout[0] + sout[1]) + sout[2]) + sout[3]
    s1 = MAX(S + (s_in - s_out), f32(0))

    qx2 = (qin[2] - F[..., 2]) + (F[..., 0] - qin[0])  # twice the unit discharge
    qy2 = (qin[3] - F[..., 3]) + (F[..., 1] - qin[1])
    dhx, dhy = hn[0] - hn[2], hn[1] - hn[3]
    dh2 = dhx * dhx + dhy * dhy
    sin2 = dh2 / (k.four_dx2 + dh2)  # g^2 / (1 + g^2), g = |dh| / (2 dx)
    cap = (f32(0.5) * k.kc) * sqrt_v((qx2 * qx2 + qy2 * qy2) * MAX(sin2, k.sin_min2))

    hlow = MIN(MIN(hn[0], hn[2]), MIN(hn[1], hn[3]))  # never below the lowest neighbour
    emax = MAX(h - hlow, f32(0))
    w2 = w1 + k.rain_dt
    ev = MIN(w2, k.evap_dt)
    w3 = w2 - ev
    ev_act = w2 - w3

    room = cap - s1
    drop = np.where(room > 0, MIN(k.ks_f * room, emax), k.kd_f * room)  # eroded, or (< 0) deposited
    drop = np.where(w3 <= 0, -s1, drop)  # the water is gone: what it carried settles
    dt1 = dT - drop
    s2 = MAX(s1 + (dT - dt1), f32(0))
    pres = MIN(w3 * k.inv_wet, f32(1))
    M1 = M + k.am * (pres - M)
    EA1 = EA + ev_act
    return dt1, w3, s2, M1, EA1, out_w, out_s


def thermal_step(Tb, dT, ph: Physics, W=None, wet_min: float = -1.0, cfrac: float = THERMAL_C) -> np.ndarray:
    """One iteration of Olsen's multi-neighbour talus rule; returns the new dT.
    With wet_min >= 0 material only slides into cells whose water W > wet_min."""
    t_ax, t_dg = talus_thresholds(ph)
    b = ph.boundary if ph.boundary == "periodic" else "closed"
    h = Tb + dT
    W = np.zeros_like(h) if W is None else W
    wm = f32(wet_min)
    wet = W > wm
    nb = []
    for kk, (dr, dc) in enumerate(MOORE):
        hj, ex = shifted(h, dr, dc, b)
        wj, _ = shifted(wet, dr, dc, b, fill=False)
        nb.append((hj, ex & wj, t_ax if kk < 4 else t_dg))
    dtot = np.zeros_like(h)
    emax = np.zeros_like(h)
    senders = np.zeros_like(h)
    for kk, (hj, ex_wet_j, t) in enumerate(nb):
        d = h - hj
        m = ex_wet_j & (d > t)
        dtot = np.where(m, dtot + d, dtot)
        emax = np.where(m, MAX(emax, d - t), emax)
        _, ex = shifted(h, *MOORE[kk], b)
        senders = np.where(ex & (-d > t) & wet, senders + f32(1), senders)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(dtot > 0, (f32(cfrac) * emax) / MAX(dtot, TINY), f32(0))
    r = f32(1) / MAX(senders, f32(1))  # each receiver is shared between the cells sending to it
    out = np.zeros_like(h)
    inn = np.zeros_like(h)
    for kk, (dr, dc) in enumerate(MOORE):
        hj, ex_wet_j, t = nb[kk]
        _, ex = shifted(h, dr, dc, b)
        sj, _ = shifted(s, dr, dc, b)
        rj, _ = shifted(r, dr, dc, b)
        d = h - hj
        out = np.where(ex_wet_j & (d > t), out + (s * d) * rj, out)
        e = hj - h
        inn = np.where(ex & wet & (e > t), inn + (sj * e) * r, inn)
    return dT + (inn - out)


def velocity(F, W, boundary: str):
    qin = []
    for d, (dr, dc) in enumerate(DIRS):
        Fj, ex = shifted(F, dr, dc, boundary)
        qin.append(np.where(ex, Fj[..., (d + 2) % 4], f32(0)))
    qx = f32(0.5) * ((qin[2] - F[..., 2]) + (F[..., 0] - qin[0]))
    qy = f32(0.5) * ((qin[3] - F[..., 3]) + (F[..., 1] - qin[1]))
    h = MAX(W, VEL_HMIN)
    return qx / h, qy / h


class ReferenceSim:
    """The numpy twin of device.DeviceSim, same interface."""

    def __init__(self, height, ph: Physics, *, water=None, sediment=None):
        self.ph = ph
        self.rows, self.cols = height.shape
        self.Tb = np.asarray(height, f32).copy()
        z = np.zeros_like(self.Tb)
        self.dT = z.copy()
        self.W = z.copy() if water is None else np.asarray(water, f32).copy()
        self.S = z.copy() if sediment is None else np.asarray(sediment, f32).copy()
        self.M = z.copy()
        self.EA = z.copy()
        self.F = np.zeros((self.rows, self.cols, 4), f32)
        self.out = np.zeros((8, self.rows, self.cols), np.float64)
        self.wave = np.sqrt(f32(G) * self.W)  # as the device initialises it

    def step(self, k: StepConstants, want_wave: bool = False) -> None:
        b = self.ph.boundary
        self.F, wave = flux(self.Tb, self.dT, self.W, self.F, k, b)
        if want_wave:
            self.wave = wave
        dT, W, S, M, EA, ow, os_ = update(self.Tb, self.dT, self.W, self.S, self.F, self.M, self.EA, k, b)
        self.dT, self.W, self.S, self.M, self.EA = dT, W, S, M, EA
        for d in range(4):
            self.out[d] += ow[d]
            self.out[4 + d] += os_[d]

    def thermal(self, iterations: int, wet_min: float = -1.0, cfrac: float = THERMAL_C) -> None:
        for _ in range(iterations):
            self.dT = thermal_step(self.Tb, self.dT, self.ph, self.W, wet_min, cfrac)

    def diag(self) -> Diag:
        ok = np.isfinite(self.W) & np.isfinite(self.dT) & np.isfinite(self.S) & np.isfinite(self.EA)
        ok &= np.all(np.isfinite(self.F), axis=-1)
        z = lambda a: np.where(ok, a, 0).astype(np.float64)
        sums = np.stack([z(self.W), z(self.dT), z(self.S), z(self.EA), z(np.abs(self.dT))], axis=-1)
        # the kernel: lane l of a row sums columns l, l + 8, ... left to right in
        # float64, then the 8 lanes are added in a fixed tree
        lanes = np.zeros((self.rows, 8, 5))
        for c0 in range(0, self.cols, 8):
            block = sums[:, c0:c0 + 8, :]
            lanes[:, :block.shape[1], :] += block
        L = [lanes[:, k, :] for k in range(8)]
        rows = ((L[0] + L[1]) + (L[2] + L[3])) + ((L[4] + L[5]) + (L[6] + L[7]))
        self.EA = np.where(ok, f32(0), self.EA)
        inf = f32(np.inf)
        mx = np.stack([
            np.where(ok, self.wave, 0).max(axis=1),
            np.where(ok, self.W, inf).min(axis=1),
            np.where(ok, self.S, inf).min(axis=1),
            (~ok).sum(axis=1).astype(f32),
            np.where(ok, self.W, 0).max(axis=1),
        ], axis=-1)
        bnd = np.zeros((2, 1))
        bnd[:, 0] = [self.out[0:4].sum(), self.out[4:8].sum()]
        return Diag.from_rows(rows, mx, bnd)

    def finish(self) -> None:
        pass

    def fields(self) -> dict[str, np.ndarray]:
        vx, vz = velocity(self.F, self.W, self.ph.boundary)
        return dict(dT=self.dT.copy(), W=self.W.copy(), S=self.S.copy(), M=self.M.copy(), vx=vx, vz=vz, F=self.F.copy())


def synthetic_world(n: int, size_m: float = 8000.0, relief_m: float = 1200.0, seed: int = 7,
                    modes: int = 160, min_wavelength_m: float = 250.0) -> np.ndarray:
    """An analytic, seamlessly tiling mountain terrain sampled at the centres of
    an n x n grid over size_m: a sum of Fourier modes with a k^-2 amplitude
    spectrum (wavelengths size_m .. min_wavelength_m), ridged. The same world
    at any n, so resolutions can be compared. float32 metres, minimum 0."""
    rng = np.random.default_rng(seed)
    kmax = int(size_m / min_wavelength_m)
    ks = []
    while len(ks) < modes:
        kx, kz = rng.integers(-kmax, kmax + 1, size=2)
        k = np.hypot(kx, kz)
        if 1 <= k <= kmax:
            ks.append((kx, kz, k))
    x = (np.arange(n) + 0.5) / n
    X, Z = np.meshgrid(x, x)
    acc = np.zeros((n, n))
    for kx, kz, k in ks:
        amp = k ** -2.0 * rng.uniform(0.5, 1.0)
        acc += amp * np.cos(2 * np.pi * (kx * X + kz * Z) + rng.uniform(0, 2 * np.pi))
    acc /= np.abs(acc).max()
    ridged = 1.0 - np.abs(acc)  # sharp ridges where the sum crosses zero
    base = 0.5 * (acc + 1.0)
    h = 0.55 * ridged ** 2 + 0.45 * base
    h = (h - h.min()) / (h.max() - h.min()) * relief_m
    return h.astype(np.float32)
