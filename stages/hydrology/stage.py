"""The hydrology stage: depressions, flow, rivers, lakes and moisture.

Pipeline (every step exact against reference.py, see the tests):
1. Depression handling: complete breaching (Lindsay 2016, the default;
   one serial work-item, kernels.cl breach_serial, bit-exact against
   reference.breach) or Priority-Flood fill (Barnes 2014) by minimax
   relaxation on the OpenCL device (kernels.cl fill_tiles); then Priority-Flood+epsilon
   (a float32-safe step: one ulp where |h| >= 1 m, 2^-23 m below) so every
   cell has a strictly descending path to an edge: the routing surface.
2. D8 steepest descent on the routing surface (kernel d8, pysheds order).
3. D8 accumulation, exact in integers, in three tiled phases (kernels
   acc_local / acc_global / acc_final): drainage area in m^2 and discharge
   from the rain field. MFD (Quinn 1991) accumulation optionally feeds the
   wetness index.
4. Lakes (lakes.py): Fill-Spill-Merge with V = S * K_r (seed 003 algorithm 2).
5. Rivers (rivers.py): drainage area >= threshold, Strahler order, width
   from Q / v with v from slope; curves on the world's terrain mesh whose
   water surface never rises downstream.
6. Wetness ln(a / tan b) and moisture (kernel wetness).

No-data (NaN or infinite heights) cells are outlets: their data neighbours
are edge cells that water leaves the map through, like the map border.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np

from pipeline.contract import Artifact, Check, CheckContext, Input, Param, ParamError, Params, ProjectPath, RunContext, Stage
from pipeline.errors import InputError, StageError
from pipeline.grid import Grid
from worldlib.terrain import TERRAIN_SOURCES
from worldlib.terrain.hillshade import hillshade
from worldlib.terrain.stats import terrain_statistics

from worldlib.flow import device as dev
from . import lakes as lakes_mod
from . import mfd
from worldlib.flow import reference as ref
from . import rivers as rivers_mod

SECONDS_PER_YEAR = 365.25 * 86400.0
# Channel heads: 0.1 km^2. Source areas measured at channel heads in steep soil-mantled land reach 1e2 .. 1e5
# m^2 (Montgomery and Dietrich 1988, 1992); DEM studies take 0.1 km^2 and less for networks of mountain land. The
# default world's slope-area plot follows the fluvial power law S ~ A^-theta from about 2e4 m^2, so this is inside
# the fluvial range (4e5 m^2 before, the heads of 8 km basins of about 28 km^2 had room for order 3 only).
CHANNEL_HEAD_AREA_M2 = 1.0e5
RIVER_MAX_RISE_M = 0.5  # a river segment may pass over ground this much above its higher end, no more


class HydrologyParams(Params):
    depression: Literal["fill", "breach"] = Param(
        "breach", description="depression handling for flow routing: breach (complete breaching, Lindsay 2016: "
        "water runs downhill into each pit and out along a carved path; serial) or fill (Priority-Flood, parallel: "
        "water crosses the filled flats in straight lines); lakes always use the filled levels of the real terrain")
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
    river_velocity_coefficient_m_s: float = Param(
        12.0, units="m/s", description="flow velocity v = k sqrt(slope) (Chezy-like), clamped to the min/max below",
        gt=0.0, le=1000.0)
    river_velocity_min_m_s: float = Param(0.2, units="m/s", description="slowest river flow (flats, lakes)", gt=0.0, le=100.0)
    river_velocity_max_m_s: float = Param(4.0, units="m/s", description="fastest river flow", gt=0.0, le=100.0)
    river_min_slope: float = Param(1e-4, units="m/m", description="slope floor for velocities", gt=0.0, le=1.0)
    river_width_depth_ratio: float = Param(12.0, units="", description="channel width / depth; width = sqrt(ratio * Q / v)", gt=0.0, le=1000.0)
    river_lift_m: float = Param(0.3, units="m", description="height of river curves above the terrain mesh", ge=0.0, le=100.0)
    lakes: bool = Param(True, description="compute lakes (Fill-Spill-Merge); off: no lakes, nothing computed")
    lake_runoff_depth_m: float = Param(
        0.05, units="m", description="K_r of seed 003: depth of water over each catchment that its basins receive "
        "(V = S * K_r), scaled by the local rain relative to the mean", ge=0.0, le=1000.0)
    lake_min_area_m2: float = Param(20000.0, units="m^2", description="smallest lake written to USD (all lakes are in the maps)", ge=0.0, le=1e12)
    mesh_max_vertices: int = Param(
        513, units="vertices", description="terrain mesh vertices per side the curves sit on: keep equal to "
        "world.mesh_max_vertices", ge=2, le=8193)
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


def rain_from_map(path: Path, rows: int, cols: int) -> np.ndarray:
    """Yearly rain (mm/year, float64) from an image file, stretched over the
    rows x cols terrain (cell-centred bilinear); clear errors for a missing,
    corrupt, integer, non-finite or negative map."""
    from worldlib.terrain.dem import read_dem, resample

    try:
        src = read_dem(path, label="rain map")
    except InputError as e:
        raise InputError(f"hydrology: {e}") from None
    if (src < 0).any():
        r, c = np.argwhere(src < 0)[0]
        raise InputError(f"hydrology: rain map {path} has negative rain ({float(src[r, c]):g} mm/year at row {r}, "
                         f"column {c})")
    return resample(src, (rows, cols), (0, 0, cols, rows)).astype(np.float64)


def _preview(h: Grid, lake_depth: np.ndarray, river: np.ndarray) -> np.ndarray:
    img = hillshade(Grid(np.nan_to_num(h.data, nan=float(np.nanmin(h.data)) if np.isfinite(h.data).any() else 0.0),
                         h.cell_size_m)).astype(np.float32)
    water = np.array([40, 90, 160], np.float32)
    lake = (lake_depth > 0)[..., None]
    img = np.where(lake, 0.3 * img + 0.7 * water, img)
    img = np.where(river[..., None], 0.2 * img + 0.8 * np.array([30, 110, 220], np.float32), img)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def run(ctx: RunContext, inputs: dict[str, Any], params: HydrologyParams) -> dict[str, Any]:
    t_all = time.perf_counter()
    T: dict[str, float] = {}
    terrain: Grid = inputs["terrain"]
    h = ref.canonical(terrain.channel(terrain.channels[0]))
    rows, cols = h.shape
    dx = float(terrain.cell_size_m)
    cell_area = dx * dx
    kind = ref.cell_kinds(h)
    h[kind == ref.NODATA] = np.nan
    data = kind != ref.NODATA
    if not data.any():
        raise InputError("hydrology: the terrain has no finite height (every cell is no-data)")
    n_data = int(data.sum())

    def lap(name, t0):
        T[name] = time.perf_counter() - t0

    ctx.progress(0.0, "depressions")
    t0 = time.perf_counter()
    fstats: dict = {}
    F = dev.fill(h, kind, eps=False, stats=fstats)
    lap("fill_s", t0)
    t0 = time.perf_counter()
    cond = dev.breach(h, kind) if params.depression == "breach" else h
    lap("breach_s", t0)
    t0 = time.perf_counter()
    R = dev.fill(cond, kind, eps=True)
    lap("fill_epsilon_s", t0)
    ctx.progress(0.25, "flow directions")
    t0 = time.perf_counter()
    code = dev.d8(R, kind, dx)
    lap("flowdir_s", t0)
    if (code == ref.PIT).any():
        raise StageError("hydrology: a cell has no downslope path after depression handling (broken invariant)")
    t0 = time.perf_counter()
    counts = dev.accumulate(code)
    lap("accumulation_s", t0)
    outlet_total = int(counts[kind == ref.EDGE].astype(np.int64).sum())
    if outlet_total != n_data:
        raise StageError(f"hydrology: accumulation at the outlets is {outlet_total} cells, not {n_data}")
    area_m2 = counts.astype(np.float64) * cell_area

    # rain and runoff (m/year); discharge in m^3/s
    hmin = float(np.nanmin(h))
    if params.rain_map_path is not None:
        rain = np.where(data, rain_from_map(ctx.resolve(params.rain_map_path), rows, cols), 0.0) / 1000.0
        ctx.metrics["rain_map_mean_mm_per_year"] = float(rain[data].mean() * 1000.0)
    else:
        rain = np.where(data, params.rain_mm_per_year + params.rain_lapse_mm_per_year_per_100m
                        * (np.nan_to_num(h, nan=hmin) - hmin) / 100.0, 0.0)
        rain = np.maximum(rain, 0.0) / 1000.0
    runoff = rain * params.runoff_coefficient
    t0 = time.perf_counter()
    if params.uniform_rain:
        discharge = area_m2 * (params.rain_mm_per_year / 1000.0 * params.runoff_coefficient) / SECONDS_PER_YEAR
    else:
        q, scale = dev.quantize(runoff * cell_area)
        discharge = dev.accumulate(code, q).astype(np.float64) / scale / SECONDS_PER_YEAR
    lap("discharge_s", t0)
    twi_area = area_m2
    if params.flow == "mfd":
        t0 = time.perf_counter()
        twi_area = mfd.accumulate(R, kind, dx, params.mfd_exponent, data.astype(np.float64) * cell_area)
        lap("mfd_accumulation_s", t0)
        ctx.metrics["mfd_area_relative_error"] = float(abs(twi_area[kind == ref.EDGE].sum() - n_data * cell_area) / (n_data * cell_area))

    ctx.progress(0.45, "lakes")
    t0 = time.perf_counter()
    if params.lakes:
        code_raw = dev.d8(np.where(data, h, np.float32(0)), kind, dx)
        mean_rain = float(rain[data].mean()) if rain[data].mean() > 0 else 1.0
        lake_in = params.lake_runoff_depth_m * cell_area * rain / mean_rain
        lk = lakes_mod.solve_lakes(h, kind, F, code, code_raw, lake_in, cell_area, dev.accumulate, dev.merge_sweep)
        lake_depth, lake_level, lake_id, lstats = lk.depth, lk.level, lk.lake_id, lk.stats
        if lstats["budget_relative_error"] > 1e-6:
            raise StageError(f"hydrology: lake volume budget off by {lstats['budget_relative_error']:.2e} (relative)")
    else:
        lake_depth, lake_level = np.zeros((rows, cols)), np.full((rows, cols), np.nan)
        lake_id, lstats = np.zeros((rows, cols), np.int32), {"lakes": 0}
    lap("lakes_s", t0)

    ctx.progress(0.6, "rivers")
    t0 = time.perf_counter()
    mesh = None
    if rows >= 2 and cols >= 2:
        from worldlib.terrain.mesh import build_terrain_mesh

        mesh = build_terrain_mesh(Grid(np.nan_to_num(h, nan=hmin), dx, ("height",), terrain.origin_m), params.mesh_max_vertices)
    ground = np.nan_to_num(h, nan=hmin).astype(np.float64)
    riv = rivers_mod.extract(code, area_m2, discharge, h, lake_depth, ground, dx, params.river_threshold_m2,
                             params.river_velocity_coefficient_m_s, params.river_velocity_min_m_s,
                             params.river_velocity_max_m_s, params.river_min_slope, params.river_width_depth_ratio,
                             params.river_lift_m)
    from worldlib.terrain.mesh import height_on_mesh

    if mesh is not None and riv.curves:
        used = np.unique(np.concatenate(riv.curves))
        ox, oz = terrain.origin_m
        gm = ground.ravel().copy()
        gm[used] = height_on_mesh(mesh, ox + (used % cols + 0.5) * dx, oz + (used // cols + 0.5) * dx)
        riv = rivers_mod.extract(code, area_m2, discharge, h, lake_depth, gm.reshape(rows, cols), dx,
                                 params.river_threshold_m2, params.river_velocity_coefficient_m_s,
                                 params.river_velocity_min_m_s, params.river_velocity_max_m_s, params.river_min_slope,
                                 params.river_width_depth_ratio, params.river_lift_m)
    lap("rivers_s", t0)

    ctx.progress(0.7, "wetness and moisture")
    t0 = time.perf_counter()
    open_water = riv.mask | (lake_depth > 0)
    if open_water.any():
        from scipy import ndimage

        dist = ndimage.distance_transform_edt(~open_water) * dx
        m_water = np.exp(-dist / params.moisture_water_distance_m)
    else:
        m_water = np.zeros((rows, cols))
    ext = inputs.get("erosion_moisture")
    if ext is not None:
        M = np.nan_to_num(ext.channel(ext.channels[0]).astype(np.float64), nan=0.0)
        if M.shape != (rows, cols):
            raise InputError(f"hydrology: erosion moisture is {M.shape}, the terrain {(rows, cols)}")
        m_ext = np.clip(M, 0.0, 1.0)  # the erosion stage's running average of water presence, 0..1
    else:
        m_ext = np.zeros((rows, cols))
    twi, moisture = dev.wetness(h, kind, twi_area, m_water, m_ext, dx, params.wetness_min_slope,
                                params.wetness_dry, params.wetness_wet)
    lap("wetness_s", t0)

    t0 = time.perf_counter()
    hack = rivers_mod.hack_exponent(code, area_m2, dx, params.hack_min_area_m2)
    lap("hack_s", t0)
    t0 = time.perf_counter()
    # does the final terrain read as eroded land (grid anisotropy, depressions, Strahler, Hack, theta ...)
    terrain_stats = terrain_statistics(h, F, code, area_m2, dx, params.river_threshold_m2, data)
    lap("terrain_statistics_s", t0)

    ctx.progress(0.8, "water layer")
    t0 = time.perf_counter()
    from . import water_usd

    ox, oz = terrain.origin_m
    pts, ws, qs, orders = [], [], [], []
    surf = riv.surface.ravel()
    for seg in riv.curves:
        x = ox + (seg % cols + 0.5) * dx
        z = oz + (seg // cols + 0.5) * dx
        if mesh is not None:
            # the curve lies on the terrain mesh (lifted by river_lift_m), also where it ends on a lake's shore:
            # the coarse mesh can stand above a small lake's level, and a vertex at the level would be buried
            y = height_on_mesh(mesh, x, z) + params.river_lift_m
        else:
            y = surf[seg]
        if not np.isfinite(y).all():
            continue
        w = np.maximum.accumulate(riv.width.ravel()[seg])
        q = discharge.ravel()[seg]
        if mesh is not None:
            x, y, z, w, q = rivers_mod.follow_mesh(lambda px, pz: height_on_mesh(mesh, px, pz) + params.river_lift_m,
                                                   x, y, z, w, q, RIVER_MAX_RISE_M)
        pts.append(np.stack([x, y, z], 1))
        ws.append(w)
        qs.append(q)
        orders.append(int(riv.order.ravel()[seg[0]]))
    lake_list = []
    if params.lakes and lstats.get("lakes", 0):
        from scipy import ndimage

        objs = ndimage.find_objects(lake_id)
        for lid, sl in enumerate(objs, start=1):
            if sl is None:
                continue
            r0, r1 = max(sl[0].start - 1, 0), min(sl[0].stop + 1, rows)
            c0, c1 = max(sl[1].start - 1, 0), min(sl[1].stop + 1, cols)
            m = lake_id[r0:r1, c0:c1] == lid
            if m.sum() * cell_area < params.lake_min_area_m2:
                continue
            grown = np.zeros((rows, cols), bool)
            grown[r0:r1, c0:c1] = ndimage.binary_dilation(m, structure=np.ones((3, 3), bool)) & data[r0:r1, c0:c1]
            lake_list.append((lid, float(np.nanmax(lake_level[r0:r1, c0:c1][m])), grown))
    usd_path = ctx.path("hydrology.water")
    uinfo = water_usd.write(usd_path, ctx.provenance, pts, ws, qs, orders, lake_list, dx, (ox, oz))
    lap("usd_s", t0)

    # grids
    def grid(a, channels):
        return Grid(np.ascontiguousarray(np.asarray(a), dtype=np.float32), dx, channels, terrain.origin_m)

    nan = np.float32(np.nan)
    k = np.clip(code, 0, 7)
    fx = np.where(code >= 0, ref.DC[k], 0).astype(np.float32)
    fz = np.where(code >= 0, ref.DR[k], 0).astype(np.float32)
    norm = np.maximum(np.hypot(fx, fz), 1)
    flow = np.stack([fx / norm, fz / norm, code.astype(np.float32)], axis=-1)
    flow[~data] = nan
    depth32 = np.where(data, lake_depth, nan)
    lakes_grid = np.stack([depth32, np.where(lake_depth > 0, lake_level, nan), lake_id.astype(np.float32)], -1)
    rivers_grid = np.stack([riv.mask.astype(np.float32), np.where(riv.mask, riv.width, 0.0), riv.order.astype(np.float32)], -1)
    acc_grid = np.stack([np.where(data, area_m2, nan), np.where(data, discharge, nan)], -1)
    out = {
        "hydrology.filled": grid(np.where(data, F, nan), ("height",)),
        "hydrology.conditioned": grid(np.where(data, R, nan), ("height",)),
        "hydrology.flow": grid(flow, ("flow.x", "flow.z", "flow.d8")),
        "hydrology.accumulation": grid(acc_grid, ("flow.accumulation", "flow.discharge")),
        "hydrology.lakes": grid(lakes_grid, ("lake.depth", "lake.level", "lake.id")),
        "hydrology.rivers": grid(rivers_grid, ("river.mask", "river.width", "river.order")),
        "hydrology.wetness": grid(twi, ("wetness",)),
        "hydrology.moisture": grid(moisture, ("moisture",)),
        "hydrology.water": usd_path,
        "hydrology.preview": _preview(grid(h, ("height",)), lake_depth, riv.mask),
    }
    for name, g in out.items():
        if isinstance(g, Grid) and np.isinf(g.data).any():
            raise StageError(f"hydrology: {name} has infinite values")
    T["total_s"] = time.perf_counter() - t_all
    stats = {
        "cells": int(rows * cols), "data_cells": n_data, "cell_size_m": dx,
        "depression_cells": int((F > h).sum()), "fill_passes": fstats.get("passes"),
        "fill_tiles_run": fstats.get("tiles_run"), "total_area_m2": float(n_data * cell_area),
        "outlet_area_m2": float(outlet_total * cell_area), "discharge_out_m3_s": float(discharge[kind == ref.EDGE].sum()),
        **{f"lake_{k_}" if not k_.startswith("lake") else k_: v for k_, v in lstats.items()},
        **riv.stats, **hack, **uinfo, "terrain": terrain_stats, "timings": T,
    }
    stats = {k_: (float(v) if isinstance(v, np.floating) else v) for k_, v in stats.items()}
    ctx.metrics.update(stats)
    out["hydrology.stats"] = stats
    ctx.progress(1.0, "done")
    return out


def _grid(name, file, channels, units, description, nodata_nan=False):
    return Artifact(name, kind="grid", file=file, channels=channels, units=units, description=description,
                    nodata_nan=nodata_nan)


BYTES_PER_CELL = 160  # about 20 float64/float32 fields: heights, fills, codes, accumulation, lakes, rivers, moisture


def check(params: HydrologyParams, ctx: CheckContext) -> Check:
    """The rain map opened, sized and checked (finite, not negative) now;
    the memory from the terrain's cells."""
    if params.rain_map_path is not None:
        try:
            rain_from_map(ctx.resolve(params.rain_map_path), 2, 2)
        except InputError as e:
            raise ParamError("rain_map_path", str(e).removeprefix("hydrology: ")) from None
    terrain = ctx.inputs.get("terrain")
    if terrain is None:
        return Check()
    cells = terrain.shape[0] * terrain.shape[1]
    return Check(memory_bytes=BYTES_PER_CELL * cells, memory_how=f"the terrain's {cells:,} cells x {BYTES_PER_CELL} B")


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
              "routing surface: filled or breached, then epsilon-filled so every cell drains (float32 steps)"),
        _grid("hydrology.flow", "flow.exr", ("flow.x", "flow.z", "flow.d8"), "1",
              "D8 flow direction: unit vector (x east, z south) and code (0..7 = N, NE, E, SE, S, SW, W, NW as in "
              "pysheds; -1 outlet; NaN no-data)", nodata_nan=True),
        _grid("hydrology.accumulation", "accumulation.exr", ("flow.accumulation", "flow.discharge"), "m^2, m^3/s",
              "D8 drainage area (m^2) and mean discharge (m^3/s) from rain * runoff"),
        _grid("hydrology.lakes", "lakes.exr", ("lake.depth", "lake.level", "lake.id"), "m, m, 1",
              "lake water depth (m), water level (m, NaN where dry) and lake id (0 = dry)", nodata_nan=True),
        _grid("hydrology.rivers", "rivers.exr", ("river.mask", "river.width", "river.order"), "1, m, 1",
              "river mask (0/1), channel width (m) and Strahler order"),
        _grid("hydrology.wetness", "wetness.exr", ("wetness",), "ln(m)", "topographic wetness index ln(a / tan b)"),
        _grid("hydrology.moisture", "moisture.exr", ("moisture",), "1",
              "moisture 0..1 from the wetness index, open water and the erosion stage's moisture"),
        Artifact("hydrology.water", kind="usd", file="water.usda", shape="any",
                 description="/World/Water: rivers as BasisCurves with widths, lakes as flat water meshes, material"),
        Artifact("hydrology.stats", kind="json", file="stats.json", shape="any",
                 description="counts, budgets, Hack's law exponent, terrain statistics (grid anisotropy, share of area "
                 "in closed depressions, Strahler order, Hack exponent, concavity theta, drainage density, "
                 "hypsometric integral: worldlib/terrain/stats.py), timings"),
        Artifact("hydrology.preview", kind="image", file="preview.png", dtype="uint8",
                 description="hillshade with lakes and rivers, 8-bit RGB"),
    ),
    params=HydrologyParams,
    run=run,
    check=check,
    source_dir=Path(__file__).resolve().parent,
    uses_opencl=True,
    shared_params=("mesh_max_vertices",),
)
