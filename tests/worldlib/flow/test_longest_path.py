"""Longest upstream flow paths (longest_path.py): counted in cardinal and
diagonal steps, the same in tiles as whole, and the running float sum's
lengths up to rounding."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib.flow import longest_path as lp
from worldlib.flow import reference as ref

from .worlds import fractal, random_small_worlds

DX = 8.0


def _codes(h: np.ndarray) -> np.ndarray:
    kind = ref.cell_kinds(h)
    return ref.d8(ref.priority_flood(h, True, kind), kind, DX)


def _running_sum(code: np.ndarray, dx: float) -> np.ndarray:
    """The longest path as a running float sum down the tree (the old definition)."""
    from worldlib.terrain.stats import topological_levels

    rcv = ref.receivers(code)
    k = np.clip(code.ravel(), 0, 7)
    step = np.where(k % 2 == 1, dx * np.sqrt(2.0), dx)
    L = np.zeros(rcv.size)
    for lev in topological_levels(rcv):
        t = rcv[lev]
        ok = t >= 0
        np.maximum.at(L, t[ok], L[lev[ok]] + step[lev[ok]])
    return L


def test_a_straight_and_a_diagonal_path():
    code = np.full((1, 5), 2, np.int8)  # east along a row
    code[0, -1] = ref.OUTLET
    a, b = lp.longest_whole(code)
    assert a.tolist() == [0, 1, 2, 3, 4] and b.tolist() == [0] * 5
    diag = np.full((3, 3), ref.OUTLET, np.int8)
    diag[0, 0], diag[1, 1] = 3, 3  # south-east twice
    a, b = lp.longest_whole(diag)
    assert b.reshape(3, 3)[2, 2] == 2 and a.reshape(3, 3)[2, 2] == 0
    assert lp.length_m(a, b, 2.0).reshape(3, 3)[2, 2] == pytest.approx(4 * np.sqrt(2.0))


def test_counts_are_the_running_sum_up_to_rounding():
    code = _codes(fractal(160, seed=3))
    a, b = lp.longest_whole(code)
    old = _running_sum(code, DX)
    new = lp.length_m(a, b, DX)
    assert np.allclose(new, old, rtol=1e-12, atol=0) and new.max() > 100 * DX


@pytest.mark.parametrize("seed, tile", [(1, 16), (2, 37), (3, 64), (4, 5)])
def test_tiles_give_the_whole_counts(seed, tile):
    h = fractal(150, seed=seed)[:, :133].copy()
    h[40:60, 70:90] = np.nan  # no-data across tile borders
    h[120, :30] = np.inf
    code = _codes(h)
    want_a, want_b = lp.longest_whole(code)
    a, b = lp.tiled_longest(code, tile)
    assert np.array_equal(a.ravel(), want_a) and np.array_equal(b.ravel(), want_b)
    assert lp.length_m(want_a, want_b, DX).max() > tile * DX  # paths longer than a tile cross its borders


def test_random_worlds_and_tilings():
    for trial, h, tile in random_small_worlds(41, 30, 12):
        code = _codes(h)
        want_a, want_b = lp.longest_whole(code)
        a, b = lp.tiled_longest(code, tile)
        assert np.array_equal(a.ravel(), want_a) and np.array_equal(b.ravel(), want_b), (trial, h.shape, tile)
