"""Terrain statistics against cases whose answers are known by construction."""
import math

import numpy as np
import pytest

from worldlib.terrain import stats as ts


def _d8_steepest(h, dx):
    """Plain steepest-descent D8 on a depression-free surface (edges are outlets)."""
    rows, cols = h.shape
    code = np.full((rows, cols), -1, np.int8)
    best = np.zeros((rows, cols))
    p = np.pad(h, 1, constant_values=np.inf)
    for k in range(8):
        nb = p[1 + ts.DR[k]:1 + ts.DR[k] + rows, 1 + ts.DC[k]:1 + ts.DC[k] + cols]
        s = (h - nb) / (dx * (math.sqrt(2) if k % 2 else 1.0))
        m = s > best
        best[m], code[m] = s[m], k
    code[0, :] = code[-1, :] = code[:, 0] = code[:, -1] = -1
    return code


def _accumulate(code):
    rcv = ts.receivers(code)
    acc = np.ones(rcv.size)
    for lev in ts.topological_levels(rcv):
        t = rcv[lev]
        ok = t >= 0
        np.add.at(acc, t[ok], acc[lev[ok]])
    return acc.reshape(code.shape)


def test_anisotropy_is_one_for_isotropic_noise_and_large_for_grid_stripes():
    rng = np.random.default_rng(3)
    n = 256
    # isotropic: white noise low-passed by a radially symmetric filter
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n)))
    iso = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) / np.maximum(k, 1 / n) ** 1.5))
    assert 0.9 < ts.grid_anisotropy(iso) < 1.1
    # stripes along the rows and diagonals (what D8 across flats prints)
    r, c = np.mgrid[0:n, 0:n]
    stripes = iso + 0.5 * iso.std() * (np.sin(2 * np.pi * r / 5.0) + np.sin(2 * np.pi * (r + c) / 7.0))
    assert ts.grid_anisotropy(stripes) > 2.0
    # the same stripes rotated off the grid's directions (about 20 degrees) are not counted
    rot = iso + 0.5 * iso.std() * np.sin(2 * np.pi * (r * math.cos(0.35) + c * math.sin(0.35)) / 5.0)
    assert ts.grid_anisotropy(rot) < 1.2


def test_local_anisotropy_tells_grid_marks_from_a_landform_trend_near_a_grid_direction():
    rng = np.random.default_rng(5)
    n = 256
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n)))
    spectrum = np.fft.fft2(rng.standard_normal((n, n))) / np.maximum(k, 1 / n) ** 1.5
    iso = np.real(np.fft.ifft2(spectrum))
    assert 0.9 < ts.grid_anisotropy_local(iso) < 1.1
    r, c = np.mgrid[0:n, 0:n]
    stripes = iso + 0.5 * iso.std() * (np.sin(2 * np.pi * r / 5.0) + np.sin(2 * np.pi * (r + c) / 7.0))
    assert ts.grid_anisotropy_local(stripes) > 2.0
    # a trend: the same noise with its power raised over 120..150 degrees (broad, around the 135 degree diagonal)
    angle = np.degrees(np.arctan2(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :])) % 180.0
    trend = np.real(np.fft.ifft2(spectrum * np.where(np.abs(angle - 135.0) <= 15.0, 2.5, 1.0)))
    assert ts.grid_anisotropy(trend) > 1.1
    assert 0.8 < ts.grid_anisotropy_local(trend) < 1.1


def test_anisotropy_share_of_wavenumbers_is_that_of_the_definition():
    # white noise: power spread evenly over wavenumbers, so the ratio is about 1 (no window bias)
    rng = np.random.default_rng(0)
    vals = [ts.grid_anisotropy(rng.standard_normal((128, 128))) for _ in range(4)]
    assert abs(np.mean(vals) - 1.0) < 0.08


def test_strahler_order_of_a_binary_tree():
    # a comb of symmetric confluences: a 1-D chain of receivers built by hand
    # cells 0..6: 0,1 -> 4; 2,3 -> 5; 4,5 -> 6 (outlet): order 1,1,1,1,2,2,3
    rcv = np.array([4, 4, 5, 5, 6, 6, -1])
    channel = np.ones(7, bool)
    order = ts.strahler_order(rcv, channel, ts.topological_levels(rcv, channel))
    assert order.tolist() == [1, 1, 1, 1, 2, 2, 3]
    # a first-order tributary joining a second-order stream keeps order 2
    rcv = np.array([2, 2, 4, 4, -1])
    order = ts.strahler_order(rcv, np.ones(5, bool), ts.topological_levels(rcv))
    assert order.tolist() == [1, 1, 2, 1, 2]


