"""Tiled D8 directions and accumulation (Barnes 2017) against the untiled
device.d8 and device.accumulate the hydrology stage uses, bit for bit, on
epsilon-filled terrains whose flow runs along tile edges, through tile
corners and across many tiles; and the fixed-point scale of
device.quantize from per-tile exact sums."""
import math

import numpy as np
import pytest

from worldlib.flow import device as dev
from worldlib.flow import reference as ref
from worldlib.flow import tiled_accum as ta
from worldlib.flow import tiled_fill as tf

from .worlds import fractal, random_small_worlds

DX = 8.0


def serpentine(rows: int = 41, cols: int = 45) -> np.ndarray:
    """One channel snaking east and west between walls down the whole map:
    a single path through every tile row many times, its outlet a low
    border cell at the end."""
    z = np.full((rows, cols), 2000.0, np.float32)
    i = 0
    for k, r in enumerate(range(1, rows - 1, 2)):
        cs = range(1, cols - 1) if k % 2 == 0 else range(cols - 2, 0, -1)
        for c in cs:
            z[r, c] = 1000.0 - 0.1 * i
            i += 1
        if r + 1 < rows - 1:
            z[r + 1, c] = 1000.0 - 0.1 * i  # the gap in the wall below the row's last cell
            i += 1
    z[r + 1, c] = 0.0  # the outlet on the south border, below the snake's last cell
    return z


def terrains():
    rng = np.random.default_rng(21)
    yield "noise", (rng.random((61, 47)) * 50 + 100).astype(np.float32)
    yield "fractal", fractal(96, 3)[:90, :77]
    yield "flats", np.round(rng.random((53, 59)) * 4).astype(np.float32)  # epsilon-filled flats: long ties
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float32)
    yield "edges", 2 * np.minimum(abs(yy - 16), abs(yy - 21)) + 0.05 * (64 - xx)  # east along rows 16 and 21
    yield "edges_T", (2 * np.minimum(abs(yy - 16), abs(yy - 21)) + 0.05 * (64 - xx)).T.copy()  # south along columns
    diag = 3 * abs(yy - xx) + 0.1 * (128 - yy - xx)  # down the main diagonal through the tile corners
    anti = 3 * abs(yy + xx - 63) + 0.1 * (64 + yy - xx)  # and the anti-diagonal, r + c = 63
    yield "corners", np.minimum(diag, anti).astype(np.float32)
    yield "serpentine", serpentine()
    nd = fractal(64, 8)[:60, :62]
    nd[rng.random(nd.shape) < 0.04] = np.nan
    nd[20:30, 14:34] = np.inf  # a no-data block across tile borders
    nd[:, 40] = np.nan  # a no-data column cutting the world in two
    yield "nodata", nd
    yield "flat", np.zeros((20, 30), np.float32)


CASES = list(terrains())
TILES = (16, 7, 23, 1000)  # uneven (world not a multiple), small, and one tile for the whole world


def routed(env, h):
    """The stage's routing surface (epsilon fill, NaN on no-data) and the world's codes."""
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    R = dev.fill(env, h, kind, eps=True)
    code = dev.d8(env, R, kind, DX)
    assert not (code == ref.PIT).any()
    return R, code


_ROUTED: dict = {}


@pytest.fixture
def worlds(cl_env):
    """Every case routed once per device (the fixture cl_env is per test)."""
    key = getattr(cl_env, "fingerprint", id(cl_env))
    if key not in _ROUTED:
        _ROUTED[key] = {name: routed(cl_env, h) for name, h in CASES}
    return _ROUTED[key]


@pytest.mark.parametrize("name", [c[0] for c in CASES])
@pytest.mark.parametrize("tile", TILES)
def test_tiled_d8_equals_untiled_bitwise(cl_env, worlds, name, tile):
    R, code = worlds[name]
    np.testing.assert_array_equal(ta.tiled_d8(R, DX, tile, cl_env), code)


@pytest.mark.parametrize("name", [c[0] for c in CASES])
@pytest.mark.parametrize("tile", TILES)
def test_tiled_accumulation_equals_untiled_bitwise(cl_env, worlds, name, tile):
    _, code = worlds[name]
    want = dev.accumulate(cl_env, code)
    got = ta.tiled_accumulate(code, tile, None, cl_env)
    assert got.dtype == want.dtype == np.uint32
    np.testing.assert_array_equal(got, want)
    w = np.random.default_rng(tile).integers(0, 10 ** 12, code.shape)
    got_w = ta.tiled_accumulate(code, tile, w, cl_env)
    assert got_w.dtype == np.int64
    np.testing.assert_array_equal(got_w, dev.accumulate(cl_env, code, w))


