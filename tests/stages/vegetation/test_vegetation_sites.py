"""Sites (sites.py) and the slope limits: species' limits of real plants
(none over 50 deg, refused by the params), the tree line by aspect, the
riparian index, avalanche run-out against the alpha-angle solution,
clearings, and on a steep synthetic world: no tree stands on ground
steeper than its species' limit, none in an avalanche track or a clearing,
and the forest-by-slope table in the stats, the USD and the report."""
import math
import tomllib
from pathlib import Path

import numpy as np
import pydantic
import pytest

from pipeline.grid import Grid
from stages.vegetation import VegetationParams
from stages.vegetation import placement as pl
from stages.vegetation import sites
from stages.vegetation.params import MAX_SPECIES_SLOPE_DEG
from stages.vegetation.report_tables import banks_table, forest_table, forest_tables

from .test_vegetation_stage import collect, run_stage, small_params

ROOT = Path(__file__).resolve().parents[3]


def config_params() -> VegetationParams:
    table = tomllib.loads((ROOT / "configs" / "default.toml").read_text())["vegetation"]
    return VegetationParams.model_validate(table)


@pytest.mark.parametrize("params", [VegetationParams(), config_params()], ids=["defaults", "default.toml"])
def test_species_slope_limits_of_real_plants(params):
    """No species grows above 50 deg; trees are closed forest (factor 1)
    to at most 40 deg and scattered to at most 45 deg."""
    assert MAX_SPECIES_SLOPE_DEG == 50.0
    trees = 0
    for name, e in params.species.items():
        assert e.slope_deg.max <= 50.0, name
        assert sites.preference_factor(np.array([0.0, 10.0]), e.slope_deg).min() == 1.0, name  # flat ground is fine
        if e.tree:
            trees += 1
            assert e.slope_deg.max <= 45.0 and e.slope_deg.max - e.slope_deg.edge <= 40.0, name
    assert trees >= 2
    assert params.rock_slope_min_deg <= 50.0 and params.scree_slope_min_deg <= 45.0  # the splat takes over


@pytest.mark.parametrize("name", ["conifer", "shrub", "grass"])
def test_params_refuse_a_slope_limit_over_50(name):
    with pytest.raises(pydantic.ValidationError) as e:
        VegetationParams.model_validate({"species": {name: {"slope_deg": {"min": 0.0, "max": 55.0, "edge": 5.0}}}})
    assert "50 deg" in str(e.value)
    VegetationParams.model_validate({"species": {name: {"slope_deg": {"min": 0.0, "max": 50.0, "edge": 5.0}}}})


def test_effective_altitude_by_aspect():
    """A steep sun-facing slope judges every range shift / 2 lower, a shaded
    one shift / 2 higher, flat ground not at all; south of the equator the
    sun faces north."""
    h = np.full(6, 1000.0, np.float32)
    slope = np.array([30, 30, 30, 30, 0, 10], np.float32)
    aspect = np.array([180, 0, 90, 270, 180, 180], np.float32)
    alt = sites.effective_altitude(h, slope, aspect, 150.0, 46.0)
    np.testing.assert_allclose(alt[:4], [925.0, 1075.0, 1000.0, 1000.0], atol=1e-3)
    assert alt[4] == 1000.0 and 925.0 < alt[5] < 1000.0
    south = sites.effective_altitude(h, slope, aspect, 150.0, -30.0)
    np.testing.assert_allclose(south[:2], [1075.0, 925.0], atol=1e-3)


