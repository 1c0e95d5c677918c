"""Every kernel against its numpy reference, determinism across work-group
sizes, and the physics of each on simple inputs.

Tolerance: the kernels switch fma contraction off, divide and take square
roots correctly rounded and use no library maths except atan/atan2 (slope,
aspect). On PoCL (the default device) every other output is compared bit
for bit; slope and aspect within 1e-4 degrees. On another device a few
float32 ulps are allowed."""
import numpy as np
import pytest

from stages.vegetation import attributes as at
from stages.vegetation import device as dev
from stages.vegetation import ecosystem as eco
from stages.vegetation import placement as pl
from stages.vegetation import reference as ref
from stages.vegetation.params import VegetationParams
from stages.vegetation.stage import preference_table, splat_table

from .conftest import on_pocl, synthetic_height

pytestmark = pytest.mark.every_device  # kernels against their references on each runtime

DX = 8.0


def same(env, a, b, atol=0.0):
    if on_pocl(env) and atol == 0.0:
        np.testing.assert_array_equal(a, b)
    else:
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=max(atol, 1e-5))


def attr_args(h, nd=8):
    sun0, sun1, inv = at.sun_table(46.0, nd)
    return (h, DX, 3, 1.0 / (3 * DX) ** 2, at.directions(nd), at.march_steps(DX, 600.0, 1.3), sun0, sun1, inv, 0.3)


@pytest.fixture(scope="module")
def terrain():
    return synthetic_height(37, 45, DX, seed=3)


def test_attributes_match_reference(cl_env, terrain):
    want = ref.attributes(*attr_args(terrain))
    for local in (None, (8, 4)):
        got = dev.attributes(cl_env, *attr_args(terrain), local=local)
        for name, g, w in zip(("slope", "aspect", "grad", "curvature", "sky", "sun"), got, want):
            if name in ("slope", "aspect"):
                np.testing.assert_allclose(g, w, atol=1e-4, rtol=0, err_msg=name)
            else:
                same(cl_env, g, w)


def test_horizon_rays_inside_the_world_match_the_reference(cl_env):
    """A scan short beside the world: most rays stay inside it and take the
    kernel's path without clamps, the rest clamp at the edges; both give the
    reference's bits, whole and in tiles (attr_args' 600 m scan leaves the
    37 x 45 world from almost every cell)."""
    sun0, sun1, inv = at.sun_table(46.0, 12)
    h = synthetic_height(70, 61, DX, seed=11)
    args = (DX, 3, 1.0 / (3 * DX) ** 2, at.directions(12), at.march_steps(DX, 80.0, 1.3), sun0, sun1, inv, 0.3)
    want = ref.attributes(h, *args)
    got = dev.attributes(cl_env, h, *args)
    for name, g, w in zip(("slope", "aspect", "grad", "curvature", "sky", "sun"), got, want):
        if name not in ("slope", "aspect"):
            same(cl_env, g, w)
    halo = int(np.ceil(at.march_steps(DX, 80.0, 1.3)[-1])) + 1
    window = ref.Window(20, 17, 70, 61, halo, halo, 24, 20)  # a 24 x 20 tile inside the 70 x 61 world
    part = dev.attributes(cl_env, h[20:20 + 24 + 2 * halo, 17:17 + 20 + 2 * halo], *args, window=window)
    for g, w in zip(part[2:], want[2:]):
        same(cl_env, g, w[20 + halo:20 + halo + 24, 17 + halo:17 + halo + 20])


@pytest.mark.parametrize("tile_cells", [16, 23])
def test_attributes_of_tiles_are_the_whole_worlds(cl_env, tile_cells):
    """A tile read with the attributes' halo computes the bits of the whole
    world's run, on the device and in the reference (world borders, corners
    and tiles smaller than the halo included)."""
    from pipeline.tiles import tiles_of

    params = VegetationParams(horizon_distance_m=160.0, horizon_directions=8)
    h = synthetic_height(41, 50, DX, seed=5)
    halo = at.halo_cells(DX, params)
    assert halo == int(np.ceil(at.march_steps(DX, 160.0, params.horizon_step_growth)[-1])) + 1
    for backend in (ref, dev.on(cl_env)):
        whole = at.compute(h, DX, params, backend)
        for tile in tiles_of(h.shape, tile_cells):
            r0, c0, rows, cols = tile.window(halo)
            part = at.compute(h[r0:r0 + rows, c0:c0 + cols], DX, params, backend, window=ref.Window.of(tile, halo))
            cells = np.s_[tile.row0:tile.row0 + tile.rows, tile.col0:tile.col0 + tile.cols]
            for name, field in part.items():
                np.testing.assert_array_equal(field, whole[name][cells], err_msg=f"{name} {tile.name}")
    tile = tiles_of(h.shape, tile_cells)[0]  # its right and lower sides are inside the world
    r0, c0, rows, cols = tile.window(halo - 1)
    with pytest.raises(ValueError, match="the scan reaches"):
        at.compute(h[r0:r0 + rows, c0:c0 + cols], DX, params, ref, window=ref.Window.of(tile, halo - 1))