@pytest.mark.parametrize("tile", (1, 2, 3, 5))
def test_tiny_tiles_with_the_reference(tile):
    """Tiles of one to a few cells (every cell on a perimeter, every move a
    crossing), the per-tile work being the numpy reference."""
    h = ref.canonical(fractal(32, 6)[:19, :23])
    h[4:6, 7:9] = np.nan
    kind = ref.cell_kinds(h)
    R = ref.priority_flood(h, True, kind)
    code = ref.d8(R, kind, DX)
    np.testing.assert_array_equal(ta.tiled_d8(R, DX, tile), code)
    np.testing.assert_array_equal(ta.tiled_accumulate(code, tile), ref.accumulate(code).astype(np.uint32))
    w = np.random.default_rng(0).integers(0, 1000, code.shape)
    np.testing.assert_array_equal(ta.tiled_accumulate(code, tile, w), ref.accumulate(code, w))


def crossings(code: np.ndarray, tile: int) -> dict:
    """Moves between tiles by kind: into a side neighbour or through a corner."""
    r, c = np.nonzero(code >= 0)
    k = code[r, c].astype(int)
    rr, cc = r + ref.DR[k], c + ref.DC[k]
    dr, dc = rr // tile != r // tile, cc // tile != c // tile
    return {"side": int((dr ^ dc).sum()), "corner": int((dr & dc).sum())}


def test_the_cases_cross_tiles_as_intended(worlds):
    """The equality tests above do meet diagonal moves through tile corners,
    flow along tile edges and paths across many tiles."""
    assert crossings(worlds["corners"][1], 16)["corner"] >= 4
    assert crossings(worlds["noise"][1], 7)["corner"] >= 10
    edges = worlds["edges"][1]
    assert (edges[16, 1:-1] == 2).all() and (edges[21, 1:-1] == 2).all()  # east along tile rows' first/last row
    code = worlds["serpentine"][1]
    assert crossings(code, 7)["side"] >= 100
    acc = ref.accumulate(code)
    assert acc.max() >= 800  # the one channel gathers the whole snake


def test_the_global_pass_is_needed(cl_env, worlds):
    """Without pass 2's inflows the tiles are only their local sums: the
    comparison above can fail."""
    _, code = worlds["serpentine"]
    want = dev.accumulate(cl_env, code)
    out = np.empty_like(want)
    for row in tf.tile_slices(code.shape, 16):
        for rs, cs in row:
            p = ta.accumulate_tile(code[rs, cs], (rs.start, cs.start), None, cl_env)
            out[rs, cs] = ta.finish_tile(code[rs, cs], np.zeros_like(p.local_sum), None, cl_env)
    assert (out != want).sum() > 100
    np.testing.assert_array_equal(ta.tiled_accumulate(code, 16, None, cl_env), want)


def test_perimeter_data_is_small(cl_env, worlds):
    """Pass 2 reads a few numbers per perimeter cell, not the tile."""
    _, code = worlds["fractal"]
    p = ta.accumulate_tile(code[:48, :40], (0, 0), None, cl_env)
    n = 2 * 48 + 2 * 40 - 4
    assert p.code.size == p.exit.size == p.local_sum.size == n
    assert ((p.exit >= -1) & (p.exit < n)).all()


@pytest.mark.parametrize("nr", (1, 2, 3, 5))
@pytest.mark.parametrize("nc", (1, 2, 3, 6))
def test_perimeter_position_inverts_perimeter_cells(nr, nc):
    cells = ta.perimeter_cells(nr, nc)
    lr, lc = np.divmod(cells, nc)
    np.testing.assert_array_equal(ta.perimeter_position(lr, lc, nr, nc), np.arange(cells.size))


def test_a_cycle_is_refused():
    code = np.full((4, 4), ref.OUTLET, np.int8)
    code[1, 1], code[1, 2], code[2, 2], code[2, 1] = 2, 4, 6, 0  # a loop over four 1-cell tiles
    with pytest.raises(ValueError, match="cycle"):
        ta.tiled_accumulate(code, 1)


# --------------------------------------------------------------------------- quantize


def weight_maps():
    rng = np.random.default_rng(4)
    yield "rain", rng.random((70, 53)) * 0.9 * 64.0  # runoff (m/year) times a cell area
    w = rng.lognormal(0, 6, (41, 37))
    w[rng.random(w.shape) < 0.05] = np.nan
    w[0, :3] = (np.inf, -np.inf, -5.0)
    yield "dirty", w
    yield "wide", np.array([[1e300, 5e-324, 1e-310], [3.0, 1e-20, 2.0 ** 1000]])  # subnormals, huge values
    yield "zeros", np.zeros((9, 11))
    yield "power_of_two", np.full((64, 64), 2.0 ** -10)  # total exactly 4: quantize halves its first scale


WEIGHTS = list(weight_maps())


