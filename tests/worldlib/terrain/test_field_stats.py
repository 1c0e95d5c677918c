"""The statistics of the height alone read by windows (field_statistics):
the same numbers as the whole run's, whatever assembles the windows, and a
world of at most ANISOTROPY_WINDOW a side measured exactly as before."""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from tests.worldlib.flow.worlds import fractal
from worldlib.terrain import stats as ts

FIELD_KEYS = ("grid_anisotropy", "grid_anisotropy_local", "depression_area_fraction", "hypsometric_integral",
              "relief_m")


def _world(rows, cols, seed, hole=True, rough=False):
    h = fractal(max(rows, cols), seed).astype(np.float64)[:rows, :cols] - 250.0  # heights of both signs
    if rough:  # heights over ten decades, whose float sums depend on their order
        rng = np.random.default_rng(seed)
        h = np.abs(rng.standard_normal((rows, cols))) * 10.0 ** rng.integers(-3, 7, (rows, cols))
    if hole:
        h[rows // 4:rows // 3, cols // 5:cols // 2] = np.nan
    filled = np.where(np.isfinite(h), h + (np.arange(cols) % 5 == 0) * 0.25, np.nan)
    return h, filled


def _sliced(a):
    return lambda r0, c0, nr, nc: a[r0:r0 + nr, c0:c0 + nc]


def _tiled(a, tr, tc):
    """A reader assembling each window from copies of tiles of tr x tc cells."""
    def read(r0, c0, nr, nc):
        out = np.empty((nr, nc))
        for tr0 in range(r0 - r0 % tr, r0 + nr, tr):
            for tc0 in range(c0 - c0 % tc, c0 + nc, tc):
                tile = a[tr0:tr0 + tr, tc0:tc0 + tc].copy()
                ra, rb = max(r0, tr0), min(r0 + nr, tr0 + tr)
                ca, cb = max(c0, tc0), min(c0 + nc, tc0 + tc)
                out[ra - r0:rb - r0, ca - c0:cb - c0] = tile[ra - tr0:rb - tr0, ca - tc0:cb - tc0]
        return out
    return read


def _terrain_statistics(h, filled, dx):
    rows, cols = h.shape
    code = np.full(h.shape, 2, np.int8)
    code[:, -1] = -1
    area = np.broadcast_to((np.arange(cols) + 1.0) * dx * dx, h.shape)
    return ts.terrain_statistics(h, filled, code, area, dx, 50 * dx * dx)


def _old_field_statistics(h, filled, dx):
    """The field statistics as terrain_statistics computed them on the whole array."""
    data = np.isfinite(h)
    hv = h[data]
    span = float(hv.max() - hv.min())
    hf = np.where(data, h, hv.mean())
    return {"grid_anisotropy": ts.grid_anisotropy(hf), "grid_anisotropy_local": ts.grid_anisotropy_local(hf),
            "depression_area_fraction": float(((filled > h) & data).sum() / max(int(data.sum()), 1)),
            "hypsometric_integral": float((hv.mean() - hv.min()) / span), "relief_m": span,
            **(ts.slope_statistics(hf, dx) if min(h.shape) * dx >= 3 * ts.SLOPE_BLOCK_M else {})}


@pytest.mark.parametrize("rows, cols, dx, hole, rough", [
    (97, 131, 8.0, True, False), (200, 61, 2.0, False, False), (150, 150, 35.0, True, False),
    (40, 300, 8.0, True, False), (10, 20, 8.0, False, False), (97, 131, 8.0, True, True)])
def test_windows_give_the_whole_runs_statistics_and_those_are_unchanged(rows, cols, dx, hole, rough):
    h, filled = _world(rows, cols, rows + cols, hole, rough)
    if rough:  # numpy's mean is not the correctly rounded one here: the test tells them apart
        hv = h[np.isfinite(h)]
        assert hv.mean() != math.fsum(hv) / hv.size
    whole = _terrain_statistics(h, filled, dx)
    old = _old_field_statistics(h, filled, dx)
    for tr, tc in ((7, 13), (rows, 5), (64, 64)):
        got = ts.field_statistics(_tiled(h, tr, tc), (rows, cols), dx, _tiled(filled, tc, tr))
        assert got == {k: whole[k] for k in got}
        assert got == old  # bitwise the statistics before they were read by windows
    assert ("slope_median_deg" in got) == (min(rows, cols) * dx >= 90.0)


def test_the_default_worlds_statistics_are_unchanged():
    """1024 x 1024 cells of 8 m with a hole of no-data: terrain_statistics
    gives bitwise what it computed on the whole array before."""
    h, filled = _world(1024, 1024, 7)
    st = _terrain_statistics(h, filled, 8.0)
    old = _old_field_statistics(h, filled, 8.0)
    assert {k: st[k] for k in old} == old


def _large_world():
    h, filled = _world(1100, 1300, 11)
    return h, filled


def test_a_large_world_does_not_depend_on_how_its_windows_are_assembled(monkeypatch):
    h, filled = _large_world()
    dx = 8.0
    a = ts.field_statistics(_sliced(h), h.shape, dx, _sliced(filled))
    monkeypatch.setattr(ts, "STRIP_CELLS", 5000)  # other strips of block rows: the same blocks
    b = ts.field_statistics(_tiled(h, 257, 41), h.shape, dx, _tiled(filled, 100, 1300))
    assert a == b
    st = _terrain_statistics(h, filled, dx)  # the whole run reads its array by the same windows
    assert {k: st[k] for k in a} == a
    # against the whole array's numbers: mean, extremes, block means and counts the same up to rounding
    old = _old_field_statistics(h, filled, dx)
    data = np.isfinite(h)
    assert a["relief_m"] == old["relief_m"] and a["depression_area_fraction"] == old["depression_area_fraction"]
    hv = h[data]
    assert a["hypsometric_integral"] == (math.fsum(hv) / hv.size - hv.min()) / (hv.max() - hv.min())
    for k in old:
        if k.startswith("slope_"):
            assert a[k] == pytest.approx(old[k], rel=1e-12, abs=1e-12), k
    # Welch: the power of the four 1024 x 1024 windows (the last ones flush with the far edges) summed
    fill = math.fsum(hv) / hv.size
    power = sum(ts._band_spectrum(np.where(data, h, fill)[r:r + 1024, c:c + 1024])[0] for r in (0, 76)
                for c in (0, 276))
    band, angle = ts._band_geometry(1024, 1024)
    assert a["grid_anisotropy"] == pytest.approx(ts._anisotropy(power, band, angle), rel=1e-12)
    assert a["grid_anisotropy_local"] == pytest.approx(ts._anisotropy_local(power, band, angle), rel=1e-12)
    assert 0.8 < a["grid_anisotropy"] < 1.25 and 0.8 < a["grid_anisotropy_local"] < 1.25


def test_windowed_path_on_small_windows_is_independent_of_the_reader_and_close_to_the_whole():
    h, filled = _world(300, 450, 5)
    dx = 8.0
    runs = [ts.field_statistics(r, h.shape, dx, f, window=128)
            for r, f in ((_sliced(h), _sliced(filled)), (_tiled(h, 13, 450), _tiled(filled, 300, 7)))]
    assert runs[0] == runs[1]
    old = _old_field_statistics(h, filled, dx)
    for k in old:
        if not k.startswith("grid_"):
            assert runs[0][k] == pytest.approx(old[k], rel=1e-12, abs=1e-12), k


def test_window_starts_cover_every_cell_with_fixed_windows():
    assert ts.window_starts(1000, 1024) == [0]
    assert ts.window_starts(2048, 1024) == [0, 1024]
    assert ts.window_starts(2100, 1024) == [0, 1024, 1076]
    for n in range(1, 40):
        starts = ts.window_starts(n, 7)
        covered = np.zeros(n, bool)
        for s in starts:
            covered[s:s + 7] = True
        assert covered.all() and all(s + min(n, 7) <= n for s in starts)


def test_exact_sum_is_fsum_whatever_the_split():
    rng = np.random.default_rng(2)
    v = rng.standard_normal(20000) * 10.0 ** rng.integers(-300, 300, 20000)
    v[::7] = 0.0
    v[::11] = 5e-324 * rng.integers(-5, 5, v[::11].size)  # subnormals
    v[::13] = -v[::13]
    total = ts.exact_sum(v)
    assert ts.exact_mean(total, 1) == math.fsum(v)
    cuts = np.sort(rng.integers(0, v.size, 9))
    assert sum(ts.exact_sum(p) for p in np.split(v, cuts)) == total
    assert ts.exact_mean(total, v.size) == float(sum(map(Fraction, v.tolist())) / v.size)  # correctly rounded
    assert ts.exact_sum(np.zeros(0)) == 0 and ts.exact_mean(0, 0) == 0.0
    h = np.array([1e16, 1.0, -1e16, 1.0])  # cancellation a float sum loses
    assert ts.exact_mean(ts.exact_sum(h), 4) == 0.5


@pytest.mark.parametrize("n, dx, block", [(16, 8.0, 30.0), (101, 8.0, 30.0), (77, 2.0, 30.0), (50, 30.0, 30.0),
                                          (40, 7.3, 30.0), (33, 35.0, 35.0)])
def test_block_taps_are_block_weights_without_zeros(n, dx, block):
    dense = ts.block_weights(n, dx, block)
    first, w = ts.block_taps(n, dx, block)
    rebuilt = np.zeros_like(dense)
    for b in range(first.size):
        for k in range(w.shape[1]):
            if w[b, k]:
                rebuilt[b, first[b] + k] = w[b, k]
    np.testing.assert_array_equal(rebuilt, dense)


def test_block_grid_is_block_average_and_independent_of_its_strips(monkeypatch):
    h, _ = _world(130, 95, 3)
    fill = float(np.nanmean(h))
    hf = np.where(np.isfinite(h), h, fill)
    grids = []
    for strip in (1, 300, 10 ** 9):
        monkeypatch.setattr(ts, "STRIP_CELLS", strip)
        grids.append(ts.block_grid(_tiled(h, 9, 95), h.shape, 8.0, 30.0, fill))
    assert all(np.array_equal(g, grids[0]) for g in grids)
    np.testing.assert_allclose(grids[0], ts.block_average(hf, 8.0, 30.0), rtol=1e-13)
    # blocks of one cell are the cells
    np.testing.assert_array_equal(ts.block_grid(_sliced(h), h.shape, 30.0, 30.0, fill), hf[:, :])
