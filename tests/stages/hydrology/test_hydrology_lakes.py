"""Lakes: volume budget, flat surfaces, spilling and merging."""
import functools

import numpy as np
import pytest

from worldlib.flow import device as dev
from stages.hydrology import lakes
from worldlib.flow import reference as ref


def solve(cl_env, h, depth_m, area=4.0, accumulate=None, merge_sweep=None):
    accumulate = accumulate or functools.partial(dev.accumulate, cl_env)
    merge_sweep = merge_sweep or functools.partial(dev.merge_sweep, cl_env)
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    raw = np.nan_to_num(h, nan=0.0)
    F = dev.fill(cl_env, h, kind, False)
    code = dev.d8(cl_env, np.nan_to_num(dev.fill(cl_env, h, kind, True), nan=0.0), kind, 2.0)
    code_raw = dev.d8(cl_env, raw, kind, 2.0)
    runoff = np.where(np.isfinite(h), depth_m * area, 0.0)
    return lakes.solve_lakes(h, kind, F, code, code_raw, runoff, area, accumulate, merge_sweep), h, F


def two_basins():
    h = np.full((20, 40), 10.0, np.float32)
    h[5:15, 3:15] = 6.0   # basin A, floor 6
    h[5:15, 22:37] = 0.0  # basin B, floor 0
    h[9, 15:22] = 8.0     # saddle A -> B at 8 m (rim elsewhere 10 m)
    return h


def check(res, h, F):
    s = res.stats
    assert s["budget_relative_error"] <= 1e-6
    assert s["stored_vs_cells_relative_error"] <= 1e-6
    for i in range(1, s["lakes"] + 1):
        lv = res.level[res.lake_id == i]
        assert np.ptp(lv) == 0.0  # flat water surface
    wet = res.depth > 0
    assert (res.level[wet] <= F[wet] + 1e-9).all()  # never above the spill level


@pytest.mark.parametrize("depth_m", [0.0, 0.01, 0.3, 1.0, 3.0, 50.0])
def test_budget_and_flat_surfaces(cl_env, depth_m):
    res, h, F = solve(cl_env, two_basins(), depth_m)
    check(res, h, F)


def test_spill_reaches_downstream_basin(cl_env):
    # rain only fills A beyond its saddle at 8 m when it has enough water; B lower gets the excess
    res, h, F = solve(cl_env, two_basins(), 3.0)  # A (capacity 960 m^3) receives at least 120 cells * 12 m^3
    a = res.level[9, 8]
    b = res.level[9, 30]
    assert a == pytest.approx(8.0)  # A is full to its saddle
    vol_b = res.depth[5:15, 22:37].sum() * 4.0
    assert vol_b > 150 * 12.0  # more than B's own rain: A's excess arrived
    total = 20 * 40 * 3.0 * 4.0
    vol_a = res.depth[5:15, 3:15].sum() * 4.0
    # B holds everything that fell on the map except A's share and what ran off the map edge
    assert vol_b > 0 and b < 8.0
    assert vol_a + vol_b + res.stats["volume_out_m3"] == pytest.approx(total, rel=1e-9)
    assert res.stats["depressions"] == 1 and res.stats["basins"] == 2  # A spills into its sibling B


def test_merge_into_one_lake(cl_env):
    res, h, F = solve(cl_env, two_basins(), 50.0)
    assert res.stats["lakes"] == 1
    lv = res.level[res.depth > 0]
    assert np.ptp(lv) == 0 and lv[0] == pytest.approx(10.0)  # both basins and the channel under one level


def test_random_terrain_and_reference_accumulation(cl_env):
    rng = np.random.default_rng(2)
    h = (rng.random((25, 31)) * 10).astype(np.float32)
    h[rng.random(h.shape) < 0.03] = np.nan
    res_d, h2, F = solve(cl_env, h, 0.7)
    check(res_d, h2, F)
    res_r, _, _ = solve(cl_env, h, 0.7, accumulate=lambda c, w: ref.accumulate(c, w))
    np.testing.assert_array_equal(res_d.depth, res_r.depth)


