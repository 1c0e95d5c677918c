"""The vegetation on a tiled world (stages/vegetation/tiled.py,
tiled_run.py): a tiled bake writes the untiled bake's files byte for byte,
in this process and on Dask; and pass by pass, on a small world with lakes,
a river, no-data cells and avalanches crossing tile edges, every field,
placement and instance equals the whole run's."""
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.grid import Grid
from pipeline.opencl import get_cl
from pipeline.tiles import GridArray, TileRunner
from stages.vegetation import stage as vs
from stages.vegetation import tiled

from ..tiled_bakes import artifact_files, bake_keys
from .test_vegetation_stage import small_params, world_inputs

REPO = Path(__file__).resolve().parents[3]
# the vegetation on hydrology's moisture, without erosion; 8 m cells (the simulation's own)
SETS = ('outputs=["vegetation"]', "hydrology.depression=fill", "erosion.enabled=false")


@pytest.mark.parametrize("resolution, executor", [(512, "local"), (640, "dask")])
def test_tiled_vegetation_writes_the_untiled_files(tmp_path, resolution, executor):
    """2 x 2 tiles, and 3 x 3 with part tiles on Dask: maps, instances
    (layer and tiles), species, stats and preview, byte for byte."""
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    sets = (*SETS, f"heightmap.resolution={resolution}", f"heightmap.size_m={resolution * 8}")
    whole = bake_keys(tmp_path, "b_whole", *sets)
    tiled_keys = bake_keys(tmp_path, "b_tiled", *sets, "tiling.tile_cells=256", executor=executor)
    assert whole == tiled_keys
    key = whole["vegetation"]
    made = artifact_files(tmp_path / "b_whole", "vegetation", key)
    assert {"instances.usdc", "stats.json", "preview.png", "species.exr", "splat.exr"} <= set(made)
    assert made == artifact_files(tmp_path / "b_tiled", "vegetation", key)
    manifest = json.loads((tmp_path / "b_tiled" / "artifacts" / "vegetation" / key / "manifest.json").read_text())
    assert manifest["metrics"]["tiled_steps"].startswith("every step")


def whole_land(dx: float, params, seed: int):
    """The test world at dx cells, and the whole run's land on it: (inputs,
    backend, run context, stage._Land)."""
    inputs = {k: Grid(np.asarray(g.data), dx, g.channels, g.origin_m) for k, g in world_inputs().items()}
    be = vs.backend_modules(get_cl())
    ctx = SimpleNamespace(seed=seed, input_artifacts={"moisture": "hydrology.moisture"}, progress=lambda *a: None)
    return inputs, be, ctx, vs._land(ctx, inputs, vs._terrain(inputs["terrain"]), params, be, vs.PhaseClock())