@pytest.mark.parametrize("jitter", [0.4, 2.5])
def test_moisture_filter_of_tiles_is_the_whole_worlds(cl_env, jitter):
    from pipeline.tiles import tiles_of

    m = np.random.default_rng(4).random((29, 34)).astype(np.float32)
    halo = ref.moisture_filter_halo(jitter)
    for backend in (ref, dev.on(cl_env)):
        whole = backend.moisture_filter(m, jitter, 91)
        for tile in tiles_of(m.shape, 8):
            r0, c0, rows, cols = tile.window(halo)
            part = backend.moisture_filter(m[r0:r0 + rows, c0:c0 + cols], jitter, 91,
                                           window=ref.Window.of(tile, halo))
            np.testing.assert_array_equal(part, whole[tile.row0:tile.row0 + tile.rows,
                                                      tile.col0:tile.col0 + tile.cols], err_msg=tile.name)


def test_attributes_physics(cl_env):
    flat = np.full((20, 24), 500.0, np.float32)
    slope, aspect, grad, curv, sky, sun = dev.attributes(cl_env, *attr_args(flat))
    assert np.all(slope == 0) and np.all(curv == 0)
    np.testing.assert_allclose(sky, 1.0, atol=1e-6)
    np.testing.assert_allclose(sun, 1.0, atol=1e-5)  # open flat ground is the reference
    # planes of 30 degrees: facing south (downhill to +z) gets more sun than facing north at 46 N
    z = (np.arange(30) + 0.5)[:, None] * DX * np.ones((1, 30))
    south = (1000.0 - np.tan(np.radians(30)) * z).astype(np.float32)
    north = (np.tan(np.radians(30)) * z).astype(np.float32)
    s_s = dev.attributes(cl_env, *attr_args(south))
    s_n = dev.attributes(cl_env, *attr_args(north))
    np.testing.assert_allclose(s_s[0][5:-5, 5:-5], 30.0, atol=1e-3)
    np.testing.assert_allclose(s_s[1][5:-5, 5:-5], 180.0, atol=1e-3)  # faces south
    np.testing.assert_allclose(s_n[1][5:-5, 5:-5] % 360.0, 0.0, atol=1e-3)  # faces north
    assert s_s[5][15, 15] > 1.1 > 0.8 > s_n[5][15, 15]
    # a bowl sees less sky at its bottom than at its rim, and its bottom is concave
    r = np.hypot(*np.meshgrid(np.arange(41) - 20.0, np.arange(41) - 20.0)) * DX
    bowl = (0.002 * r ** 2).astype(np.float32)
    b = dev.attributes(cl_env, *attr_args(bowl))
    assert b[4][20, 20] < b[4][20, 35] <= 1.0 and b[3][20, 20] > 0


def test_moisture_filter_matches_reference_and_is_normalised(cl_env, terrain):
    m = np.random.default_rng(1).random(terrain.shape).astype(np.float32)
    want = ref.moisture_filter(m, 1.0, 77)
    for local in (None, (4, 4)):
        same(cl_env, dev.moisture_filter(cl_env, m, 1.0, 77, local=local), want)
    const = np.full((16, 16), 0.4, np.float32)
    # the weights (4 centre, 2 diagonal, 1 axial) sum to 16: a constant stays itself (the thesis's /12 gave 4/3 of it)
    np.testing.assert_array_equal(dev.moisture_filter(cl_env, const, 1.0, 5), const)


def test_suitability_matches_reference_and_respects_ranges(cl_env, terrain):
    p = VegetationParams()
    names = ["conifer", "broadleaf", "shrub", "grass"]
    tab = preference_table(p, names)
    slope, _, _, curv, _, sun = ref.attributes(*attr_args(terrain))
    moist = np.random.default_rng(2).random(terrain.shape).astype(np.float32)
    blocked = np.zeros(terrain.shape, np.uint8)
    blocked[5:9, 5:9] = 1
    want = ref.suitability(terrain, slope, moist, sun, curv, blocked, tab)
    for local in (None, (16,)):
        same(cl_env, dev.suitability(cl_env, terrain, slope, moist, sun, curv, blocked, tab, local=local), want)
    assert np.all(want[:, 5:9, 5:9] == 0)
    for s, name in enumerate(names):
        e = p.species[name]
        out = (terrain <= e.altitude_m.min) | (terrain >= e.altitude_m.max) | (slope >= e.slope_deg.max) \
            | (moist <= e.moisture.min) | (moist >= e.moisture.max)
        assert np.all(want[s][out] == 0), name
        assert want[s].max() <= 1.0 and want[s].min() >= 0.0
    # inside every core (away from the soft edges) the factor is exactly 1
    one = ref.suitability(np.float32([800]), np.float32([10]), np.float32([0.5]), np.float32([1.0]),
                          np.float32([0.0]), np.uint8([0]), tab[:1])
    assert one[0, 0] == 1.0