def test_no_depressions(cl_env):
    yy, xx = np.mgrid[0:10, 0:12]
    res, h, F = solve(cl_env, (xx + yy).astype(np.float32), 1.0)
    assert res.stats["lakes"] == 0 and (res.depth == 0).all()


def test_hack_exponent_matches_brute_force():
    """Mainstream length = longest upstream path, by explicit walks; main
    stems traced from the outlets by the longest donor."""
    from worldlib.flow import reference as ref
    from stages.hydrology.rivers import hack_exponent

    rng = np.random.default_rng(3)
    h = ref.canonical(rng.random((30, 34)) * 50 + np.linspace(0, 40, 34)[None, :])
    kind = ref.cell_kinds(h)
    code = ref.d8(ref.priority_flood(h, eps=True, kind=kind), kind, 5.0)
    rcv = ref.receivers(code)
    A = ref.accumulate(code).astype(np.float64).ravel() * 25.0
    step = np.where(np.clip(code.ravel(), 0, 7) % 2 == 1, 5.0 * np.sqrt(2.0), 5.0)
    L = np.zeros(rcv.size)
    for s in range(rcv.size):  # walk down from every cell, the path length so far reaches each cell below
        c, d = s, 0.0
        while rcv[c] >= 0:
            d += step[c]
            c = rcv[c]
            L[c] = max(L[c], d)
    amin = 500.0
    sel = (A >= amin) & (L > 0)
    h_all = np.polyfit(np.log(A[sel]), np.log(L[sel]), 1)[0]
    stem = []
    for o in np.flatnonzero((code.ravel() == ref.OUTLET) & (A >= amin)):
        c = o
        while c >= 0 and A[c] >= amin and L[c] > 0:
            stem.append(c)
            don = np.flatnonzero(rcv == c)
            c = don[np.argmax(L[don] + step[don])] if don.size else -1
    stem = np.array(stem)
    h_stem = np.polyfit(np.log(A[stem]), np.log(L[stem]), 1)[0]
    got = hack_exponent(code, A.reshape(code.shape), 5.0, amin)
    assert got["hack_cells"] == sel.sum() and got["hack_mainstem_cells"] == stem.size
    assert got["hack_exponent"] == pytest.approx(h_all, abs=1e-9)
    assert got["hack_exponent_mainstem"] == pytest.approx(h_stem, abs=1e-9)
    assert got["longest_flow_path_m"] == pytest.approx(L.max())


def merge_cases():
    rng = np.random.default_rng(11)
    yield "two_basins", two_basins()
    yield "noise", (rng.random((45, 38)) * 20).astype(np.float32)
    nested = np.full((33, 33), 10.0, np.float32)
    for k in range(1, 16):
        nested[k:-k, k:-k] = 10.0 - k * (0.5 if k % 2 else -0.3)
    yield "nested", nested
    plateau = np.round(rng.random((40, 40)) * 3).astype(np.float32)  # many equal heights: ties by index
    yield "ties", plateau
    yield "flat", np.zeros((10, 12), np.float32)


@pytest.mark.parametrize("name,h", list(merge_cases()), ids=[c[0] for c in merge_cases()])
def test_solve_with_kernel_sweep_equals_reference_sweep(cl_env, name, h):
    res_dev, _, _ = solve(cl_env, h, 0.5)
    res_ref, _, _ = solve(cl_env, h, 0.5, merge_sweep=lakes.merge_tree_reference)
    for f in ("level", "depth", "lake_id"):
        assert getattr(res_dev, f).tobytes() == getattr(res_ref, f).tobytes(), f
    assert res_dev.spills == res_ref.spills and res_dev.stats == res_ref.stats


# --------------------------------------------------------------------------- the sparse solve


