"""The stage on a tiled world (tiled_run.py, tiled.py, tiled_lakes.py): its
steps per tile or on the few cells they concern give the untiled bake's
files byte for byte, in this process and on Dask."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ..tiled_bakes import artifact_files, bake_keys

REPO = Path(__file__).resolve().parents[3]
FILL = ("outputs=[\"hydrology\"]", "hydrology.depression=fill", "erosion.enabled=false")


@pytest.fixture
def project(tmp_path):
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    return tmp_path


@pytest.mark.parametrize("resolution, executor, depression", [(512, "local", "fill"), (640, "dask", "breach")])
def test_tiled_hydrology_writes_the_untiled_files(project, resolution, executor, depression):
    """2 x 2 tiles, and 3 x 3 with part tiles on Dask: filled, routing,
    directions, accumulation and everything made from them."""
    sets = (*FILL, f"heightmap.resolution={resolution}", f"hydrology.depression={depression}")
    whole = bake_keys(project, "b_whole", *sets)
    tiled = bake_keys(project, "b_tiled", *sets, "tiling.tile_cells=256", executor=executor)
    assert whole == tiled, (whole, tiled)
    assert artifact_files(project / "b_whole", "hydrology", whole["hydrology"]) == \
        artifact_files(project / "b_tiled", "hydrology", tiled["hydrology"])
    manifest = json.loads((project / "b_tiled" / "artifacts" / "hydrology" / tiled["hydrology"] /
                           "manifest.json").read_text())
    assert manifest["metrics"]["tiled_steps"].startswith("every step")
    assert {p["pass"] for p in manifest["metrics"]["tiling"]["passes"]} >= {
        "fill", "filled", "directions", "accumulation", "counts", "discharge", "lake_cells", "lake_exits", "network",
        "ground", "wetness", "maps", "paths", "paths_finish", "hack", "bed_fit",
        *(("drainage", "breach", "breached") if depression == "breach" else ())}


@pytest.mark.parametrize("depression, lowest_m", [("fill", 0.0), ("breach", 0.0), ("breach", 5.0)])
def test_the_tiled_flow_steps_equal_the_untiled_on_a_world_with_holes(tmp_path, depression, lowest_m):
    """NaN and +-inf no-data across tile borders, part tiles: filled,
    routing (filled, or breached), directions and accumulation bitwise the
    untiled steps'. Breached: with land down to 0 m the carves' float steps
    are finer than the epsilon fill's, which runs its rounds after them;
    above 1 m they are its own, and it is skipped."""
    from pipeline import exr
    from pipeline.grid import Grid
    from pipeline.opencl import get_cl
    from pipeline.tiles import GridFile, TileRunner
    from pipeline.timing import StepTimes
    from stages.hydrology import STAGE, HydrologyParams
    from stages.hydrology import tiled
    from stages.hydrology.routing import condition, flow_directions, land_of
    from tests.worldlib.flow.worlds import fractal

    h = fractal(300, seed=5)[:, :280] + np.float32(lowest_m)
    h[100:140, 250:262] = np.nan
    h[40:44, :60] = np.inf
    h[200, 10:30] = -np.inf
    exr.write_grid(tmp_path / "h.exr", Grid(h.astype(np.float32), 8.0))
    env = get_cl()
    land = land_of(exr.read_grid(tmp_path / "h.exr"))
    surfaces = condition(env, land, depression, StepTimes())
    flow = flow_directions(env, land, surfaces.routing, StepTimes())
    runner = TileRunner(128, stage=STAGE, run_key="k", seed=0, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    core = tiled.flow_core(runner, GridFile(tmp_path / "h.exr"), HydrologyParams(depression=depression))
    rounds = [p["pass"] for p in runner.passes if p["pass"].startswith("breached_routing")]
    assert bool(rounds) == (depression == "breach" and lowest_m == 0.0), rounds
    whole = lambda name: core[name].read(0, 0, *land.shape)
    assert np.array_equal(whole("filled"), surfaces.filled, equal_nan=True)
    assert np.array_equal(whole("routing"), surfaces.routing, equal_nan=True)
    assert np.array_equal(whole("code"), flow.code)
    assert np.array_equal(whole("counts").astype(np.float64) * land.cell_area, flow.area_m2)


@pytest.mark.parametrize("rain", ["uniform", "lapse", "map"])
def test_the_tiled_discharge_equals_the_untiled(tmp_path, rain):
    """Uniform rain (the drainage area times the runoff), rain with height
    (fixed-point weights at the world's scale from an exact total) and a
    rain map read by window: the discharge bitwise the untiled one, on part
    tiles with no-data across their borders."""
    from pipeline import exr
    from pipeline.grid import Grid
    from pipeline.opencl import get_cl
    from pipeline.tiles import GridFile, TileRunner
    from pipeline.timing import StepTimes
    from stages.hydrology import STAGE, HydrologyParams
    from stages.hydrology import tiled
    from stages.hydrology.routing import (condition, discharge_m3_s, flow_directions, land_of, rain_from_map,
                                          rain_m_per_year)
    from tests.worldlib.flow.worlds import fractal

    h = (fractal(300, seed=9)[:, :270] * 400.0).astype(np.float32)
    h[100:140, 250:262] = np.nan
    h[40:44, :60] = np.inf
    exr.write_grid(tmp_path / "h.exr", Grid(h, 8.0))
    rain_map = None
    if rain == "map":
        rain_map = tmp_path / "rain.exr"
        exr.write_grid(rain_map, Grid(np.random.default_rng(3).uniform(200.0, 3000.0, (7, 9)).astype(np.float32), 1.0))
    params = HydrologyParams(depression="fill", rain_lapse_mm_per_year_per_100m=150.0 if rain == "lapse" else 0.0,
                             rain_map_path=str(rain_map) if rain_map else None)
    env = get_cl()
    land = land_of(exr.read_grid(tmp_path / "h.exr"))
    flow = flow_directions(env, land, condition(env, land, "fill", StepTimes()).routing, StepTimes())
    rain_mm = None if rain_map is None else rain_from_map(rain_map, *land.shape)
    want = discharge_m3_s(env, land, flow, rain_m_per_year(land, params, rain_mm), params, StepTimes())
    runner = TileRunner(128, stage=STAGE, run_key="k", seed=0, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    core = tiled.flow_core(runner, GridFile(tmp_path / "h.exr"), params)
    got = tiled.discharge(runner, GridFile(tmp_path / "h.exr"), core, params, rain_map).read(0, 0, *land.shape)
    assert got.dtype == np.float64 and np.array_equal(got, want)
    assert params.uniform_rain == (rain == "uniform") and np.ptp(want[land.data]) > 0


def test_the_tiled_river_network_is_the_whole_worlds(tmp_path):
    """The network's cells gathered tile by tile (part tiles, no-data across
    borders, rivers crossing tiles) are the whole world's, with the same
    receivers, codes, areas, discharges and heights, and solve to the same rivers."""
    from pipeline import exr
    from pipeline.grid import Grid
    from pipeline.opencl import get_cl
    from pipeline.tiles import GridFile, TileRunner
    from pipeline.timing import StepTimes
    from stages.hydrology import STAGE, HydrologyParams
    from stages.hydrology import rivers, tiled
    from stages.hydrology.routing import condition, discharge_m3_s, flow_directions, land_of, rain_m_per_year
    from tests.worldlib.flow.worlds import fractal
    from worldlib.flow import reference as ref
    import math

    yy, xx = np.mgrid[0:300, 0:270] / 300.0
    h = (fractal(300, seed=4)[:, :270] * 20 + 300 * xx + 60 * np.sin(9 * xx) * np.cos(7 * yy)).astype(np.float32)
    h[100:140, 120:135] = np.nan
    exr.write_grid(tmp_path / "h.exr", Grid(h, 8.0))
    params = HydrologyParams(depression="fill", river_threshold_m2=2e4, rain_lapse_mm_per_year_per_100m=100.0)
    env = get_cl()
    land = land_of(exr.read_grid(tmp_path / "h.exr"))
    surfaces = condition(env, land, params.depression, StepTimes())
    flow = flow_directions(env, land, surfaces.routing, StepTimes())
    q = discharge_m3_s(env, land, flow, rain_m_per_year(land, params, None), params, StepTimes())
    no_lakes = type("NoLakes", (), {"depth": np.zeros(land.shape), "level": np.full(land.shape, np.nan),
                                    "lake_id": np.zeros(land.shape, np.int32)})
    dry = np.zeros(land.shape, bool)
    want = rivers.gather_network(flow.code, flow.area_m2, q, land.h, no_lakes, surfaces.filled, dry,
                                 params.river_threshold_m2)
    runner = TileRunner(128, stage=STAGE, run_key="k", seed=0, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    terrain = GridFile(tmp_path / "h.exr")
    core = tiled.flow_core(runner, terrain, params)
    core["discharge"] = tiled.discharge(runner, terrain, core, params, None)
    got, sums = tiled.network(runner, terrain, core, params)
    cells = got["cells"]
    assert np.array_equal(cells, want.cells) and cells.size > 1000
    assert np.array_equal(got["filled"], surfaces.filled.ravel()[cells])
    assert sums["n_data"] == land.n_data and sums["depression_cells"] == int((surfaces.filled > land.h).sum())
    assert sums["discharge_out_m3_s"] == math.fsum(q[land.kind == 1].tolist()) > 0
    assert sums["mean_rain_m"] == math.fsum(rain_m_per_year(land, params, None)[land.data].tolist()) / land.n_data
    assert np.array_equal(ref.subset_receivers(cells, got["rcv"]), want.rcv)
    for name in ("code", "area_m2", "discharge", "h"):
        assert np.array_equal(got[name], getattr(want, name)), name
    assert (want.rcv >= 0).sum() == cells.size - (got["code"] == -1).sum()  # the network is closed downstream
    nw = rivers.network_of(cells, got["rcv"], got["code"], got["area_m2"], got["discharge"], got["h"],
                           np.zeros(cells.size), np.full(cells.size, np.nan), np.zeros(cells.size, np.int32),
                           got["filled"],
                           np.zeros(cells.size, bool))
    a, b = rivers.solve_network(nw, land.dx, land.n_data, params), rivers.solve_network(want, land.dx, land.n_data,
                                                                                       params)
    assert np.array_equal(a.order, b.order) and a.order.max() >= 3 and a.stats == b.stats


@pytest.mark.parametrize("tile", [64, 100])
def test_the_beds_carved_window_by_window_are_the_whole_carve(cl_env, tile):
    """channels.carve on windows of a world (with the segments near each:
    segments_near) gives the whole carve's ground and wet cells bitwise, with
    pools filled, reaches crossing windows and beds wider than a cell."""
    from pipeline.grid import Grid
    from pipeline.timing import StepTimes
    from stages.hydrology import HydrologyParams, channels, water_layer
    from stages.hydrology import lakes as lakes_mod
    from stages.hydrology import rivers
    from stages.hydrology.routing import condition, discharge_m3_s, flow_directions, land_of, rain_m_per_year
    from tests.worldlib.flow.worlds import fractal

    yy, xx = np.mgrid[0:300, 0:270] / 300.0
    h = (fractal(300, seed=7)[:, :270] * 20 + 300 * xx + 60 * np.sin(9 * xx) * np.cos(7 * yy)).astype(np.float32)
    params = HydrologyParams(river_threshold_m2=2e4, lake_min_area_m2=192.0, lake_runoff_depth_m=3.0,
                             river_mesh_min_width_m=0.5)
    land = land_of(Grid(h, 8.0))
    s = condition(cl_env, land, "fill", StepTimes())
    f = flow_directions(cl_env, land, s.routing, StepTimes())
    rain = rain_m_per_year(land, params, None)
    lk = lakes_mod.lake_maps(cl_env, land, s.filled, f.code, rain, params)
    riv = rivers.extract(f.code, f.area_m2, discharge_m3_s(cl_env, land, f, rain, params, StepTimes()), land.h, lk,
                         s.filled, land.dx, params)
    whole = water_layer.river_water(land, f.code, riv, lk.lake_id, lk.level, params)
    assert whole.stats["river_reaches"] >= 2 and whole.stats["river_pool_cells_filled"] > 0
    rs, pool_ids = water_layer.river_reaches(riv.network, riv.solved, land.shape, land.dx, tuple(land.origin_m),
                                             params)
    seg, origin = channels.segments(rs), tuple(land.origin_m)
    k = channels.carve_reach_cells(seg, land.dx, params.river_floor_m, params.river_bank_m)
    ground, wet = np.empty(land.shape), np.empty(land.shape, bool)
    parts = []
    for r0 in range(0, land.shape[0], tile):
        for c0 in range(0, land.shape[1], tile):
            sl = np.s_[r0:r0 + tile, c0:c0 + tile]
            near = channels.segments_near(seg, land.dx, origin, (r0, c0, tile, tile), k)
            assert len(near["a"]) < len(seg["a"]) or len(seg["a"]) < 50
            ground[sl], wet[sl], pools = water_layer.carved_ground(land.h[sl], lk.lake_id[sl], lk.level[sl], near,
                                                                   pool_ids, land.dx, origin, params,
                                                                   window=(r0, c0, *land.shape))
            parts.append((True, water_layer.ground_stats(land.h[sl], ground[sl], wet[sl], pools)))
    assert np.array_equal(ground, whole.ground, equal_nan=True) and np.array_equal(wet, whole.wet)
    stats = water_layer.tiles_ground_stats(parts)
    assert stats == {k_: whole.stats[k_] for k_ in stats}


def _wet_tile(tctx, inputs, params, shared):
    from pipeline.tiles import TileOutput

    return TileOutput({"wet": inputs["under"].read_tile(tctx.tile) > 0})


def test_the_tiled_wetness_and_moisture_equal_the_whole(tmp_path):
    """Wetness and moisture tile by tile (a one-cell halo for the slopes, the
    open water within its reach, the erosion stage's moisture by window) are
    the whole run's bitwise, with no-data across tile borders and water
    beyond a tile's reach."""
    from pipeline import exr
    from pipeline.grid import Grid
    from pipeline.opencl import get_cl
    from pipeline.tiles import GridFile, TileRunner
    from pipeline.timing import StepTimes
    from stages.hydrology import STAGE, HydrologyParams
    from stages.hydrology import tiled
    from stages.hydrology.moisture import water_reach_cells, wetness_and_moisture
    from stages.hydrology.routing import condition, flow_directions, land_of
    from tests.worldlib.flow.worlds import fractal

    h = (fractal(300, seed=2)[:, :290] * 300.0).astype(np.float32)
    h[100:140, 120:135] = np.nan
    h[250, :40] = -np.inf
    exr.write_grid(tmp_path / "h.exr", Grid(h, 8.0))
    rng = np.random.default_rng(5)
    ext = rng.uniform(-0.2, 1.2, h.shape).astype(np.float32)
    ext[5:9, 5:9] = np.nan
    exr.write_grid(tmp_path / "m.exr", Grid(ext, 8.0, ("moisture",)))
    water = np.zeros(h.shape, bool)
    water[20:23, 30:200] = True  # a river across tiles
    water[280, 280] = True
    params = HydrologyParams(moisture_water_distance_m=60.0)
    assert water_reach_cells(8.0, 60.0) == 60
    env = get_cl()
    land = land_of(exr.read_grid(tmp_path / "h.exr"))
    flow = flow_directions(env, land, condition(env, land, params.depression, StepTimes()).routing, StepTimes())
    want = wetness_and_moisture(env, land, flow.area_m2, water, exr.read_grid(tmp_path / "m.exr"), params)
    runner = TileRunner(128, stage=STAGE, run_key="k", seed=0, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    terrain = GridFile(tmp_path / "h.exr")
    core = tiled.flow_core(runner, terrain, params)
    # the open water as the run has it: a river's cells, a lake's, and cells under a river's surface
    river, lake, under = np.zeros_like(water), np.zeros_like(water), np.zeros_like(water)
    river[20:23, 30:120], lake[20:23, 120:200], under[280, 280] = True, True, True
    assert np.array_equal(river | lake | under, water)
    cells = lambda m: np.flatnonzero(m).astype(np.int64)
    rivers_ = tiled.SparseCells(h.shape[1], cells(river), {"mask": np.ones(river.sum(), bool)})
    lakes = tiled.SparseCells(h.shape[1], cells(lake | (water[::-1] & ~water)),
                              {"depth": np.where(lake, 1.0, 0.0)[lake | (water[::-1] & ~water)]})
    exr.write_grid(tmp_path / "u.exr", Grid(under.astype(np.float32), 8.0, ("wet",)))
    wet, _ = runner.map(_wet_tile, "wet", h.shape, {"under": GridFile(tmp_path / "u.exr")}, None,
                        grids={"wet": ("wet",)})
    out = tiled.wetness(runner, terrain, core["counts"], GridFile(tmp_path / "m.exr"), wet["wet"], rivers_, lakes,
                        params)
    for name, w in zip(("wetness", "moisture"), want):
        assert np.array_equal(out[name].read(0, 0, *h.shape), w, equal_nan=True), name
    assert (want[1][150:, :100] > 0).any() and np.nanmin(want[1]) >= 0.0


@pytest.mark.parametrize("tile, lapse", [(128, 0.0), (100, 120.0)])
def test_the_tiled_depression_cells_are_the_whole_gather(tmp_path, tile, lapse):
    """lakes.DepressionCells gathered tile by tile (the lake routing's
    runoff in Barnes' passes, exits by pointer jumping, exits' ends chained
    through the tiles' perimeters) equal the whole maps' gather field by
    field, and solve to the same lakes, on a world of many lakes with
    no-data holes, lakes and spills across tile borders."""
    import functools

    from pipeline import exr
    from pipeline.grid import Grid
    from pipeline.opencl import get_cl
    from pipeline.tiles import GridFile, TileRunner
    from pipeline.timing import StepTimes
    from stages.hydrology import STAGE, HydrologyParams, tiled, tiled_lakes
    from stages.hydrology import lakes as lakes_mod
    from stages.hydrology.routing import condition, flow_directions, land_of, rain_m_per_year
    from worldlib.flow import device as dev
    from tests.worldlib.flow.worlds import fractal

    yy, xx = np.mgrid[0:300, 0:280] / 300.0
    h = (fractal(300, seed=11)[:, :280] * 25 + 200 * xx + 60 * np.sin(9 * xx) * np.cos(7 * yy)).astype(np.float32)
    h[100:140, 150:165] = np.nan
    h[210, 20:60] = np.inf
    exr.write_grid(tmp_path / "h.exr", Grid(h, 8.0))
    params = HydrologyParams(depression="fill", lake_runoff_depth_m=2.0, rain_lapse_mm_per_year_per_100m=lapse)
    env = get_cl()
    land = land_of(exr.read_grid(tmp_path / "h.exr"))
    surfaces = condition(env, land, params.depression, StepTimes())
    flow = flow_directions(env, land, surfaces.routing, StepTimes())
    rain = rain_m_per_year(land, params, None)
    import math
    mean_rain = math.fsum(rain[land.data].tolist()) / land.n_data
    code_raw = dev.d8(env, np.where(land.data, land.h, np.float32(0)), land.kind, land.dx)
    want = lakes_mod.gather_depressions(land.h, land.kind, surfaces.filled, flow.code, code_raw,
                                        params.lake_runoff_depth_m * land.cell_area * rain / mean_rain,
                                        functools.partial(dev.accumulate, env))
    runner = TileRunner(tile, stage=STAGE, run_key="k", seed=0, project_root=tmp_path, units=None,
                        work=tmp_path / "work")
    terrain = GridFile(tmp_path / "h.exr")
    core = tiled.flow_core(runner, terrain, params)
    got = tiled_lakes.gather(runner, terrain, core, params, None)
    assert want.size > 500 and want.exits.size > 20 and got.total_in == want.total_in
    assert got.out_direct == want.out_direct and (got.cols, got.n_cells) == (want.cols, want.n_cells)
    for name in lakes_mod.DepressionCells.PER_CELL + lakes_mod.DepressionCells.PER_EXIT:
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    a = lakes_mod.solve_depressions(got, land.cell_area)
    b = lakes_mod.solve_depressions(want, land.cell_area)
    assert np.array_equal(a.level, b.level, equal_nan=True) and np.array_equal(a.lake_id, b.lake_id)
    assert a.stats == b.stats and a.stats["lakes"] > 20 and a.spills == b.spills


def test_a_tiled_world_is_checked_for_a_tile_and_its_sparse_sets():
    """The check names what a tiled run holds: a tile with the open water's
    reach and the cells of the world-wide solves, filled or breached; MFD runs whole."""
    from pipeline.contract import CheckContext, GridInfo
    from stages.hydrology import HydrologyParams
    from stages.hydrology.stage import BYTES_PER_CELL, check

    inputs = {"terrain": GridInfo((16384, 16384), 1.0, "heightmap.resolution")}
    ctx = lambda tile: CheckContext(seed=0, project_root=Path("."), inputs=inputs, tile_cells=tile)
    fill = HydrologyParams(depression="fill")
    assert check(fill, ctx(0)).memory_bytes == BYTES_PER_CELL * 16384 ** 2
    tiled = check(fill, ctx(1024))
    assert tiled.memory_bytes < 4e9 and "1664^2" in tiled.memory_how  # 1024 + 2 x 320 cells of reach
    assert check(HydrologyParams(depression="breach"), ctx(1024)).memory_bytes == tiled.memory_bytes
    assert check(HydrologyParams(flow="mfd"), ctx(1024)).memory_bytes == BYTES_PER_CELL * 16384 ** 2
