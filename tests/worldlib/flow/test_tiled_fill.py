"""The tiled fill (Barnes 2016) against the untiled fill the hydrology stage
uses (device.fill, eps=False), bit for bit, on terrains whose depressions,
flats and no-data cross tile borders."""
import numpy as np
import pytest

from worldlib.flow import device as dev
from worldlib.flow import reference as ref
from worldlib.flow import tiled_fill as tf

from .worlds import fractal, random_small_worlds


def terrains():
    rng = np.random.default_rng(11)
    yield "noise", (rng.random((61, 47)) * 50 + 100).astype(np.float32)
    yield "fractal", fractal(96, 3)[:90, :77]
    pits = fractal(64, 5)
    pits[rng.random(pits.shape) < 0.05] -= 40.0  # single-cell pits everywhere
    yield "pits", pits
    yield "flats", np.round(rng.random((53, 59)) * 4).astype(np.float32)  # many ties and flats
    plateau = (rng.random((48, 48)) * 2).astype(np.float32)
    plateau[8:40, 8:40] = 30.0  # a plateau across the borders of 4 tiles of 16
    plateau[16:32, 16:32] = 10.0  # holding a lake that spills over the plateau's rim
    yield "plateau", plateau
    yy, xx = np.mgrid[0:70, 0:70]
    bowl = (((xx - 35.0) ** 2 + (yy - 35.0) ** 2) * 0.01 + 50).astype(np.float32)  # one pit spans every tile
    bowl[:, 0] = bowl[0, :] = bowl[:, -1] = bowl[-1, :] = 200.0
    bowl[0, 50] = 60.0  # its outlet on the map border
    bowl += (rng.random(bowl.shape) * 0.5).astype(np.float32)
    yield "bowl", bowl
    nd = fractal(64, 8)[:60, :62]
    nd[rng.random(nd.shape) < 0.04] = np.nan
    nd[20:30, 14:34] = np.inf  # a no-data block across tile borders, its rim outlets
    nd[:, 40] = np.nan  # a no-data column cutting the world in two
    yield "nodata", nd
    yield "negative", (rng.random((33, 35)) * 2 - 1).astype(np.float32)
    yield "flat", np.zeros((20, 30), np.float32)


CASES = list(terrains())
TILES = (16, 7, 23, 1000)  # uneven (world not a multiple), small, and one tile for the whole world


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def untiled(env, h):
    h = ref.canonical(h)
    return dev.fill(env, h, ref.cell_kinds(h), eps=False)