def holey_fractal(n, seed, beta):
    """Fractal terrain with NaN cells, an inf block and a NaN strip at the left edge; varying runoff."""
    from tests.worldlib.flow.worlds import fractal

    h = fractal(n, seed, beta)
    r = np.random.default_rng(seed + 100)
    h[r.random(h.shape) < 0.01] = np.nan
    a, b = (int(x) for x in r.integers(10, n - 30, 2))
    h[a:a + 12, b:b + 9] = np.inf
    h[n // 3: n // 3 + 5, :7] = np.nan
    return h, r.random(h.shape) * 2.0


def prepared(cl_env, h, depth_m, weights=None, area=4.0):
    """solve_lakes' inputs as lake_maps builds them (no-data NaN, code_raw on the data heights)."""
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    h[kind == ref.NODATA] = np.nan
    F = dev.fill(cl_env, h, kind, False)
    code = dev.d8(cl_env, np.nan_to_num(dev.fill(cl_env, h, kind, True), nan=0.0), kind, 2.0)
    code_raw = dev.d8(cl_env, np.where(np.isfinite(h), h, np.float32(0)), kind, 2.0)
    runoff = np.where(np.isfinite(h), depth_m * area, 0.0) * (1.0 if weights is None else weights)
    return h, kind, F, code, code_raw, runoff, area


def solve_prepared(cl_env, args):
    return lakes.solve_lakes(*args, functools.partial(dev.accumulate, cl_env),
                             functools.partial(dev.merge_sweep, cl_env))


def digest(res) -> str:
    import hashlib

    d = hashlib.sha256()
    for f in ("level", "depth", "lake_id"):
        d.update(getattr(res, f).tobytes())
    d.update(repr([(int(x), int(t), float(v)) for x, t, v in res.spills]).encode())
    return d.hexdigest()[:16]


def golden_worlds():
    yield "two_basins", two_basins(), 3.0, None, "7f7d24f07900c2e1"
    rng = np.random.default_rng(2)
    h = (rng.random((25, 31)) * 10).astype(np.float32)
    h[rng.random(h.shape) < 0.03] = np.nan
    yield "random_nan", h, 0.7, None, "50d089a49c135ffa"
    hf, wf = holey_fractal(100, 1, 2.2)
    yield "fractal", hf, 0.3, wf, "7863fa2dbcaa2ada"


@pytest.mark.parametrize("name,h,depth_m,w,want", list(golden_worlds()), ids=[c[0] for c in golden_worlds()])
def test_sparse_solve_is_bitwise_the_whole_array_solve(cl_env, name, h, depth_m, w, want):
    """Levels, depths, labels and spills bitwise those of the whole-array
    solve the sparse one replaced (digests of its results at commit
    b62f1c3); the float sums of the stats are correctly rounded now."""
    assert digest(solve_prepared(cl_env, prepared(cl_env, h, depth_m, w))) == want


@pytest.mark.parametrize("n,seed,beta", [(120, 4, 1.6), (90, 5, 2.4)])
def test_sparse_solve_equals_its_whole_maps(cl_env, n, seed, beta):
    """solve_depressions on the gathered cells is solve_lakes' whole maps at
    those cells, dry elsewhere; the labels are scipy's on the whole map."""
    from scipy import ndimage

    h, w = holey_fractal(n, seed, beta)
    args = prepared(cl_env, h, 0.4, w)
    whole = solve_prepared(cl_env, args)
    dc = lakes.gather_depressions(*args[:-1], functools.partial(dev.accumulate, cl_env))
    sol = lakes.solve_depressions(dc, args[-1], functools.partial(dev.merge_sweep, cl_env))
    assert dc.size > 100 and sol.stats["lakes"] > 10
    for f in ("level", "depth", "lake_id"):
        full = getattr(whole, f).ravel()
        assert full[dc.cells].tobytes() == getattr(sol, f).tobytes(), f
        rest = np.delete(full, dc.cells)
        assert (np.isnan(rest) if f == "level" else rest == 0).all(), f
    want_id, nlakes = ndimage.label(whole.depth > 0, structure=np.ones((3, 3), bool))
    np.testing.assert_array_equal(whole.lake_id, want_id)
    assert sol.stats == whole.stats and sol.stats["lakes"] == nlakes and sol.spills == whole.spills
    check(whole, args[0], args[2])


def test_depression_cells_hold_nothing_world_sized(cl_env):
    h, w = holey_fractal(100, 1, 2.2)
    args = prepared(cl_env, h, 0.3, w)
    dc = lakes.gather_depressions(*args[:-1], functools.partial(dev.accumulate, cl_env))
    m, k = dc.size, dc.exits.size
    assert 0 < m < h.size // 4 and 0 < k <= m and dc.n_cells == h.size and dc.cols == h.shape[1]
    arrays = {f: getattr(dc, f) for f in dc.__dataclass_fields__ if isinstance(getattr(dc, f), np.ndarray)}
    assert set(arrays) == set(dc.PER_CELL) | set(dc.PER_EXIT)
    for f, a in arrays.items():
        assert a.shape[0] == (m if f in dc.PER_CELL else k), f
    assert np.all(np.diff(dc.cells) > 0) and dc.cells.dtype == np.int64 and dc.exit.dtype == np.int64
    assert set(np.unique(dc.exit).tolist()) == set(dc.exits.tolist())
    with pytest.raises(ValueError, match="rows"):
        lakes.DepressionCells(**{**{f: getattr(dc, f) for f in dc.__dataclass_fields__}, "acc": np.zeros(h.size)})


def test_sparse_solve_of_a_world_without_depressions(cl_env):
    yy, xx = np.mgrid[0:10, 0:12]
    args = prepared(cl_env, (xx + yy).astype(np.float32), 1.0)
    dc = lakes.gather_depressions(*args[:-1], functools.partial(dev.accumulate, cl_env))
    sol = lakes.solve_depressions(dc, args[-1])
    assert dc.size == 0 and dc.exits.size == 0 and sol.level.size == sol.depth.size == sol.lake_id.size == 0
    assert sol.stats["lakes"] == 0 and sol.stats["volume_out_m3"] == sol.stats["volume_in_m3"] == 120 * 4.0
    res = solve_prepared(cl_env, args)
    assert (res.depth == 0).all() and np.isnan(res.level).all() and res.stats == sol.stats


def test_depression_spilling_into_no_data(cl_env):
    """A basin whose lowest rim is the edge ring around a no-data hole: it
    fills to that ring's height and spills into the hole (off the map)."""
    h = np.full((30, 30), 10.0, np.float32)
    h[5:25, 5:25] = 0.0  # basin floor 0, rim 10
    h[12:18, 12:18] = 5.0  # a mound in the basin ...
    h[14:16, 14:16] = np.nan  # ... around a hole: the mound's cells next to it are outlets at 5 m
    args = prepared(cl_env, h, 20.0)
    res = solve_prepared(cl_env, args)
    dc = lakes.gather_depressions(*args[:-1], functools.partial(dev.accumulate, cl_env))
    assert (dc.F == 5.0).all() and dc.size == 20 * 20 - 36
    assert res.stats["lakes"] == 1 and res.level[6, 6] == 5.0 and np.nanmax(res.level) == 5.0
    assert len(res.spills) == 1 and res.spills[0][1] == -1  # the excess leaves through the hole
    x = res.spills[0][0]
    assert args[0].ravel()[x] == 5.0 and 12 <= x // 30 < 18 and 12 <= x % 30 < 18  # a mound cell
    check(res, args[0], args[2])
    assert res.stats["volume_stored_m3"] == pytest.approx(364 * 5.0 * 4.0, rel=1e-12)