def test_splat_matches_reference_and_sums_to_one(cl_env, terrain):
    p = VegetationParams(snow_min_m=900.0, snow_max_m=1100.0, rock_min_m=1000.0, rock_max_m=1300.0)
    slope, _, grad, _, _, _ = ref.attributes(*attr_args(terrain))
    moist = np.random.default_rng(3).random(terrain.shape).astype(np.float32)
    water = np.zeros(terrain.shape, np.uint8)
    water[:3] = 1
    tab = splat_table(p)
    want = ref.splat(terrain, slope, grad, moist, water, tab)
    for local in (None, (32,)):
        same(cl_env, dev.splat(cl_env, terrain, slope, grad, moist, water, tab, local=local), want)
    assert want.min() >= 0.0 and want.max() <= 1.0
    assert np.abs(want.astype(np.float64).sum(-1) - 1.0).max() <= 1e-6
    assert np.all(want[:3, :, 4] == 1.0)  # water is mud
    for k in range(6):
        assert want[..., k].max() > 0.05, k  # every layer shows somewhere on this terrain


def test_splat_fixes_the_thesis_sum_over_one():
    """High snow and wet ground at once: the thesis's coefficients sum past 1
    (its mud is never limited by snow); ours still sum to 1."""
    p = VegetationParams(snow_melt=0.0)
    tab = splat_table(p)
    alt = np.full(4, 1600.0, np.float32)
    slope = np.full(4, 2.0, np.float32)
    grad = np.tan(np.radians(slope)).astype(np.float32)
    moist = np.full(4, 1.0, np.float32)
    assert ref.seed004_sum(alt, slope, grad, moist, tab).max() > 1.5
    w = ref.splat(alt, slope, grad, moist, np.zeros(4, np.uint8), tab)
    assert np.abs(w.astype(np.float64).sum(-1) - 1).max() <= 1e-6
    assert w[0, 5] > 0.9 and w[0, 4] < 0.1  # snow first, mud only under what snow leaves


def _small_sim(backend, local=None, seed=7, **over):
    p = VegetationParams(years=40, step_years=5, **over)
    names = p.plant_species()
    rng = np.random.default_rng(5)
    from scipy import ndimage

    suit = np.stack([ndimage.gaussian_filter(rng.random((29, 41)), 3) for _ in names])
    suit = np.clip((suit - 0.45) * 8, 0, 1).astype(np.float32)
    grid = eco.SimGrid(41, 29, 8.0)
    kw = {"local": local} if local else {}
    return eco.simulate(suit, grid, p, names, seed, backend, **kw)


def test_ecosystem_kernels_match_reference(cl_env):
    want = _small_sim(ref)
    for local in (None, (8, 4)):
        got = _small_sim(dev.on(cl_env), local)
        np.testing.assert_array_equal(got.sp, want.sp)
        np.testing.assert_array_equal(got.birth, want.birth)
        assert got.history == want.history
    assert want.history[-1] != want.history[0]  # something happened
    other = _small_sim(dev.on(cl_env), seed=8)
    assert not np.array_equal(other.sp, want.sp)


def test_poisson_kernel_matches_reference(cl_env):
    dom = pl.Domain(40, 52, 4.0, (0.0, 0.0))
    rng = np.random.default_rng(4)
    rad = np.where(rng.random((40, 52)) < 0.8, 4.0 + 4.0 * rng.random((40, 52)), 0.0).astype(np.float32)
    # obstacles: a few plants of a species placed before
    prev = pl.Placed("big", (rng.random(30) * dom.width).astype(np.float32), (rng.random(30) * dom.depth).astype(np.float32),
                     np.full(30, 6.0, np.float32), np.arange(30), {})
    obst = pl._obstacles([(prev, 1.5)], 0.5, dom, 4.0 / np.sqrt(2))
    want, wc, _ = pl.poisson_sample(rad, 4.0, dom, 5, 99, ref, obst)
    for local in (None, (4, 2)):
        got, gc, _ = pl.poisson_sample(rad, 4.0, dom, 5, 99, dev.on(cl_env), obst, local=local)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(gc, wc)
    assert len(want) > 50


