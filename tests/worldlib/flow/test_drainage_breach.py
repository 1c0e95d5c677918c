"""Complete breaching along the depressions' floods and the drainage (drainage_breach):
against a cell-by-cell reference, what it promises of the surface, and the
tiled passes bit for bit the whole run."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib.flow import drainage_breach as db
from worldlib.flow import reference as ref

from .worlds import fractal, random_small_worlds


def _drainage(h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canonical heights (NaN on no-data), their kinds, and the carves' paths (carve_codes)."""
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    h[kind == ref.NODATA] = np.nan
    surface = ref.priority_flood(h, eps=True, kind=kind)
    paths = db.carve_codes(h, ref.priority_flood(h, kind=kind), surface, ref.d8(surface, kind, 1.0))
    return h, kind, paths


def _step_down(x: np.float32) -> np.float32:
    """The next float32 down, the denormals skipped (reference.canonical has none)."""
    tiny = np.finfo(np.float32).tiny
    y = np.nextafter(x, np.float32(-np.inf))
    return y if not 0 < abs(y) < tiny else np.float32(0.0 if x > 0 else -tiny)


def _cell_by_cell(h: np.ndarray, kind: np.ndarray, paths: np.ndarray) -> np.ndarray:
    """The definition read literally: cells in a topological order of the
    paths (every donor before its receiver), each one's carve stepped down
    one float."""
    rcv = ref.receivers(paths)
    levels = ref.topological_levels(rcv)
    assert sum(lv.size for lv in levels) == h.size  # the paths are a forest
    z = h.ravel().astype(np.float32)
    b = z.copy()
    carving = ref.pits(h, kind).ravel()
    arriving = np.full(z.size, np.inf, np.float32)
    for c in np.concatenate(levels).tolist():
        if arriving[c] < z[c]:
            b[c], carving[c] = arriving[c], True
        if carving[c] and rcv[c] >= 0:
            r = rcv[c]
            arriving[r] = min(arriving[r], _step_down(b[c]))
    return b.reshape(h.shape)


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.int32)


def test_ordered_heights_step_like_nextafter_but_over_the_denormals():
    z = np.array([-np.inf, -3.5, -1.1754944e-38, 0.0, 1.1754944e-38, 1.0, 1000.0, np.inf], np.float32)
    o = db.ordered(z)
    assert (np.diff(o) > 0).all() and o[3] == 0 and db.ordered(np.float32([-0.0]))[0] == 0
    assert o[2] == -1 and o[4] == 1  # the least normals next to zero
    down = db.from_ordered(o[[1, 5, 6]] - 1)
    np.testing.assert_array_equal(down, np.nextafter(z[[1, 5, 6]], np.float32(-np.inf)))
    np.testing.assert_array_equal(_bits(db.from_ordered(o)), _bits(z))
    assert np.isnan(db.from_ordered(db.ordered(np.float32([np.nan])))).all()


@pytest.mark.parametrize("seed", range(3))
def test_breach_is_the_definition_cell_by_cell(seed):
    h = fractal(48, seed)
    h = np.round(h / 25) * 25  # flats and closed basins
    h[np.random.default_rng(seed).random(h.shape) < 0.02] = np.nan
    h, kind, paths = _drainage(h)
    assert np.array_equal(_bits(db.breach(h, kind, paths)), _bits(_cell_by_cell(h, kind, paths)))


def test_a_closed_basin_drains_through_a_cut_in_its_rim_and_nothing_rises():
    y, x = np.mgrid[0:21, 0:21]
    h = (10.0 + np.minimum(np.minimum(y, 20 - y), np.minimum(x, 20 - x))).astype(np.float32)  # a rim over 10 m
    h[5:16, 5:16] = 2.0  # a pit in a flat-floored basin
    h[10, 10] = 1.0
    h[10, 16:] = [6.0, 5.5, 5.0, 4.5, 4.0]  # a notch in the rim and a gully down to the map's edge
    h, kind, paths = _drainage(h)
    b = db.breach(h, kind, paths)
    assert (b <= h).all() and b[10, 10] == 1.0
    rcv, c, path = ref.receivers(paths), 10 * 21 + 10, []
    while c >= 0:
        path.append(c)
        c = rcv[c]
    assert (np.diff(b.ravel()[path]) < 0).all()  # cut from the pit below it all the way ...
    assert set(range(10 * 21 + 16, 10 * 21 + 21)) <= set(path)  # ... through the notch and the gully
    assert not (ref.d8(b, kind, 1.0) == ref.PIT).any()
    assert not ((b < h) & (h >= 10.0)).any()  # the rim is cut at its notch only


def test_breached_surfaces_drain_and_are_never_raised():
    for trial, h, _ in random_small_worlds(7, 60, 24):
        h, kind, paths = _drainage(h)
        b = db.breach(h, kind, paths)
        data = kind != ref.NODATA
        assert (b[data] <= h[data]).all() and np.isnan(b[~data]).all(), trial
        assert not (ref.d8(b, kind, 1.0) == ref.PIT).any(), trial


def test_tiled_breaching_is_the_whole_run_bit_for_bit():
    """Random small worlds with flats and holes in random tiles of 1 to 11
    cells (single rows and columns, part tiles), and a world whose one
    basin's carves cross many tiles."""
    for trial, h, tile in random_small_worlds(11, 80, 40):
        h, kind, paths = _drainage(h)
        assert np.array_equal(_bits(db.tiled_breach(h, paths, tile)), _bits(db.breach(h, kind, paths))), trial
    y, x = np.mgrid[0:90, 0:70]
    bowl = (np.hypot(y - 45, x - 35) * 3 + fractal(96, 3)[:90, :70] / 40).astype(np.float32)
    bowl[45, 69] = 0.5  # one low cell on the rim: the bowl drains through it
    h, kind, paths = _drainage(bowl)
    whole = db.breach(h, kind, paths)
    assert np.ptp(np.nonzero(whole < h)[1]) >= 30  # carves from the bottom to the rim: 5 tiles of 7 and more
    for tile in (7, 16, 33):
        assert np.array_equal(_bits(db.tiled_breach(h, paths, tile)), _bits(whole)), tile


@pytest.mark.parametrize("seed", range(2))
def test_carves_cut_about_what_lindsays_cut(seed):
    """Against reference.breach (Lindsay's flood order over the whole map)
    on rough fractal land with many depressions: the carved volume within
    3 % of it, where carving along the drainage alone (straight across the
    fill's flats, through inner ridges) cuts 15 % and more above it."""
    h = ref.canonical(fractal(128, seed, beta=2.0))
    kind = ref.cell_kinds(h)
    surface = ref.priority_flood(h, eps=True, kind=kind)
    drainage = ref.d8(surface, kind, 1.0)
    paths = db.carve_codes(h, ref.priority_flood(h, kind=kind), surface, drainage)
    carved = lambda b: float((h - b).astype(np.float64).sum())
    lindsay = carved(ref.breach(h, kind))
    assert abs(carved(db.breach(h, kind, paths)) / lindsay - 1.0) < 0.03
    assert carved(db.breach(h, kind, drainage)) / lindsay > 1.15