def test_tree_line_higher_on_sunny_slopes(tmp_path):
    """A cone of 31 deg: the conifer's highest instance on its south side
    stands higher than on its north side, by about the shift."""
    n, dx = 200, 8.0
    z, x = np.meshgrid((np.arange(n) - n / 2 + 0.5) * dx, (np.arange(n) - n / 2 + 0.5) * dx, indexing="ij")
    h = (1600.0 - 0.6 * np.hypot(x, z)).astype(np.float32)
    conifer = {"altitude_m": {"min": 0.0, "max": 1300.0, "edge": 40.0}, "clustering": 0.0}
    p = small_params(grow=["conifer"], species={"conifer": conifer}, clearing_share=0.0, avalanche_release_share=0.0,
                     treeline_aspect_shift_m=150.0)
    out, _ = run_stage(tmp_path, p, inputs={"terrain": Grid(h, dx, ("height",), (0.0, 0.0))})
    pos, _ = collect(out["vegetation.instances"])["conifer"]
    c = n / 2 * dx
    near_axis = np.abs(pos[:, 0] - c) < 150
    north = pos[near_axis & (pos[:, 2] < c - 200)]  # rows (z) grow southwards: the north side faces north
    south = pos[near_axis & (pos[:, 2] > c + 200)]
    shift = south[:, 1].max() - north[:, 1].max()
    assert 110.0 < shift < 170.0, shift


