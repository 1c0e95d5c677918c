"""Resolution independence and the fBm power spectrum."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from stages.heightmap import noise
from stages.heightmap.stage import HeightmapParams, heights
from pipeline.opencl import get_cl


def lowpassed_difference(kw, coarse, fine, sigma=2.0, seed=3):
    """Relative RMS difference between the coarse map and the fine map
    box-downsampled to the coarse grid, both Gaussian blurred by sigma coarse
    cells: rms(a - b) / std(a)."""
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    hc, _ = heights(cl_env, HeightmapParams(resolution=coarse, **kw), seed)
    hf, _ = heights(cl_env, HeightmapParams(resolution=fine, **kw), seed)
    k = fine // coarse
    hf = hf.astype(np.float64).reshape(coarse, k, coarse, k).mean(axis=(1, 3))
    a = gaussian_filter(hc.astype(np.float64), sigma, mode="nearest")
    b = gaussian_filter(hf, sigma, mode="nearest")
    return float(np.sqrt(np.mean((a - b) ** 2)) / a.std())


# Measured relative RMS (seed 3, defaults otherwise), 128 vs 512 / 512 vs 2048:
#   fbm 0.0010 / 0.0002, ridged 0.021 / 0.005, warped (ridged basis) 0.021 / 0.005, fault 0.0014 / 0.0003.
# A different seed gives about 1.4, so these are the same landforms. Ridged is
# worse because the octaves skipped above the coarse grid's Nyquist limit add a
# positive mean in the ridged sum (they average to zero in fBm). Tolerances are
# about 2.5x the measured values. 128 vs 512 tests the same property as
# 512 vs 2048 (positions are in metres, the grid only samples them) at 1/16 of
# the cost; the error shrinks about 4x per 4x resolution, so the smaller pair is
# the harder test.
@pytest.mark.parametrize("generator,tol", [("fbm", 0.003), ("ridged", 0.05), ("warped", 0.05), ("fault", 0.004)])
def test_resolution_independence(generator, tol):
    kw = dict(generator=generator, size_m=8192.0)
    err = lowpassed_difference(kw, 128, 512)
    assert err < tol, err


def test_resolution_independence_512_vs_2048_default_generator():
    err = lowpassed_difference(dict(size_m=8192.0), 512, 2048)
    assert err < 0.0125, err  # measured 0.005


def test_different_seed_is_a_different_map(cl_env):
    """Sanity of the metric: the same comparison between two seeds is large."""
    hc, _ = heights(cl_env, HeightmapParams(resolution=128), 3)
    hd, _ = heights(cl_env, HeightmapParams(resolution=128), 4)
    a, b = (gaussian_filter(h.astype(np.float64), 2.0, mode="nearest") for h in (hc, hd))
    assert np.sqrt(np.mean((a - b) ** 2)) / a.std() > 0.5


def radial_power_spectrum(h):
    n = h.shape[0]
    p = np.abs(np.fft.fft2(h - h.mean())) ** 2
    k = np.fft.fftfreq(n) * n
    kb = np.rint(np.hypot(*np.meshgrid(k, k))).astype(int).ravel()
    total = np.bincount(kb, p.ravel())
    count = np.bincount(kb)
    ks = np.arange(1, n // 2)
    return ks, total[1:n // 2] / count[1:n // 2]


@pytest.mark.parametrize("hurst", [0.5, 1.0])
def test_fbm_spectral_slope(cl_env, hurst):
    """A 2D fBm surface with Hurst exponent H has a radially averaged power
    spectrum P(k) ~ k^-(2H+2). The map is tileable (periodic, so no leakage
    from the borders); the slope is fitted over k = 8..64 cycles per map
    (three octaves, clear of the first octave at k = 2 and of the Nyquist
    cut-off), averaged over two seeds. Measured (lacunarity 2, 3 seeds):
    H = 0.5: -2.94, -2.96, -2.91; H = 1.0: -3.90, -3.93, -3.87; the octave
    spacing leaves ripples that bias the fit by about 0.1. Tolerance 0.2."""
    n = 512
    slopes = []
    for seed in (0, 1):
        s = noise.make_spec(seed=seed, generator="fbm", size_m=float(n), resolution=n, wavelength_m=n / 2.0, octaves=16,
                            lacunarity=2.0, hurst=hurst, relief_m=1.0, base_m=0.0, tileable=True)
        h, _ = noise.bake(cl_env, s, (0, 0, n, n))
        k, p = radial_power_spectrum(h.astype(np.float64))
        m = (k >= 8) & (k <= 64)
        slopes.append(np.polyfit(np.log(k[m]), np.log(p[m]), 1)[0])
    expected = -(2.0 * hurst + 2.0)
    assert abs(np.mean(slopes) - expected) < 0.2, (slopes, expected)
