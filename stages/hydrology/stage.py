"""The hydrology stage: depressions, flow, rivers, lakes and moisture.

Pipeline (every step exact against reference.py, see the tests):
1. Depression handling (routing.py, as steps 2 and 3): Priority-Flood fill
   (Barnes 2014) on the OpenCL device in three phases (kernels.cl
   fill_local, fill_levels, fill_combine: per-tile fill and labels, the
   spill levels over tile edges, the max of both); then Priority-Flood+
   epsilon by minimax relaxation (fill_tiles) (a float32-safe step: one ulp
   where |h| >= 1 m, 2^-23 m below) so every cell has a strictly
   descending path to an edge. That is the routing surface of
   depression = fill; the default, breach, carves each pit's way out
   instead (complete breaching, worldlib.flow.drainage_breach: across a
   depression along Lindsay's flood order from its outlet, then down the
   epsilon-filled surface's drainage; no cell raised, the same cells on a
   tiled world), and epsilon-fills that.
2. D8 steepest descent on the routing surface (kernel d8, pysheds order).
3. D8 accumulation, exact in integers, in three tiled phases (kernels
   acc_local / acc_global / acc_final): drainage area in m^2 and discharge
   from the rain field. MFD (Quinn 1991) accumulation optionally feeds the
   wetness index.
4. Lakes (lakes.py): Fill-Spill-Merge with V = S * K_r (seed 003 algorithm 2).
5. Rivers (rivers.py, channels.py, water_layer.py): drainage area >=
   threshold, Strahler order; bankfull discharge from the runoff, width and
   depth by hydraulic geometry; a water level that never rises downstream;
   the beds carved into the ground (hydrology.ground) and the river surfaces
   as ribbon meshes on them.
6. Wetness ln(a / tan b) and moisture (moisture.py, kernel wetness).
7. The USD water layer (water_usd.py: ribbons and lakes with the water
   material) and the grids (grids.py).

No-data (NaN or infinite heights) cells are outlets: their data neighbours
are edge cells that water leaves the map through, like the map border.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np

from pipeline.contract import (Artifact, Check, CheckContext, DrawnMap, Input, Param, ParamError, Params, ProjectPath,
                               Relief, ReportMap, ReportTable, RunContext, Stage, ValueRange)
from pipeline.errors import InputError, StageError
from pipeline import exr
from pipeline.grid import Grid
from pipeline.tiles import GridFile
from worldlib.terrain import TERRAIN_SOURCES
from worldlib.terrain.hillshade import hillshade

from . import channels
from . import lakes as lakes_mod
from worldlib.flow import reference as ref
from . import rivers as rivers_mod
from . import water_layer
from .grids import output_grids
from .moisture import wetness_and_moisture
from .report_water import draw_water, width_tables
from .routing import (SECONDS_PER_YEAR, Land, Timings, condition, discharge_m3_s, flow_directions,
                      land_of, rain_from_map, rain_m_per_year, wetness_area)
from . import summary, tiled_run

__all__ = ["SECONDS_PER_YEAR", "STAGE", "HydrologyParams", "rain_from_map", "run", "check"]
# Channel heads: 0.1 km^2. Source areas measured at channel heads in steep soil-mantled land reach 1e2 .. 1e5
# m^2 (Montgomery and Dietrich 1988, 1992); DEM studies take 0.1 km^2 and less for networks of mountain land. The
# default world's slope-area plot follows the fluvial power law S ~ A^-theta from about 2e4 m^2, so this is inside
# the fluvial range (4e5 m^2 before, the heads of 8 km basins of about 28 km^2 had room for order 3 only).
CHANNEL_HEAD_AREA_M2 = 1.0e5


class HydrologyParams(Params):
    depression: Literal["fill", "breach"] = Param(
        "breach", description="depression handling for flow routing: breach (complete breaching: water runs "
        "downhill into each pit and out along a path carved one float32 step per cell, across a depression along "
        "its lowest ground from the outlet its fill spills through, as Lindsay 2016 floods it, then down the "
        "drainage; tiled like fill) or fill (Priority-Flood: water crosses the filled flats in straight lines); "
        "lakes always use the filled levels of the real terrain")
    flow: Literal["d8", "mfd"] = Param(
        "d8", description="accumulation for the wetness index: d8 (single direction) or mfd (Quinn 1991 multiple "
        "flow directions); rivers always follow the D8 tree")
    mfd_exponent: float = Param(1.1, units="", description="mfd: flow share ~ slope^p * contour length", ge=0.1, le=10.0)
    rain_mm_per_year: float = Param(1000.0, units="mm/year", description="rain at the lowest point of the map", ge=0.0, le=20000.0)
    rain_lapse_mm_per_year_per_100m: float = Param(
        0.0, units="mm/year per 100 m", description="orographic rain: extra rain per 100 m above the lowest point "
        "(0 = uniform rain)", ge=-2000.0, le=2000.0)
    rain_map_path: Optional[ProjectPath] = Param(
        None, units="path", description="a rain map instead of rain_mm_per_year and the lapse: an image file (EXR, "
        "TIFF; first channel, float) of yearly rain in mm/year, stretched over the terrain and resampled bilinearly")
    runoff_coefficient: float = Param(0.5, units="", description="share of rain that runs off into rivers", ge=0.0, le=1.0)
    river_threshold_m2: float = Param(
        CHANNEL_HEAD_AREA_M2, units="m^2", description="drainage area at which a channel (river) starts: the "
        "channel heads of the network whose Strahler order, Hack exponent and concavity stats.json reports",
        gt=0.0, le=1e12)
    bankfull_discharge_ratio: float = Param(
        7.0, units="", description="bankfull discharge (about the 1.5-year flood, Leopold, Wolman and Miller 1964) "
        "over the mean annual discharge (runoff x drainage area): the flood that shapes the channel; in small "
        "mountain basins a few to about ten times the mean", gt=0.0, le=1000.0)
    width_coefficient: float = Param(
        4.33, units="m (m^3/s)^-b", description="a of the bankfull width w = a Q_bf^b (Leopold and Maddock 1953); "
        "4.33: Hey and Thorne 1986, gravel-bed rivers with grassy banks (3.33 to 2.34 with more trees on the banks)",
        gt=0.0, le=1000.0)
    width_exponent: float = Param(0.5, units="", description="b of w = a Q_bf^b (about 0.5 downstream)", gt=0.0, le=1.0)
    depth_coefficient: float = Param(
        0.22, units="m (m^3/s)^-f", description="c of the bankfull mean depth d = c Q_bf^f (Hey and Thorne 1986)",
        gt=0.0, le=100.0)
    depth_exponent: float = Param(0.37, units="", description="f of d = c Q_bf^f (0.3-0.4 downstream)", gt=0.0, le=1.0)
    river_mesh_min_width_m: float = Param(
        2.0, units="m", description="narrowest river drawn as a surface mesh and carved into the ground (narrower "
        "channels are only in the maps)", gt=0.0, le=1e4)
    river_floor_m: float = Param(
        2.0, units="m", description="floor either side of the channel, rising gently from the water level, so "
        "the ground grid resolves a channel narrower than its cells", ge=0.0, le=1e4)
    river_bank_m: float = Param(
        16.0, units="m", description="width over which the cut blends back into the terrain beyond the floor",
        ge=0.0, le=1e4)
    lakes: bool = Param(True, description="compute lakes (Fill-Spill-Merge); off: no lakes, nothing computed")
    lake_runoff_depth_m: float = Param(
        0.05, units="m", description="K_r of seed 003: depth of water over each catchment that its basins receive "
        "(V = S * K_r), scaled by the local rain relative to the mean", ge=0.0, le=1000.0)
    lake_min_area_m2: float = Param(
        2000.0, units="m^2", description="smallest lake written to USD (all lakes are in the maps); 2000 m^2: a pond "
        "about 45 m across, a few pixels in a view of the whole default world", ge=0.0, le=1e12)
    mesh_max_vertices: int = Param(
        1025, units="vertices", description="terrain mesh vertices per side (the world's): stats.json reports "
        "the share of the river surface that shows above this mesh of the carved ground", ge=2, le=8193)
    wetness_min_slope: float = Param(1e-3, units="m/m", description="slope floor in ln(a / tan b)", gt=0.0, le=1.0)
    wetness_dry: float = Param(3.0, units="ln(m)", description="wetness index mapped to moisture 0", ge=-50.0, le=50.0)
    wetness_wet: float = Param(12.0, units="ln(m)", description="wetness index mapped to moisture 1", ge=-50.0, le=50.0)
    moisture_water_distance_m: float = Param(
        40.0, units="m", description="moisture from open water decays as exp(-distance / this)", gt=0.0, le=1e5)
    hack_min_area_m2: float = Param(
        CHANNEL_HEAD_AREA_M2, units="m^2", description="smallest drainage area in the Hack's law fit: Hack's law is a law of the "
        "channel network, so the default is the channel-initiation area (river_threshold_m2's default)",
        gt=0.0, le=1e12)

    @property
    def uniform_rain(self) -> bool:
        return self.rain_lapse_mm_per_year_per_100m == 0.0 and self.rain_map_path is None


def run(ctx: RunContext, inputs: dict[str, Any], params: HydrologyParams) -> dict[str, Any]:
    t_all = time.perf_counter()
    T = Timings()
    land = land_of(inputs["terrain"])
    ctx.progress(0.0, "depressions")
    surfaces = condition(ctx.cl, land, params.depression, T)
    ctx.progress(0.25, "flow directions")
    flow = flow_directions(ctx.cl, land, surfaces.routing, T)
    rain = _rain(ctx, land, params)
    discharge = discharge_m3_s(ctx.cl, land, flow, rain, params, T)
    twi_area = _wetness_area(ctx, land, surfaces, flow, params, T)
    ctx.progress(0.45, "lakes")
    with T.lap("lakes_s"):
        lakes = lakes_mod.lake_maps(ctx.cl, land, surfaces.filled, flow.code, rain, params)
    ctx.progress(0.6, "rivers")
    with T.lap("rivers_s"):
        riv = rivers_mod.extract(flow.code, flow.area_m2, discharge, land.h, lakes, surfaces.filled, land.dx, params)
    with T.lap("river_beds_s"):
        water = water_layer.river_water(land, flow.code, riv, lakes.lake_id, lakes.level, params)
    ctx.progress(0.7, "wetness and moisture")
    with T.lap("wetness_s"):
        twi, moisture = wetness_and_moisture(ctx.cl, land, twi_area, riv.mask | water.wet | (lakes.depth > 0),
                                             inputs.get("erosion_moisture"), params)
    hack, terrain_stats = summary.network_statistics(land.h, surfaces.filled, flow.code, flow.area_m2, land.data,
                                                     land.dx, params, T)
    ctx.progress(0.8, "water layer")
    width_table = channels.width_table(flow.area_m2, riv.width, riv.net)
    with T.lap("usd_s"):
        lake_list = []
        if params.lakes and lakes.stats.get("lakes", 0):
            lake_list = water_layer.lake_outlines(land, lakes.lake_id, lakes.level, params.lake_min_area_m2)
        usd_path, uinfo = write_water_layer(ctx, water.ribbons, width_table, lake_list, land.dx, land.origin_m)
    out = output_grids(land, surfaces, flow, discharge, lakes, riv, twi, moisture, usd_path, water)
    for name, g in out.items():
        if isinstance(g, Grid) and np.isinf(g.data).any():
            raise StageError(f"hydrology: {name} has infinite values")
    T["total_s"] = time.perf_counter() - t_all
    stats = summary.stats_json(land.shape, land.n_data, land.dx, int((surfaces.filled > land.h).sum()),
                               flow.outlet_total, math.fsum(discharge[land.kind == ref.EDGE].tolist()), lakes.stats,
                               {**riv.stats, **water.stats}, hack, uinfo, terrain_stats)
    stats.update(summary.climate(math.fsum(rain[land.data].tolist()) / land.n_data, params),
                 river_width_by_area=width_table)
    # how the fill ran (its kernel's passes): the run's, not the content's
    ctx.metrics.update(stats, timings=dict(T), fill_run=surfaces.fill_stats)
    out["hydrology.stats"] = stats
    ctx.progress(1.0, "done")
    return out


def run_tiled(ctx: RunContext, inputs: dict[str, Any], params: HydrologyParams) -> dict[str, Any]:
    """run on a tiled world: every step per tile or on the few cells it
    concerns (tiled_run.py), with the same files; MFD wetness is serial
    and runs whole."""
    why = "MFD wetness (flow = mfd) is serial" if params.flow != "d8" else None
    if why is None:
        return tiled_run.run(ctx, inputs, params, write_water_layer)
    ctx.metrics["tiled_steps"] = f"none: {why}; the stage ran whole"
    return run(ctx, {role: exr.read_grid(v.path) if isinstance(v, GridFile) else v for role, v in inputs.items()},
               params)


def write_water_layer(ctx: RunContext, ribbons, width_table: list, lake_list: list, dx: float,
                      origin_m) -> tuple[Path, dict]:
    """/World/Water: the river ribbons and the lakes (lake_list: water_layer.lake_outlines')."""
    from . import water_usd

    usd_path = ctx.path("hydrology.water")
    return usd_path, water_usd.write(usd_path, ctx.provenance, ribbons, width_table, lake_list, dx, tuple(origin_m))


def _rain(ctx: RunContext, land: Land, params: HydrologyParams) -> np.ndarray:
    """Yearly rain (m/year): the rain map's (its mean a metric) or from the params."""
    if params.rain_map_path is None:
        return rain_m_per_year(land, params, None)
    rows, cols = land.shape
    rain = rain_m_per_year(land, params, rain_from_map(ctx.resolve(params.rain_map_path), rows, cols))
    ctx.metrics["rain_map_mean_mm_per_year"] = math.fsum(rain[land.data].tolist()) / land.n_data * 1000.0
    return rain


def _wetness_area(ctx: RunContext, land: Land, surfaces, flow, params: HydrologyParams, T: Timings) -> np.ndarray:
    twi_area, mfd_error = wetness_area(land, surfaces, flow, params, T)
    if mfd_error is not None:
        ctx.metrics["mfd_area_relative_error"] = mfd_error
    return twi_area


def _grid(name, file, channels, units, description, nodata_nan=False):
    return Artifact(name, kind="grid", file=file, channels=channels, units=units, description=description,
                    nodata_nan=nodata_nan)


# the whole run's maps (heights, fills, codes, accumulation, lakes, rivers, ground, moisture) and the terrain
# statistics' work: a 2048^2 bake peaked at 1.58 GB, 0.3 GB of it the Python and OpenCL runtime
BYTES_PER_CELL = 300


def check(params: HydrologyParams, ctx: CheckContext) -> Check:
    """The rain map checked now from its header and a bounded read
    (worldlib.terrain.dem.scan_raster: size, float, finite, 0 .. 20000
    mm/year, the range of rain_mm_per_year); the memory from the terrain's cells."""
    if params.rain_map_path is not None:
        from worldlib.terrain.dem import check_rain_map

        try:
            check_rain_map(ctx.resolve(params.rain_map_path), max_mm_per_year=20000.0)
        except InputError as e:
            raise ParamError("rain_map_path", str(e).removeprefix("hydrology: ")) from None
    terrain = ctx.inputs.get("terrain")
    if terrain is None:
        return Check()
    cells = terrain.shape[0] * terrain.shape[1]
    if ctx.tile_cells and params.flow == "d8":
        return _tiled_memory(params, tuple(terrain.shape), float(terrain.cell_size_m), ctx.tile_cells)
    return Check(memory_bytes=BYTES_PER_CELL * cells, memory_how=f"the terrain's {cells:,} cells x {BYTES_PER_CELL} B")


# a tiled run holds a tile pass at a time (a tile with the open water's reach around it) and the cells the
# world-wide solves work on: the river network's, the depressions', those draining enough for Hack's law (each
# about 100 B; together well under a tenth of the cells at any resolution)
# a tile pass's maps and numpy temporaries: a 4096^2 world at 2 m in 1024^2 tiles (1344^2 held with the water's
# reach) peaked at 0.95 GB, 0.3 GB of it the runtime
BYTES_PER_TILE_CELL = 300
SPARSE_BYTES_PER_CELL = 10


def _tiled_memory(params: HydrologyParams, shape: tuple[int, int], dx: float, tile_cells: int) -> Check:
    """A tile pass and the sparse sets of the world-wide solves."""
    from .moisture import water_reach_cells

    held = tile_cells + 2 * water_reach_cells(dx, params.moisture_water_distance_m)
    cells = shape[0] * shape[1]
    return Check(memory_bytes=BYTES_PER_TILE_CELL * held * held + SPARSE_BYTES_PER_CELL * cells,
                 memory_how=f"a tile and the water's reach ({held}^2 cells x {BYTES_PER_TILE_CELL} B) and the "
                 f"network's, depressions' and Hack's cells ({cells:,} cells x {SPARSE_BYTES_PER_CELL} B)")


STAGE = Stage(
    name="hydrology",
    version=1,
    description="Water: depression filling or breaching, D8 flow and accumulation, rivers with widths and Strahler "
    "order, lakes by Fill-Spill-Merge (seed 003 algorithm 2), wetness index and moisture, and a USD water layer",
    inputs=(
        Input("terrain", one_of=TERRAIN_SOURCES, description="the final terrain height", channels=("height",), units="m"),
        Input("erosion_moisture", one_of=("erosion.moisture",), optional=True, channels=("moisture",), units="1",
              description="where water stood during the erosion storm, 0..1"),
    ),
    outputs=(
        _grid("hydrology.filled", "filled.exr", ("height",), "m", "depression-filled height (Priority-Flood)"),
        _grid("hydrology.conditioned", "conditioned.exr", ("height",), "m",
              "routing surface: epsilon-filled, or breached along its drainage, so every cell drains (float32 steps)"),
        _grid("hydrology.flow", "flow.exr", ("flow.x", "flow.z", "flow.d8"), "1",
              "D8 flow direction: unit vector (x east, z south) and code (0..7 = N, NE, E, SE, S, SW, W, NW as in "
              "pysheds; -1 outlet; NaN no-data)", nodata_nan=True),
        _grid("hydrology.accumulation", "accumulation.exr", ("flow.accumulation", "flow.discharge"), "m^2, m^3/s",
              "D8 drainage area (m^2) and mean discharge (m^3/s) from rain * runoff"),
        _grid("hydrology.lakes", "lakes.exr", ("lake.depth", "lake.level", "lake.id"), "m, m, 1",
              "lake water depth (m), water level (m, NaN where dry) and lake id (0 = dry)", nodata_nan=True),
        _grid("hydrology.rivers", "rivers.exr", ("river.mask", "river.width", "river.order"), "1, m, 1",
              "river mask (0/1: the network and every cell under a river surface), bankfull width (m) and Strahler "
              "order"),
        _grid("hydrology.wetness", "wetness.exr", ("wetness",), "ln(m)", "topographic wetness index ln(a / tan b)"),
        _grid("hydrology.moisture", "moisture.exr", ("moisture",), "1",
              "moisture 0..1 from the wetness index, open water and the erosion stage's moisture"),
        _grid("hydrology.ground", "ground.exr", ("height",), "m",
              "the terrain with the river beds carved (bankfull channel, floor and banks) and the pools the rivers "
              "pass (lakes below lake_min_area_m2) filled to their level: the ground the world's mesh and the "
              "vegetation use", nodata_nan=True),
        Artifact("hydrology.water", kind="usd", file="water.usda", shape="any",
                 description="/World/Water: river surfaces as ribbon meshes at their water level, lakes as flat "
                 "meshes at their level, all bound to one UsdPreviewSurface water material; the width table"),
        Artifact("hydrology.stats", kind="json", file="stats.json", shape="any",
                 description="counts, budgets, Hack's law exponent, terrain statistics (grid anisotropy, share of area "
                 "in closed depressions, Strahler order, Hack exponent, concavity theta, drainage density, "
                 "hypsometric integral: worldlib/terrain/stats.py); the timings are metrics"),
        Artifact("hydrology.preview", kind="image", file="preview.png", dtype="uint8",
                 description="hillshade with lakes and rivers, 8-bit RGB"),
    ),
    params=HydrologyParams,
    run=run,
    run_tiled=run_tiled,
    check=check,
    report=(DrawnMap("water", "Rivers and lakes (as in the USD)", draw_water, Relief(hillshade, TERRAIN_SOURCES, "height")),
            ReportTable("River width against drainage area", width_tables),
            ReportMap("hydrology.moisture", "moisture", name="moisture", title="Moisture ({artifact})", palette="wet",
                      values=ValueRange(0.0, 1.0), relief=Relief(hillshade, TERRAIN_SOURCES, "height"))),
    source_dir=Path(__file__).resolve().parent,
    uses_opencl=True,
    shared_params=("mesh_max_vertices",),
)
