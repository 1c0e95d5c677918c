"""Depressions and flow (the stage's steps 1 to 3): the routing surface, D8
directions, drainage area, rain and discharge."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, StageError
from pipeline.grid import Grid
from worldlib.flow import device as dev
from worldlib.flow import drainage_breach
from worldlib.flow import reference as ref

from pipeline.timing import StepTimes as Timings

from . import mfd

SECONDS_PER_YEAR = 365.25 * 86400.0


@dataclass(frozen=True)
class Land:
    """The terrain as the stage reads it."""
    h: np.ndarray  # canonical float32 height (m), NaN on no-data cells
    kind: np.ndarray  # ref.cell_kinds: interior, edge (an outlet) or no-data
    data: np.ndarray  # bool: a finite height
    dx: float  # cell size (m)
    origin_m: tuple[float, float]
    hmin: float  # lowest height (m)

    @property
    def shape(self) -> tuple[int, int]:
        return self.h.shape

    @property
    def cell_area(self) -> float:
        return self.dx * self.dx

    @property
    def n_data(self) -> int:
        return int(self.data.sum())


def land_of(terrain: Grid) -> Land:
    """The terrain's first channel as canonical heights; no-data cells are outlets' neighbours."""
    h = ref.canonical(terrain.channel(terrain.channels[0]))
    kind = ref.cell_kinds(h)
    h[kind == ref.NODATA] = np.nan
    data = kind != ref.NODATA
    if not data.any():
        raise InputError("hydrology: the terrain has no finite height (every cell is no-data)")
    return Land(h, kind, data, float(terrain.cell_size_m), terrain.origin_m, float(np.nanmin(h)))


@dataclass(frozen=True)
class Surfaces:
    filled: np.ndarray  # pure Priority-Flood fill of the terrain (the lakes' levels)
    routing: np.ndarray  # epsilon-filled, or breached (drainage_breach) and epsilon-filled: every cell drains
    fill_stats: dict  # the fill kernel's passes and tiles


def condition(env, land: Land, depression: str, timings: Timings) -> Surfaces:
    """Step 1 on the OpenCL device `env` (the stage's ctx.cl): the filled surface, and the routing surface
    (epsilon-filled, or breached and epsilon-filled: worldlib.flow.drainage_breach)."""
    fstats: dict = {}
    with timings.lap("fill_s"):
        F = dev.fill(env, land.h, land.kind, eps=False, stats=fstats)
    with timings.lap("fill_epsilon_s"):
        R = dev.fill(env, land.h, land.kind, eps=True)
    if depression == "breach":
        # paths a tiled world takes too: the depressions' floods, the epsilon-filled surface's drainage elsewhere
        with timings.lap("breach_s"):
            paths = drainage_breach.carve_codes(land.h, F, R, dev.d8(env, R, land.kind, land.dx))
            B = drainage_breach.breach(land.h, land.kind, paths)
            R = dev.fill(env, B, land.kind, eps=True)  # the epsilon fill's steps where the carves' are finer
    return Surfaces(F, R, fstats)


@dataclass(frozen=True)
class Flow:
    code: np.ndarray  # D8 code per cell on the routing surface
    area_m2: np.ndarray  # float64 drainage area
    outlet_total: int  # cells drained at the outlets (all data cells)


def flow_directions(env, land: Land, routing: np.ndarray, timings: Timings) -> Flow:
    """Steps 2 and 3 on the OpenCL device `env`: D8 on the routing surface and its exact accumulation."""
    with timings.lap("flowdir_s"):
        code = dev.d8(env, routing, land.kind, land.dx)
    if (code == ref.PIT).any():
        raise StageError("hydrology: a cell has no downslope path after depression handling (broken invariant)")
    with timings.lap("accumulation_s"):
        counts = dev.accumulate(env, code)
    outlet_total = int(counts[land.kind == ref.EDGE].astype(np.int64).sum())
    if outlet_total != land.n_data:
        raise StageError(f"hydrology: accumulation at the outlets is {outlet_total} cells, not {land.n_data}")
    return Flow(code, counts.astype(np.float64) * land.cell_area, outlet_total)


def rain_m_per_year(land: Land, params, rain_map_mm: np.ndarray | None) -> np.ndarray:
    """Yearly rain (m/year, float64, 0 on no-data): the rain map's, or the
    uniform rain plus the orographic lapse above the lowest point."""
    if rain_map_mm is not None:
        return np.where(land.data, rain_map_mm, 0.0) / 1000.0
    rain = np.where(land.data, params.rain_mm_per_year + params.rain_lapse_mm_per_year_per_100m
                    * (np.nan_to_num(land.h, nan=land.hmin) - land.hmin) / 100.0, 0.0)
    return np.maximum(rain, 0.0) / 1000.0


def rain_from_map(path: Path, rows: int, cols: int, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Yearly rain (mm/year, float64) from an image file, stretched over the
    rows x cols terrain (cell-centred bilinear), on the cells window =
    (col0, row0, cols, rows) of it (default: all; a window's values are the
    whole map's there); clear errors for a missing, corrupt, integer,
    non-finite or negative map."""
    from worldlib.terrain.dem import read_dem, resample

    try:
        src = read_dem(path, label="rain map")
    except InputError as e:
        raise InputError(f"hydrology: {e}") from None
    if (src < 0).any():
        r, c = np.argwhere(src < 0)[0]
        raise InputError(f"hydrology: rain map {path} has negative rain ({float(src[r, c]):g} mm/year at row {r}, "
                         f"column {c})")
    return resample(src, (rows, cols), window or (0, 0, cols, rows)).astype(np.float64)


def discharge_m3_s(env, land: Land, flow: Flow, rain: np.ndarray, params, timings: Timings) -> np.ndarray:
    """Mean discharge (m^3/s): the runoff accumulated down the D8 tree on the OpenCL device `env`."""
    runoff = rain * params.runoff_coefficient
    with timings.lap("discharge_s"):
        if params.uniform_rain:
            return flow.area_m2 * (params.rain_mm_per_year / 1000.0 * params.runoff_coefficient) / SECONDS_PER_YEAR
        q, scale = dev.quantize(runoff * land.cell_area)
        return dev.accumulate(env, flow.code, q).astype(np.float64) / scale / SECONDS_PER_YEAR


def wetness_area(land: Land, surfaces: Surfaces, flow: Flow, params, timings: Timings) -> tuple[np.ndarray, float | None]:
    """The drainage area the wetness index uses: D8's, or MFD's (Quinn 1991)
    with its relative error at the outlets."""
    if params.flow != "mfd":
        return flow.area_m2, None
    with timings.lap("mfd_accumulation_s"):
        twi_area = mfd.accumulate(surfaces.routing, land.kind, land.dx, params.mfd_exponent,
                                  land.data.astype(np.float64) * land.cell_area)
    n_data, cell_area = land.n_data, land.cell_area
    error = float(abs(twi_area[land.kind == ref.EDGE].sum() - n_data * cell_area) / (n_data * cell_area))
    return twi_area, error