def test_riparian_index():
    """A flat floor at 0 m with a river down its middle, walls rising at
    45 deg from 40 m out: 1 on the water and the low banks, 0 past the
    distance or the height."""
    n, dx = 64, 2.0
    x = (np.arange(n) - n // 2) * dx
    h = np.tile(np.maximum(np.abs(x) - 40.0, 0.0), (8, 1)).astype(np.float32)
    water = np.zeros(h.shape, bool)
    water[:, n // 2] = True
    level = h.astype(np.float64)
    half = np.where(water, 1.0, 0.0)
    r = sites.riparian_index(h, water, level, half, dx, 3.0, 30.0)
    row = r[0]
    assert row[n // 2] == 1.0
    d = np.abs(x) - 1.0  # from the river's edge
    np.testing.assert_allclose(row[(d > 0) & (d <= 30)], (1 - sites.smooth01(d / 30.0))[(d > 0) & (d <= 30)], atol=1e-6)
    assert (row[np.abs(x) >= 31.0] == 0).all()
    r2 = sites.riparian_index(h, water, level, half, dx, 3.0, 200.0)[0]
    assert (r2[np.abs(x) >= 43.0] == 0).all() and r2[np.abs(x) == 30.0].min() > 0.5  # the walls rise out of it
    assert not sites.riparian_index(h, np.zeros_like(water), level, half, dx, 3.0, 30.0).any()


@pytest.mark.parametrize("seed", range(6))
def test_riparian_index_of_tiles_is_the_whole_worlds(seed):
    """A tile read with riparian_halo gets the whole world's index bit for
    bit, also where several water cells are equally near (straight rivers
    on the grid's axes, scattered ponds)."""
    from pipeline.tiles import tiles_of

    rng = np.random.default_rng(seed)
    rows, cols, dx = 90, 110, 2.0
    water = rng.random((rows, cols)) < (0.002, 0.01, 0.05)[seed % 3]
    if seed % 2:
        water[:, 40] = water[60, :] = True
    h, level = rng.random((rows, cols)) * 20, rng.random((rows, cols)) * 20
    half = np.where(water, rng.random((rows, cols)) * 6, 0.0)
    params = VegetationParams(riparian_height_m=5.0, riparian_distance_m=20.0)
    whole = sites.riparian_index(h, water, level, half, dx, 5.0, 20.0)
    halo = sites.riparian_halo(dx, params, float(half.max()))
    for tile in tiles_of((rows, cols), 32):
        r0, c0, n_rows, n_cols = tile.window(halo)
        part = np.s_[r0:r0 + n_rows, c0:c0 + n_cols]
        got = sites.riparian_index(h[part], water[part], level[part], half[part], dx, 5.0, 20.0)[tile.inner(halo)]
        np.testing.assert_array_equal(got, whole[tile.row0:tile.row0 + tile.rows, tile.col0:tile.col0 + tile.cols])


def tiled_run_out(h, release, dx, alpha, tile_cells):
    """run_out as a tiled bake spreads it: each tile (and a one-cell halo)
    spreads its own lines, the lines crossing into a neighbour are handed
    on in rounds until none crosses."""
    from pipeline.tiles import tiles_of

    tiles = tiles_of(h.shape, tile_cells)
    runs, inbox = {}, {(t.row, t.col): [] for t in tiles}
    for t in tiles:
        r0, c0, rows, cols = t.window(1)
        part = h[r0:r0 + rows, c0:c0 + cols]
        own = np.zeros(part.shape, bool)
        own[t.inner(1)] = True
        run = sites.RunOut(part, sites.d8_receivers(part, dx), dx, alpha, own)
        seeds = np.flatnonzero((release[r0:r0 + rows, c0:c0 + cols] & own).ravel())
        runs[t.row, t.col] = (t, run)
        inbox[t.row, t.col].append((seeds, np.full(seeds.size, sites.NO_HEADING), run.hf[seeds], True))
    rounds = 0
    while any(inbox.values()):
        rounds += 1
        sent, inbox = inbox, {key: [] for key in inbox}
        for key, messages in sent.items():
            t, run = runs[key]
            r0, c0, _, cols = t.window(1)
            for cells, headings, values, are_slots in messages:
                slots = headings if are_slots else run.slot(cells, headings)
                cells_out, headings_out, values_out = run.spread(run.seed(cells, slots, values))
                wr, wc = r0 + cells_out // cols, c0 + cells_out % cols
                for owner in set(zip((wr // tile_cells).tolist(), (wc // tile_cells).tolist())):
                    mine = (wr // tile_cells == owner[0]) & (wc // tile_cells == owner[1])
                    o, o_run = runs[owner]
                    orow0, ocol0, _, ocols = o.window(1)
                    local = (wr[mine] - orow0) * ocols + (wc[mine] - ocol0)
                    inbox[owner].append((local, headings_out[mine], values_out[mine], False))
    path = np.zeros(h.shape, bool)
    for t, run in runs.values():
        path[t.row0:t.row0 + t.rows, t.col0:t.col0 + t.cols] = run.path()[t.inner(1)]
    return path, rounds


@pytest.mark.parametrize("seed", range(4))
def test_run_out_of_tiles_is_the_whole_worlds(seed):
    """Avalanches spread tile by tile, handing their lines to the
    neighbours in rounds, reach the cells the whole world's reach: on rough
    slopes, terraces of flats (where lines keep their heading) and pits."""
    rng = np.random.default_rng(seed)
    rows, cols, dx = 70, 83, 4.0
    r, c = np.mgrid[0:rows, 0:cols]
    h = 900.0 - 3.0 * r - 1.2 * c + 6.0 * rng.random((rows, cols))
    if seed % 2:
        h = np.floor(h / 12.0) * 12.0  # terraces: wide flats
    release = (rng.random((rows, cols)) < 0.02) & (r < rows // 2)
    whole = sites.run_out(h, release, dx, 20.0)
    assert whole.sum() > 4 * release.sum()  # the lines run far
    for tile_cells in (16, 29):
        tiled, rounds = tiled_run_out(h, release, dx, 20.0, tile_cells)
        assert rounds > 1
        np.testing.assert_array_equal(tiled, whole)


def test_noise_of_a_window_is_the_whole_worlds():
    """The clearings, the avalanche release patches and the clumping noise
    of a window of the world, given its first cell, have the world's bits
    (cell sizes and origins whose products round)."""
    params = VegetationParams(clearing_share=0.3, clearing_size_m=37.0)
    for dx, origin in ((5.41, (-2771.3, 113.7)), (1.0, (0.0, 0.0))):
        whole = sites.clearings((70, 90), params, dx, origin, 11)
        clump = pl.value_noise((70, 90), dx, origin, 23.0, 5)
        first, shape = (33, 47), (20, 31)
        cells = np.s_[33:53, 47:78]
        np.testing.assert_array_equal(sites.clearings(shape, params, dx, origin, 11, first), whole[cells])
        np.testing.assert_array_equal(pl.value_noise(shape, dx, origin, 23.0, 5, first), clump[cells])


def test_avalanche_run_out_against_the_alpha_line():
    """A 35 deg slope onto a flat floor: an avalanche released at the top
    runs down the slope and out over the floor until its alpha line (from
    the release height, falling tan(alpha) per metre) meets the floor."""
    n, dx = 200, 5.0
    x = np.arange(n) * dx
    top = 60 * dx
    h1 = np.where(x < top, (top - x) * math.tan(math.radians(35.0)), 0.0)
    h = np.tile(h1, (5, 1)).astype(np.float32)
    release = np.zeros(h.shape, bool)
    release[2, 0] = True
    for alpha in (20.0, 26.0, 30.0):
        path = sites.run_out(h, release, dx, alpha)
        reach = np.flatnonzero(path[2]).max() * dx
        expect = float(h1[0]) / math.tan(math.radians(alpha))  # the line meets the floor (h = 0) here
        assert abs(reach - expect) <= dx, (alpha, reach, expect)
        assert path.sum() == path[2].sum()  # one flow line (D8 straight down the slope)
    assert not sites.run_out(h, np.zeros_like(release), dx, 26.0).any()


def test_run_out_keeps_the_highest_line():
    """Two releases on one flow line: the path is that of the higher one,
    whatever the other does."""
    n, dx = 120, 5.0
    h1 = np.maximum(400.0 - np.arange(n) * dx * 0.6, 0.0)
    h = np.tile(h1, (3, 1)).astype(np.float32)
    hi, lo = np.zeros(h.shape, bool), np.zeros(h.shape, bool)
    hi[1, 0] = True
    lo[1, 30] = True
    np.testing.assert_array_equal(sites.run_out(h, hi | lo, dx, 26.0), sites.run_out(h, hi, dx, 26.0))


def test_clearings_share_and_determinism():
    p = VegetationParams(clearing_share=0.1, clearing_size_m=200.0)
    wide = sites.clearings((512, 512), p, 16.0, (0.0, 0.0), 7)  # 40 wavelengths a side: the share is measured
    assert 0.08 < float((wide >= 0.5).mean()) < 0.12
    c = sites.clearings((256, 256), p, 8.0, (0.0, 0.0), 7)
    np.testing.assert_array_equal(c, sites.clearings((256, 256), p, 8.0, (0.0, 0.0), 7))
    assert not np.array_equal(c, sites.clearings((256, 256), p, 8.0, (0.0, 0.0), 8))
    # local: a window of a larger world is the same
    big = sites.clearings((300, 300), p, 8.0, (0.0, 0.0), 7)
    np.testing.assert_array_equal(big[:256, :256], c)
    assert not sites.clearings((64, 64), VegetationParams(clearing_share=0.0), 8.0, (0.0, 0.0), 7).any()


def steep_world():
    """Slopes from flat to about 70 deg: a ramp whose gradient grows across
    the map, with a bump of noise, from 300 to about 1600 m."""
    from scipy import ndimage

    n, dx = 128, 8.0
    z, x = np.meshgrid(np.arange(n) * dx, np.arange(n) * dx, indexing="ij")
    grad = np.tan(np.radians(np.clip(x / (n * dx) * 75.0, 0.0, 70.0)))
    h = 300.0 + ndimage.uniform_filter1d(np.cumsum(grad * dx, axis=1), 5, axis=1) * (0.6 + 0.4 * np.cos(z / 300.0))
    rng = np.random.default_rng(3)
    h += 3.0 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 2.0)
    return Grid(h.astype(np.float32), dx, ("height",), (0.0, 0.0))


@pytest.fixture(scope="module")
def steep(tmp_path_factory):
    params = small_params(grow=["conifer", "broadleaf", "shrub", "grass"], clearing_share=0.08,
                          clearing_size_m=150.0, avalanche_release_min_m=450.0, avalanche_release_share=0.3,
                          avalanche_release_patch_m=200.0,
                          species={"conifer": {"altitude_m": {"min": 0.0, "max": 2500.0, "edge": 100.0}},
                                   "broadleaf": {"altitude_m": {"min": 0.0, "max": 2500.0, "edge": 100.0}}})
    out, _ = run_stage(tmp_path_factory.mktemp("steep"), params, inputs={"terrain": steep_world()})
    return out, params


def test_no_plant_on_ground_steeper_than_its_limit(steep):
    out, params = steep
    terrain = steep_world()
    slope = out["vegetation.attributes"].channel("attr.slope")
    assert (slope > 55).mean() > 0.1 and (slope < 20).mean() > 0.1  # the world spans the limits
    dom = pl.Domain(*slope.shape, terrain.cell_size_m, terrain.origin_m)
    found = collect(out["vegetation.instances"])
    steepest = out["vegetation.stats"]["steepest_instance_slope_deg"]
    for name in params.plant_species():
        pos, _ = found[name]
        tr, tc = dom.world_cell(pos)
        assert slope[tr, tc].max() < params.species[name].slope_deg.max, name
        assert steepest[name] == pytest.approx(float(slope[tr, tc].max()), abs=1e-3)
    assert max(steepest["conifer"], steepest["broadleaf"]) > 35.0  # scattered trees do reach the steep ground


def test_no_tree_in_avalanche_tracks_or_clearings(steep):
    out, params = steep
    terrain = steep_world()
    s = out["vegetation.sites"]
    ava, clr = s.channel("site.avalanche"), s.channel("site.clearing")
    assert (ava >= 0.99).mean() > 0.01 and (clr >= 0.99).mean() > 0.02
    dom = pl.Domain(*ava.shape, terrain.cell_size_m, terrain.origin_m)
    found = collect(out["vegetation.instances"])
    for name in ("conifer", "broadleaf"):
        tr, tc = dom.world_cell(found[name][0])
        assert (ava[tr, tc] < 1.0).all() and (clr[tr, tc] < 1.0).all(), name
    tr, tc = dom.world_cell(found["shrub"][0])
    assert ((ava[tr, tc] >= 0.99) | (clr[tr, tc] >= 0.99)).any()  # shrubs grow there


def test_forest_by_slope_table(steep, tmp_path):
    from pipeline import usdio

    out, params = steep
    f = out["vegetation.stats"]["forest_by_slope"]
    assert f["classes_deg"] == ["0-10", "10-20", "20-30", "30-40", "40-50", ">50"]
    assert sum(f["land_share"]) == pytest.approx(1.0, abs=1e-3) and sum(f["tree_share"]) == pytest.approx(1.0, abs=1e-3)
    assert f["tree_share"][-1] == 0.0 and f["trees_per_ha"][-1] == 0.0 and f["land_share"][-1] > 0.1
    assert f["trees_per_ha"][2] > 5 * max(f["trees_per_ha"][4], 1e-3)  # closed below 30 deg, scattered at 40-50
    stats_trees = sum(out["vegetation.stats"]["instances"][n] for n in ("conifer", "broadleaf"))
    assert f["trees"] == stats_trees
    # the report's table, from the composed world's /World/Vegetation customData
    world, _ = usdio.create_stage(tmp_path / "world.usda", {})
    world.GetRootLayer().subLayerPaths.append(usdio.relative_asset_path(out["vegetation.instances"],
                                                                         tmp_path / "world.usda"))
    world.GetRootLayer().Save()
    table, banks = forest_tables(tmp_path / "world.usda")
    assert table == forest_table(f) and banks == banks_table(out["vegetation.stats"]["plants_on_banks"])
    assert [r[0] for r in table.rows] == f["classes_deg"] and table.rows[-1][2] == 0.0
    assert [r[0] for r in banks.rows] == sorted(params.plant_species())


def test_banks_have_their_own_mix(tmp_path):
    """A flat valley floor 240 m wide with a river down its middle between
    25 deg walls: spruce keeps off the banks (the broadleaf and shrub
    species take them), so the banks' mix differs from the slopes'."""
    n, dx = 128, 8.0
    x = (np.arange(n) - n // 2 + 0.5) * dx
    h1 = 500.0 + np.maximum(np.abs(x) - 120.0, 0.0) * math.tan(math.radians(25.0))
    h = np.tile(h1, (n, 1)).astype(np.float32)
    river = np.zeros((n, n), np.float32)
    river[:, n // 2] = 1.0
    origin = (0.0, 0.0)
    inputs = {"terrain": Grid(h, dx, ("height",), origin),
              "moisture": Grid(np.full((n, n), 0.6, np.float32), dx, ("moisture",), origin),
              "rivers": Grid(np.stack([river, river * 6.0, river], -1), dx, ("river.mask", "river.width", "river.order"),
                             origin)}
    wide = {"altitude_m": {"min": 0.0, "max": 3000.0, "edge": 50.0}}
    p = small_params(grow=["conifer", "broadleaf", "shrub"], species={"conifer": wide, "broadleaf": wide},
                     clearing_share=0.0, avalanche_release_share=0.0, riparian_height_m=3.0,
                     riparian_distance_m=80.0)
    out, _ = run_stage(tmp_path, p, inputs=inputs)
    b = out["vegetation.stats"]["plants_on_banks"]
    per = {name: (on, off) for name, on, off in zip(b["species"], b["banks_per_ha"], b["elsewhere_per_ha"])}
    assert b["bank_ha"] > 5.0
    assert per["conifer"][0] < 0.2 * per["conifer"][1], per
    assert per["broadleaf"][0] > 1.5 * per["broadleaf"][1] and per["broadleaf"][0] > per["conifer"][0], per
    rip = out["vegetation.sites"].channel("site.riparian")
    assert rip[:, n // 2].min() == 1.0 and rip[:, 0].max() == 0.0


@pytest.mark.parametrize("over", [
    dict(avalanche_release_share=1.0, avalanche_alpha_deg=5.5, avalanche_track_width_m=0.0, avalanche_release_min_m=-100.0,
         avalanche_release_slope_min_deg=0.0, avalanche_release_slope_max_deg=90.0),
    dict(avalanche_release_share=1.0, avalanche_alpha_deg=60.0, avalanche_track_width_m=5000.0),
    dict(clearing_share=0.9, clearing_size_m=1.0, riparian_height_m=1e-3, riparian_distance_m=1e5,
         treeline_aspect_shift_m=2000.0),
    dict(clearing_share=0.0, avalanche_release_share=0.0, clearing_size_m=1e5, avalanche_release_patch_m=1e5),
])
def test_sites_under_extreme_params(over):
    """Every site field finite and in [0, 1] (the altitude within half the
    shift), whatever the knobs; the whole-map and the no-release ends."""
    from .conftest import synthetic_height
    from stages.vegetation import attributes, reference

    n, dx = 64, 8.0
    h = synthetic_height(n, n, dx, seed=4)
    p = VegetationParams.model_validate({**VegetationParams().model_dump(), **over})
    a = attributes.compute(h, dx, p, reference)
    water = np.zeros((n, n), bool)
    water[:, 10] = True
    s = sites.compute(h, a, water, water, h.astype(np.float64), np.zeros((n, n)), p, dx, (0.0, 0.0), 3)
    for f in (s.riparian, s.avalanche, s.clearing):
        assert np.isfinite(f).all() and f.min() >= 0.0 and f.max() <= 1.0
    assert np.abs(s.altitude - h).max() <= 0.5 * p.treeline_aspect_shift_m + 1e-2
    if over.get("avalanche_release_min_m") == -100.0:
        assert s.stats["avalanche"]["path_share"] > 0.5  # nearly everything releases and runs far
    if over.get("avalanche_release_share") == 0.0:
        assert not s.avalanche.any() and not s.clearing.any()