@pytest.mark.parametrize("name,h", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("tile", TILES)
def test_tiled_fill_equals_untiled_bitwise(cl_env, name, h, tile):
    want = untiled(cl_env, h)
    got = tf.tiled_fill(h, tile, cl_env)
    np.testing.assert_array_equal(bits(got), bits(want))


@pytest.mark.parametrize("tile", (1, 2, 3, 5))
def test_tiny_tiles_with_the_reference_fill(tile):
    """Tiles of one to a few cells (every cell on a perimeter), the per-tile
    fill being the numpy reference."""
    rng = np.random.default_rng(tile)
    h = np.round(rng.random((13, 17)) * 6).astype(np.float32)
    h[rng.random(h.shape) < 0.08] = np.nan
    h = ref.canonical(h)
    want = ref.priority_flood(h, False)
    np.testing.assert_array_equal(bits(tf.tiled_fill(h, tile)), bits(want))


def test_random_worlds_and_tilings():
    """Many small worlds and tile sizes, the numpy reference on both sides."""
    for trial, h, tile in random_small_worlds(99, 60, 26):
        np.testing.assert_array_equal(bits(tf.tiled_fill(h, tile)), bits(ref.priority_flood(h, False)),
                                      err_msg=f"trial {trial}: {h.shape}, tile {tile}")


def test_the_global_pass_is_needed(cl_env):
    """Without the levels of pass 2 the bowl (one depression over 3x3 tiles)
    stays unfilled: the comparison above can fail."""
    h = ref.canonical(dict(CASES)["bowl"])
    padded = np.pad(h, 1, constant_values=np.nan)
    out = np.empty_like(h)
    for row in tf.tile_slices(h.shape, 30):
        for rs, cs in row:
            t = tf.fill_tile(h[rs, cs], tf.tile_kind(padded[rs.start:rs.stop + 2, cs.start:cs.stop + 2]), cl_env)
            out[rs, cs] = tf.finish_tile(t.filled, t.labels, np.full(t.perimeter.n_labels + 1, -np.inf, np.float32))
    want = untiled(cl_env, h)
    assert (out < want).sum() > 1000
    np.testing.assert_array_equal(bits(tf.tiled_fill(h, 30, cl_env)), bits(want))


def test_tile_kind_is_the_world_kind_cut():
    h = ref.canonical(dict(CASES)["nodata"])
    kind = ref.cell_kinds(h)
    padded = np.pad(h, 1, constant_values=np.nan)
    for row in tf.tile_slices(h.shape, 16):
        for rs, cs in row:
            np.testing.assert_array_equal(tf.tile_kind(padded[rs.start:rs.stop + 2, cs.start:cs.stop + 2]), kind[rs, cs])


def test_perimeter_data_is_small(cl_env):
    """What pass 2 reads grows with the tile's perimeter, not its area."""
    h = ref.canonical(fractal(128, 4))
    kind = ref.cell_kinds(h)
    t = tf.fill_tile(h, kind, cl_env)
    p = t.perimeter
    assert p.n_labels <= 4 * 128 - 4
    assert p.top[0].size == p.bottom[0].size == p.left[0].size == p.right[0].size == 128
    assert p.spill[0].size < 4 * p.n_labels + 8  # an almost planar graph of watersheds
    assert set(np.unique(t.labels)) <= set(range(-1, p.n_labels + 1))


@pytest.mark.parametrize("name", ["fractal", "bowl", "flats", "nodata"])
def test_epsilon_finish_is_exact_given_the_perimeter(cl_env, name):
    """The epsilon fill's last pass: with the final values of a tile's
    perimeter, the tile's own epsilon fill is the untiled one, bit for bit."""
    h = ref.canonical(dict(CASES)[name])
    kind = ref.cell_kinds(h)
    want = dev.fill(cl_env, h, kind, eps=True)
    for row in tf.tile_slices(h.shape, 16):
        for rs, cs in row:
            got = tf.finish_tile_eps(h[rs, cs], kind[rs, cs], want[rs, cs], cl_env)
            np.testing.assert_array_equal(bits(got), bits(want[rs, cs]))


def test_bad_tile_size():
    with pytest.raises(ValueError, match="tile size"):
        tf.tiled_fill(np.zeros((4, 4), np.float32), 0)


@pytest.mark.parametrize("name,h", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("tile", (16, 23, 1000))
def test_tiled_epsilon_fill_equals_untiled_bitwise(cl_env, name, h, tile):
    """The epsilon fill (the stage's routing surface) by rounds of
    neighbour perimeters: exact, in a number of rounds that is not fixed."""
    h = ref.canonical(h)
    want = dev.fill(cl_env, h, ref.cell_kinds(h), eps=True)
    got, rounds = tf.tiled_fill_eps(h, tile, cl_env)
    np.testing.assert_array_equal(bits(got), bits(want))
    assert rounds == 2 if tile == 1000 else 2 <= rounds <= 30  # one tile: its fill, then a round that confirms it


def test_epsilon_rounds_stop_at_the_cap():
    h = ref.canonical(dict(CASES)["bowl"])
    with pytest.raises(ValueError, match="no fixed point after 1 rounds"):
        tf.tiled_fill_eps(h, 16, None, max_rounds=1)


def test_a_surface_with_no_unsettled_cell_is_its_own_epsilon_fill():
    """eps_unsettled counts the cells the epsilon fill would raise: none
    exactly where the fill leaves the surface as it is (filled surfaces,
    raw land with pits, land with sub-step slopes below 1 m)."""
    rng = np.random.default_rng(3)
    for trial in range(40):
        h = (rng.random((int(rng.integers(3, 30)), int(rng.integers(3, 30)))) * (2.0 if trial % 2 else 200.0))
        h = ref.canonical(h.astype(np.float32))
        if trial % 3 == 0:
            h = ref.priority_flood(h, eps=True)  # its own fill
        kind = ref.cell_kinds(h)
        halo = np.pad(h, 1, constant_values=np.nan)
        unchanged = np.array_equal(ref.priority_flood(h, eps=True, kind=kind), h, equal_nan=True)
        assert (tf.eps_unsettled(halo, kind) == 0) == unchanged, trial