def tiled_growth(tmp_path, inputs: dict, params, seed: int, be, tile_cells: int):
    """Passes 1 to 7 of a tiled run on the test world: (runner, inputs read
    by window, the fields' output, the growth's output)."""
    grid = inputs["terrain"]
    shape, dx = grid.data.shape[:2], grid.cell_size_m
    runner = TileRunner(tile_cells, stage=vs.STAGE, run_key="test", seed=seed, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    windows = {k: GridArray(g) for k, g in inputs.items()}
    plants, gname = params.plant_species(), params.grass_species()
    out = tiled.fields(runner, windows, params, shape, dx, grid.origin_m, seed, plants + [gname])
    return runner, windows, out, tiled.growth(runner, out, windows, params, shape, dx, grid.origin_m, seed, be)


@pytest.fixture(scope="module")
def world():
    inputs = world_inputs()
    h = np.array(inputs["terrain"].channel("height"))
    h[3:6, 100:104] = np.nan  # no-data cells
    inputs["terrain"] = Grid(h, inputs["terrain"].cell_size_m, ("height",), inputs["terrain"].origin_m)
    # avalanches from the upper slopes, long enough to cross tiles; a short horizon keeps the halo small
    params = small_params(horizon_distance_m=120.0, avalanche_release_min_m=900.0, avalanche_release_share=0.5,
                          avalanche_release_patch_m=60.0, avalanche_alpha_deg=18.0, clearing_share=0.2)
    return inputs, params


@pytest.mark.parametrize("tile_cells", [32, 45])
def test_tiled_fields_are_the_whole_runs(world, tmp_path, tile_cells):
    inputs, params = world
    cl = get_cl()
    be = vs.backend_modules(cl)
    seed = 20261123
    grid = inputs["terrain"]
    ctx = SimpleNamespace(seed=seed, input_artifacts={"moisture": "hydrology.moisture"}, progress=lambda *a: None)
    land = vs._land(ctx, inputs, vs._terrain(grid), params, be, vs.PhaseClock())
    splat = vs._splat(land, params, seed, be)
    grow = params.plant_species() + [params.grass_species()]
    suit = vs._suitability(land, params, grow, be)
    assert land.sites.avalanche.max() == 1.0 and land.sites.clearing.max() > 0.5  # the sites are there

    runner = TileRunner(tile_cells, stage=vs.STAGE, run_key="test", seed=seed, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    out = tiled.fields(runner, {k: GridArray(g) for k, g in inputs.items()}, params, grid.data.shape[:2],
                       grid.cell_size_m, grid.origin_m, seed, grow)
    assert out["avalanche_rounds"] >= 1  # lines crossed tile edges
    shape = grid.data.shape[:2]
    f = out["fields"].read(0, 0, *shape)
    a = land.attributes
    for k, name in enumerate(tiled.FIELDS):
        want = {"moisture": land.moisture, "altitude.effective": land.sites.altitude,
                "site.riparian": land.sites.riparian, "site.clearing": land.sites.clearing,
                "water": land.water.astype(np.float32), "nodata": land.nodata.astype(np.float32)}.get(name)
        np.testing.assert_array_equal(f[..., k], a[name] if want is None else want, err_msg=name)
    np.testing.assert_array_equal(out["sites"].read(0, 0, *shape), land.sites.channels()[0])
    np.testing.assert_array_equal(out["moisture_filtered"].read(0, 0, *shape)[..., 0] if
                                  out["moisture_filtered"].read(0, 0, *shape).ndim == 3 else
                                  out["moisture_filtered"].read(0, 0, *shape), splat.moisture_filtered)
    np.testing.assert_array_equal(out["splat"].read(0, 0, *shape), splat.weights)
    np.testing.assert_array_equal(np.moveaxis(out["suitability"].read(0, 0, *shape), -1, 0), suit)


@pytest.mark.parametrize("dx, tile_cells", [(8.0, 32), (2.0, 40)])
def test_tiled_growth_maps_are_the_whole_runs(tmp_path, dx, tile_cells):
    """The simulation fed by the tiles (its grid the cells themselves at 8 m,
    4 x 4 blocks at 2 m), the relative yield, targets, canopy and grass maps
    read back per tile, and the exact sums: the whole run's bits."""
    from stages.vegetation import ecosystem, grass, placement

    params = small_params(horizon_distance_m=60.0, clearing_share=0.2)
    seed = 7
    inputs, be, ctx, land = whole_land(dx, params, seed)
    grid = inputs["terrain"]
    shape = grid.data.shape[:2]
    splat = vs._splat(land, params, seed, be)
    plants, gname = params.plant_species(), params.grass_species()
    suit = vs._suitability(land, params, plants + [gname], be)
    sim, share = vs._compete(ctx, land, suit[:len(plants)], params, plants, seed, be)
    n_t, cap_info = placement.target_density(params, plants, suit[:len(plants)], share, dx, grid.origin_m, seed)
    cover = grass.canopy_cover(params, plants, n_t)
    gdens, gheight = grass.grass_maps(params, gname, suit[len(plants)], splat.weights, cover,
                                      splat.moisture_filtered, dx, grid.origin_m, seed)

    runner = TileRunner(tile_cells, stage=vs.STAGE, run_key="test", seed=seed, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    windows = {k: GridArray(g) for k, g in inputs.items()}
    out = tiled.fields(runner, windows, params, shape, dx, grid.origin_m, seed, plants + [gname])
    got = tiled.growth(runner, out, windows, params, shape, dx, grid.origin_m, seed, be)
    assert tiled.sim_factor(shape, dx, params, tile_cells) == (1 if dx == 8.0 else 4)
    np.testing.assert_array_equal(got["sim"].sp, sim.sp)
    np.testing.assert_array_equal(np.moveaxis(got["share"].read(0, 0, *shape), -1, 0), share)
    np.testing.assert_array_equal(np.moveaxis(got["target"].read(0, 0, *shape), -1, 0), n_t)
    np.testing.assert_array_equal(got["grass"].read(0, 0, *shape), np.stack([gdens, gheight], -1))
    np.testing.assert_array_equal(got["canopy"].read(0, 0, *shape)[..., 0], cover)
    for s, name in enumerate(plants):
        assert got["target_max"][name] == float(n_t[s].max())
        assert got["capped_plants"][name] == cap_info[name]["capped_plants"]
    assert grass.tuft_spacing_of(params, gname, got["grass_density_exact"], dx) == \
        grass.tuft_spacing(params, gname, gdens, dx)
    assert ecosystem.block_factor(*shape, dx, got["sim_grid"]) == (0 if dx == 8.0 else 4)


@pytest.mark.parametrize("dx, tile_cells", [(8.0, 32), (4.0, 48)])
def test_tiled_placement_is_the_whole_runs(tmp_path, dx, tile_cells):
    """Every plant species placed tile by tile (Poisson passes in rounds,
    block selection per tile) is the whole run's placement bit for bit:
    positions, radii, Poisson cells and counts."""
    from stages.vegetation import placement

    base = world_inputs()
    inputs = {k: Grid(np.asarray(g.data), dx, g.channels, g.origin_m) for k, g in base.items()}
    params = small_params(horizon_distance_m=60.0, density_block_m=8 * dx, poisson_passes=3)
    cl = get_cl()
    be = vs.backend_modules(cl)
    seed = 11
    grid = inputs["terrain"]
    shape = grid.data.shape[:2]
    runner, _, _, grown = tiled_growth(tmp_path, inputs, params, seed, be, tile_cells)
    plants = params.plant_species()
    got = tiled.place(runner, grown, params, shape, dx, grid.origin_m, seed)
    n_t = np.moveaxis(grown["target"].read(0, 0, *shape), -1, 0)
    want = placement.place_species(params, plants, n_t, placement.Domain(*shape, dx, grid.origin_m), seed, be)
    placed = 0
    for name in plants:
        for field in ("x", "z", "r", "cell"):
            np.testing.assert_array_equal(getattr(got[name], field), getattr(want[name], field), err_msg=name)
        for key in ("target_plants", "candidates", "placed", "shortfall_plants", "blocks_short", "poisson_cells",
                    "obstacles"):
            assert got[name].stats.get(key) == want[name].stats.get(key), (name, key)
        placed += len(got[name].x)
    assert placed > 100


def test_tiled_tufts_are_the_whole_runs(tmp_path):
    """The grass tufts gathered from the tiles' shares of the tufts' grid are
    grass.place_tufts' on the whole density, in the same order."""
    from stages.vegetation import grass, placement

    base = world_inputs()
    inputs = {k: Grid(np.asarray(g.data), 4.0, g.channels, g.origin_m) for k, g in base.items()}
    params = small_params(horizon_distance_m=60.0)
    be = vs.backend_modules(get_cl())
    grid = inputs["terrain"]
    shape = grid.data.shape[:2]
    runner = TileRunner(48, stage=vs.STAGE, run_key="test", seed=5, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    windows = {k: GridArray(g) for k, g in inputs.items()}
    plants, gname = params.plant_species(), params.grass_species()
    out = tiled.fields(runner, windows, params, shape, 4.0, grid.origin_m, 5, plants + [gname])
    grown = tiled.growth(runner, out, windows, params, shape, 4.0, grid.origin_m, 5, be)
    got, stats = tiled.tufts(runner, grown, params, shape, 4.0, grid.origin_m, 5)
    density = grown["grass"].read(0, 0, *shape)[..., 0]
    want, want_stats = grass.place_tufts(params, gname, density, placement.Domain(*shape, 4.0, grid.origin_m), 5, be)
    assert stats == want_stats and len(want.x) > 200
    for field in ("x", "z", "r", "cell"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)


def test_tiled_instances_are_the_whole_runs(tmp_path):
    """Every species' instances made tile by tile (the terrain mesh's
    lattice read by tile, drops on cells where it may not grow and in the
    river's ribbon, tints): the whole run's bit for bit."""
    dx, seed = 4.0, 3
    params = small_params(horizon_distance_m=60.0, density_block_m=8 * dx, poisson_passes=3, mesh_max_vertices=50)
    inputs, be, ctx, land = whole_land(dx, params, seed)
    grid = inputs["terrain"]
    shape = grid.data.shape[:2]
    splat = vs._splat(land, params, seed, be)
    growth = vs._grow(ctx, land, params, seed, be, vs.PhaseClock())
    grass_layer = vs._grass(land, growth, splat, params, seed, be)
    want_sets, want_dropped, want_tints = vs._instances(land, growth, grass_layer, params, seed)

    runner, windows, out, grown = tiled_growth(tmp_path, inputs, params, seed, be, 32)
    gname = params.grass_species()
    placed = tiled.place(runner, grown, params, shape, dx, grid.origin_m, seed)
    tufts, _ = tiled.tufts(runner, grown, params, shape, dx, grid.origin_m, seed)
    half = 0.5 * float(np.nanmax(inputs["rivers"].channel("river.width")))
    sets, dropped, tints = tiled.instances(runner, windows, out, grown, placed, tufts, params, shape, dx,
                                           grid.origin_m, seed, float(np.nanmin(grid.channel("height"))), half)
    assert sorted(sets) == sorted(want_sets) and dropped == want_dropped
    assert sum(dropped["in_rivers"].values()) > 0  # the river's ribbon took some
    for name, inst in sets.items():
        want = want_sets[name]
        for field in ("positions", "orientations", "scales", "age", "random", "ids", "radius"):
            np.testing.assert_array_equal(getattr(inst, field), getattr(want, field), err_msg=f"{name} {field}")
        np.testing.assert_array_equal(tints[name], want_tints[name])
    assert gname in sets and len(sets[gname]) > 100


def test_a_tiled_world_is_checked_for_a_tile_not_a_species_poisson_grid():
    """The open world's check: a tiled run holds a tile's maps and the larger
    of the horizon's heights and a tile's Poisson window (the rounds stay in
    the tiles' files), not a species' whole Poisson grid (16 B a cell)."""
    from pipeline.contract import CheckContext, GridInfo
    from stages.vegetation.params import VegetationParams

    inputs = {"terrain": GridInfo((8192, 8192), 1.0, "heightmap.resolution")}
    ctx = lambda tile: CheckContext(seed=0, project_root=Path("."), inputs=inputs, tile_cells=tile)
    p = VegetationParams()
    whole_grid = max(vs.species_poisson_cells(p, 8191.0, 8191.0).values())  # 2.8 M cells: 45 MB at 16 B
    tiled = vs.check(p, ctx(1024))
    assert "Poisson window" in tiled.memory_how and "Poisson grid" not in tiled.memory_how
    untiled_maps = vs.check(p, ctx(0)).memory_bytes
    assert tiled.memory_bytes < 0.1 * untiled_maps
    window = int(tiled.memory_how.split("Poisson window (")[1].split(" cells")[0].replace(",", ""))
    assert window < 0.05 * whole_grid  # a tile's share with its 48-cell rim