@pytest.mark.parametrize("name,w", WEIGHTS, ids=[c[0] for c in WEIGHTS])
@pytest.mark.parametrize("tile", (1, 5, 16, 1000))
def test_exact_sum_is_fsum_for_any_tiling(name, w, tile):
    clean = np.maximum(np.nan_to_num(w, nan=0.0, posinf=0.0), 0.0)
    sums = [ta.exact_sum(w[rs, cs]) for row in tf.tile_slices(w.shape, tile) for rs, cs in row]
    assert ta.exact_total(sums) == math.fsum(clean.ravel())


@pytest.mark.parametrize("name,w", WEIGHTS, ids=[c[0] for c in WEIGHTS])
@pytest.mark.parametrize("tile", (1, 5, 16, 1000))
def test_tiled_quantize_equals_quantize(name, w, tile):
    q, scale = dev.quantize(w)
    q2, scale2 = ta.tiled_quantize(w, tile)
    assert scale2 == scale
    np.testing.assert_array_equal(q2, q)


def test_the_halving_case_is_met():
    w = dict(WEIGHTS)["power_of_two"]
    assert ta.first_scale(ta.exact_total([ta.exact_sum(w)])) == 2.0 ** 60
    assert ta.tiled_quantize(w, 7)[1] == 2.0 ** 59 == dev.quantize(w)[1]


def test_quantized_discharge_tiled_equals_untiled(cl_env, worlds):
    """The stage's discharge path: quantize, accumulate; every step by tiles."""
    _, code = worlds["nodata"]
    rain = np.where(code != ref.NODATA_CODE, np.random.default_rng(9).random(code.shape) * 57.6, 0.0)
    q, scale = dev.quantize(rain)
    want = dev.accumulate(cl_env, code, q)
    q2, scale2 = ta.tiled_quantize(rain, 16)
    assert scale2 == scale
    np.testing.assert_array_equal(ta.tiled_accumulate(code, 16, q2, cl_env), want)


def test_a_numpy_total_across_the_scale_step():
    """A total that numpy's pairwise sum and the exact sum put on either
    side of first_scale's step (4 + 11 ulps and 4 + 12 ulps: scales 2^60
    and 2^59): device.quantize sums exactly (math.fsum), as the tiles do
    (exact_sum), so both find 2^59 and the same integers."""
    four = 4.0
    step = four
    while ta.first_scale(step) == 2.0 ** 60:
        step = np.nextafter(step, 8.0)
    ulp = np.spacing(four)
    assert (step - four) / ulp == 12
    w = np.array([[step - ulp, 0.3 * ulp, 0.3 * ulp]])
    assert w.sum() == step - ulp and math.fsum(w.ravel()) == step  # numpy drops both halves of an ulp
    assert ta.first_scale(w.sum()) == 2.0 ** 60 and ta.first_scale(math.fsum(w.ravel())) == 2.0 ** 59
    q, scale = dev.quantize(w)
    q2, scale2 = ta.tiled_quantize(w, 1)
    assert scale == scale2 == 2.0 ** 59
    np.testing.assert_array_equal(q, q2)


def test_random_worlds_and_tilings():
    """Many small worlds and tile sizes, the numpy reference on both sides."""
    for trial, h, tile in random_small_worlds(77, 40, 24):
        kind = ref.cell_kinds(h)
        R = ref.priority_flood(h, True, kind)
        code = ref.d8(R, kind, DX)
        msg = f"trial {trial}: {h.shape}, tile {tile}"
        np.testing.assert_array_equal(ta.tiled_d8(R, DX, tile), code, err_msg=msg)
        np.testing.assert_array_equal(ta.tiled_accumulate(code, tile), ref.accumulate(code).astype(np.uint32),
                                      err_msg=msg)


def test_tiles_in_separate_processes(cl_env, worlds):
    """Passes 1 and 3 in worker processes that receive one tile each (the
    numpy reference there, no device), pass 2 on the perimeters alone: the
    untiled device result, weighted too."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    _, code = worlds["serpentine"]
    w = np.random.default_rng(5).integers(0, 10 ** 9, code.shape)
    grid = [x for row in tf.tile_slices(code.shape, 16) for x in row]
    tx = len(tf.tile_slices(code.shape, 16)[0])
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        perims = list(pool.map(ta.accumulate_tile, [code[rs, cs] for rs, cs in grid],
                               [(rs.start, cs.start) for rs, cs in grid], [w[rs, cs] for rs, cs in grid]))
        inflow = [x for row in ta.solve_inflow([perims[i:i + tx] for i in range(0, len(perims), tx)]) for x in row]
        tiles = list(pool.map(ta.finish_tile, [code[rs, cs] for rs, cs in grid], inflow,
                              [w[rs, cs] for rs, cs in grid]))
    out = np.empty(code.shape, np.int64)
    for (rs, cs), t in zip(grid, tiles):
        out[rs, cs] = t
    np.testing.assert_array_equal(out, dev.accumulate(cl_env, code, w))
