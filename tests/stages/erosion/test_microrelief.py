"""The microrelief below the geology's cells (stages/erosion/microrelief.py):
its spectrum against the steady state's analytic one, its RMS, no grid
marks, the same bits in any window, and none where it has no room."""
import math

import numpy as np
import pytest

from stages.erosion import microrelief as mr_mod
from stages.erosion.microrelief import MicroRelief
from worldlib.terrain.stats import grid_anisotropy


def periodic(seed: int, n: int = 512, rms: float = 0.1, size: float = 1.5) -> MicroRelief:
    return MicroRelief.of(seed, (n, n), 1.0, 8.0, rms, size, periodic=True)


def test_the_spectrum_is_the_steady_state_of_disturbances_and_creep():
    """S(k) = C (exp(-k^2 s0^2) - exp(-k^2 s1^2)) with s0 = 1.5 m, s1 = half
    the 8 m geology cell, C from the RMS: ring means of the periodogram of a
    periodic field, three seeds pooled. Measured 0.98 .. 1.05 down to 6 m
    wavelengths and 0.85 at 3 .. 4 m (the classes' midpoint rule there)."""
    n, s0, s1, rms = 512, 1.5, 4.0, 0.1
    k1 = 2 * np.pi * np.fft.fftfreq(n, 1.0)
    k = np.hypot(*np.meshgrid(k1, k1, indexing="ij"))
    c = rms ** 2 / (1 / (4 * math.pi * s0 ** 2) - 1 / (4 * math.pi * s1 ** 2))
    want = c * (np.exp(-k ** 2 * s0 ** 2) - np.exp(-k ** 2 * s1 ** 2))
    power = sum(np.abs(np.fft.fft2(periodic(seed).field((0, 0, n, n)))) ** 2 / n ** 2 for seed in (1, 2, 3)) / 3
    edges = 2 * np.pi / np.array([32.0, 16.0, 12.0, 8.0, 6.0, 4.0, 3.0])
    ratios = [power[(k >= a) & (k < b)].mean() / want[(k >= a) & (k < b)].mean() for a, b in zip(edges, edges[1:])]
    assert all(0.9 < r < 1.1 for r in ratios[:-1]), ratios
    assert 0.75 < ratios[-1] < 1.1, ratios


def test_the_rms_is_the_asked_one_and_the_relief_has_no_grid_marks():
    fields = [periodic(seed, rms=0.25).field((0, 0, 512, 512)) for seed in (4, 5, 6)]
    for f in fields:
        assert f.std() == pytest.approx(0.25, rel=0.05) and abs(f.mean()) < 0.01
    # the 2-to-16-cell grid anisotropy of isotropic noise (one 512^2 field: 0.94 .. 1.11)
    assert 0.93 < np.mean([grid_anisotropy(f) for f in fields]) < 1.07


def test_the_separable_filters_are_the_divergence_of_the_smoothed_noise():
    """One class against its definition summed in 2-D: h(p) = sum_q
    grad_p G_s(p - q) . xi(q), the noise of the class at every cell q within
    the kernels' radius of p along each axis."""
    mr = MicroRelief.of(9, (300, 300), 1.0, 8.0, 0.1, 1.5)
    k, s = 2, mr.sizes_m[2]
    rad = mr_mod._radius(s, 1.0)
    r0, c0, rows, cols = 40, 57, 6, 5
    got = mr._class(k, s, (r0, c0, rows, cols))
    rr, cc = np.arange(r0 - rad, r0 + rows + rad), np.arange(c0 - rad, c0 + cols + rad)
    xi_x, xi_y = mr._noise(2 * k, rr, cc), mr._noise(2 * k + 1, rr, cc)
    want = np.zeros((rows, cols))
    for i in range(rows):
        for j in range(cols):
            dz = (r0 + i) - rr[:, None].astype(float)  # p - q, rows (south)
            dx = (c0 + j) - cc[None, :].astype(float)  # p - q, columns (east)
            g = np.exp(-(dx ** 2 + dz ** 2) / (2 * s * s)) / (2 * math.pi * s * s)
            g *= (np.abs(dx) <= rad) & (np.abs(dz) <= rad)
            want[i, j] = np.sum(-dx / (s * s) * g * xi_x - dz / (s * s) * g * xi_y)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max())  # float32 filters


def test_a_cell_gets_the_same_bits_in_any_window():
    mr = MicroRelief.of(3, (700, 90), 1.0, 8.0, 0.1, 1.5)
    whole = mr.field((0, 0, 700, 90))  # two bands of ROWS_AT_ONCE rows
    assert np.array_equal(mr.field((505, 7, 30, 50)), whole[505:535, 7:57])
    assert np.array_equal(mr.field((0, 0, 1, 1)), whole[:1, :1])
    assert not np.array_equal(MicroRelief.of(4, (700, 90), 1.0, 8.0, 0.1, 1.5).field((0, 0, 8, 8)), whole[:8, :8])
    # periodic edges: the noise wraps on the world, so the relief does
    wrap = MicroRelief.of(3, (64, 48), 1.0, 8.0, 0.1, 1.5, periodic=True)
    assert np.array_equal(wrap.field((64, 48 * 2, 64, 48)), wrap.field((0, 0, 64, 48)))


@pytest.mark.parametrize("dx, geology_cell_m, rms, size", [
    (8.0, 8.0, 0.1, 1.5),  # the default world: the geology on the cells, nothing finer on the grid
    (1.0, 8.0, 0.0, 1.5),  # none asked
    (1.0, 8.0, 0.1, 4.0),  # disturbances as wide as half the geology's cell
    (2.0, 4.0, 0.1, 0.5),  # a cell as wide as half the geology's cell
])
def test_no_microrelief_where_it_has_no_room(dx, geology_cell_m, rms, size):
    assert MicroRelief.of(1, (64, 64), dx, geology_cell_m, rms, size) is None


def test_extreme_parameters_stay_finite_and_scale():
    """Disturbances finer than a cell use one cell; a large RMS is the same field scaled."""
    fine = MicroRelief.of(2, (64, 64), 1.0, 8.0, 0.1, 1e-6)
    assert 1.0 < fine.sizes_m[0] < 1.1  # the first class's middle: s0 = 1 cell
    big = MicroRelief.of(2, (64, 64), 1.0, 8.0, 10.0, 1e-6).field((0, 0, 64, 64))
    assert np.isfinite(big).all()
    np.testing.assert_allclose(big, 100.0 * fine.field((0, 0, 64, 64)), rtol=1e-5, atol=1e-5)  # float32: 1e-6 of the 10 m RMS