def test_cone_and_plane_statistics():
    dx = 10.0
    n = 65
    r, c = np.mgrid[0:n, 0:n]
    # a tilted plane draining east: no depressions, parallel flow, order 1
    plane = (n - c) * 0.1 * dx
    code = _d8_steepest(plane, dx)
    area = _accumulate(code) * dx * dx
    st = ts.terrain_statistics(plane, plane, code, area, dx, channel_area_m2=5 * dx * dx)
    assert st["depression_area_fraction"] == 0.0
    assert st["strahler_order_max"] == 1
    assert st["hypsometric_integral"] == pytest.approx(0.5, abs=0.02)
    # along a parallel flow line L = (A / dx^2 - 1) dx (Hack exponent 1, a little above it at small A)
    # and the slope is constant (theta 0)
    assert st["hack_exponent"] == pytest.approx(1.0, abs=0.1)
    assert st["concavity_theta"] == pytest.approx(0.0, abs=0.05)
    # channel length per area: every row is one channel of n - 6 cells (A >= 5 cells) ... up to the outlet column
    rows_with_channels = n - 2
    length_km = rows_with_channels * (n - 1 - 5) * dx / 1000
    assert st["drainage_density_per_km"] == pytest.approx(length_km / (n * n * dx * dx / 1e6), rel=0.1)


def test_depressions_and_concavity_of_a_known_profile():
    dx = 50.0  # the slope reach (200 m) is 4 cells
    n = 80
    r, c = np.mgrid[0:n, 0:n]
    # a valley draining east along the middle row, steep sides: along the floor the drainage area
    # grows as A ~ n (c + 1) cells and the floor slope is S = 2 (c + 1)^-0.5 per cell, so theta = 0.5
    floor = 4.0 * (math.sqrt(n) - np.sqrt(c + 1.0)) * dx
    h = floor + 20.0 * dx * np.abs(r - n // 2)
    h[10:14, 10:14] -= 50.0  # one closed pit of 16 cells, far from the valley floor
    filled = h.copy()
    filled[10:14, 10:14] = h[9, 10:14].min()  # not a real fill: only its cells count
    code = _d8_steepest(filled, dx)
    area = _accumulate(code) * dx * dx
    st = ts.terrain_statistics(h, np.maximum(filled, h), code, area, dx, channel_area_m2=200 * dx * dx)
    assert st["depression_area_fraction"] == pytest.approx(16 / (n * n))
    assert st["strahler_order_max"] == 1  # one stem, no confluence of channels
    assert st["concavity_theta_cell"] == pytest.approx(0.5, abs=0.05)
    assert st["concavity_theta"] == pytest.approx(0.5, abs=0.08)


def test_slope_statistics_of_planes_and_block_averaging():
    dx = 8.0
    r, c = np.mgrid[0:128, 0:128] * dx
    for deg in (5.0, 25.0, 45.0):
        plane = 100.0 + math.tan(math.radians(deg)) * (0.6 * c + 0.8 * r)
        st = ts.slope_statistics(plane, dx)
        assert st["slope_block_m"] == 30.0
        for key in ("slope_p10_deg", "slope_median_deg", "slope_p90_deg", "slope_mean_deg"):
            # a plane averages to a plane; cells cut by a block edge shift the blocks' centroids a little
            assert st[key] == pytest.approx(deg, rel=1e-2)
        assert st["slope_p90_deg"] - st["slope_p10_deg"] < 0.5
        assert st["slope_share_over_40_deg"] == (1.0 if deg > 40 else 0.0)
        assert st["slope_share_under_10_deg"] == (1.0 if deg < 10 else 0.0)
    # 30 m blocks over 8 m cells: each block weighs its cells by the overlap (3.75 cells a block)
    w = ts.block_weights(16, 8.0, 30.0)
    assert w.shape == (4, 16)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w[0, :5], [8 / 30, 8 / 30, 8 / 30, 6 / 30, 0.0])


def test_slope_statistics_average_away_what_is_finer_than_the_block():
    """A 16 m ripple of 45 degrees on a gentle plane: at 30 m blocks the
    ripple averages out and the plane's slope remains; measured per cell,
    the ripple would dominate."""
    dx = 2.0
    r, c = np.mgrid[0:300, 0:300] * dx
    base = math.tan(math.radians(8.0)) * c
    ripple = 16.0 / (2 * math.pi) * np.sin(2 * math.pi * r / 16.0)  # slope amplitude 1: 45 degrees
    st = ts.slope_statistics(base + ripple, dx)
    assert st["slope_median_deg"] < 12.0 and st["slope_share_over_40_deg"] == 0.0
    assert np.median(ts.slope_degrees(base + ripple, dx)) > 30.0