def test_poisson_of_tiles_in_rounds_is_the_whole_worlds(cl_env):
    """Tiles of the Poisson grid, each read with POISSON_ROUND_HALO cells of
    the last round's points around it and run through one pass (all its
    phases), keep exactly the points the whole grid gets, pass after pass,
    with obstacles (each window given only those its darts reach); on the
    device and in the reference."""
    dom = pl.Domain(120, 150, 4.0, (0.0, 0.0))
    rng = np.random.default_rng(8)
    rad = np.where(rng.random((120, 150)) < 0.85, 4.0 + 4.0 * rng.random((120, 150)), 0.0).astype(np.float32)
    prev = pl.Placed("big", (rng.random(80) * dom.width).astype(np.float32),
                     (rng.random(80) * dom.depth).astype(np.float32), np.full(80, 6.0, np.float32), np.arange(80), {})
    c = 4.0 / np.sqrt(2)
    obst = pl._obstacles([(prev, 1.5)], 0.5, dom, c)
    nx, nz = int(dom.width // c) + 1, int(dom.depth // c) + 1
    P, halo, tile = ref.PN + 1, pl.POISSON_ROUND_HALO, 64
    assert nx > tile + 2 * halo  # the windows are smaller than the grid
    for backend in (ref, dev.on(cl_env)):
        whole = backend.Poisson(nx, nz, c, dom.width, dom.depth, rad, dom.dx, pl.MARGIN_M, *obst)
        state = np.zeros((nz, nx, 4), np.float32)
        for k in range(3):
            for pz in range(P):
                for px in range(P):
                    whole.phase(px, pz, k, 99)
            after = state.copy()
            for tz in range(0, nz, tile):
                for tx in range(0, nx, tile):
                    x0, z0 = max(tx - halo, 0), max(tz - halo, 0)
                    x1, z1 = min(tx + tile + halo, nx), min(tz + tile + halo, nz)
                    win, (rs, cs) = pl.point_window(x0, z0, x1 - x0, z1 - z0, c, dom)
                    near = pl._obstacles([(prev, 1.5)], 0.5, dom, c, window_m=(x0 * c, x1 * c, z0 * c, z1 * c))
                    assert near.onwx * near.onwz < obst.onwx * obst.onwz and 0 < near.start[-1] < obst.start[-1]
                    reach = ((prev.x > x0 * c - obst.oc) & (prev.x < x1 * c + obst.oc) & (prev.z > z0 * c - obst.oc)
                             & (prev.z < z1 * c + obst.oc))  # a cell around the window: what its darts test
                    assert set(prev.x[reach]) <= set(near.pts[:near.start[-1], 0])
                    part = backend.Poisson(nx, nz, c, dom.width, dom.depth, rad[rs, cs], dom.dx, pl.MARGIN_M, *near,
                                           window=win, pts=state[z0:z1, x0:x1])
                    for pz in range(P):
                        for px in range(P):
                            part.phase(px, pz, k, 99)
                    got = part.read().reshape(z1 - z0, x1 - x0, 4)
                    after[tz:tz + tile, tx:tx + tile] = got[tz - z0:tz - z0 + tile, tx - x0:tx - x0 + tile]
            state = after
            np.testing.assert_array_equal(state.reshape(-1, 4), whole.read(), err_msg=f"pass {k}")
        assert (state[..., 2] > 0).sum() > 500


def test_grass_tufts_match_reference(cl_env):
    dens = np.random.default_rng(6).random((30, 33)).astype(np.float32)
    args = (dens, 4.0, 40, 35, 3.1, 0.8, 32 * 4.0, 29 * 4.0, 1234)
    want = ref.grass_tufts(*args)
    for local in (None, (8, 5)):
        same(cl_env, dev.grass_tufts(cl_env, *args, local=local), want)
    kept = want[want[:, 3] > 0]
    assert 0.3 < len(kept) / len(want) < 0.7  # density is uniform 0..1: about half kept


def test_grass_tufts_of_tiles_are_the_whole_worlds(cl_env):
    """A window of the tufts' grid with the density field's window under it
    gets the world's tufts bit for bit."""
    dom = pl.Domain(30, 33, 4.0, (0.0, 0.0))
    dens = np.random.default_rng(6).random((30, 33)).astype(np.float32)
    nx, nz, sp = 40, 35, 3.1
    args = (4.0, nx, nz, sp, 0.8, 32 * 4.0, 29 * 4.0, 1234)
    for backend in (ref, dev.on(cl_env)):
        whole = backend.grass_tufts(dens, *args).reshape(nz, nx, 4)
        for z0, x0, wnz, wnx in ((0, 0, 12, 17), (11, 23, 24, 17), (30, 5, 5, 9)):
            win, (rs, cs) = pl.point_window(x0, z0, wnx, wnz, sp, dom)
            part = backend.grass_tufts(dens[rs, cs], *args, window=win).reshape(wnz, wnx, 4)
            np.testing.assert_array_equal(part, whole[z0:z0 + wnz, x0:x0 + wnx])
