"""What the stage reports of a world, whole or tiled: stats.json from the
world's counts and sums (each sum correctly rounded, so it does not depend
on how the world was split), the climate, and the network statistics."""
from __future__ import annotations

import numpy as np

from worldlib.terrain.stats import terrain_statistics

from . import rivers as rivers_mod
from .routing import SECONDS_PER_YEAR


def stats_json(shape: tuple[int, int], n_data: int, dx: float, depression_cells: int, outlet_cells: int,
               discharge_out_m3_s: float, lstats: dict, river_stats: dict, hack: dict, uinfo: dict,
               terrain_stats: dict) -> dict:
    """stats.json: what the run made, the same every bake (its timings are
    the manifest's metrics, a run record)."""
    rows, cols = shape
    cell_area = dx * dx
    stats = {
        "cells": int(rows * cols), "data_cells": n_data, "cell_size_m": dx,
        "depression_cells": int(depression_cells), "total_area_m2": float(n_data * cell_area),
        "outlet_area_m2": float(outlet_cells * cell_area), "discharge_out_m3_s": discharge_out_m3_s,
        **{f"lake_{k_}" if not k_.startswith("lake") else k_: v for k_, v in lstats.items()},
        **river_stats, **hack, **uinfo, "terrain": terrain_stats,
    }
    return {k_: (float(v) if isinstance(v, np.floating) else v) for k_, v in stats.items()}


def climate(mean_rain_m: float, params) -> dict:
    """The climate the discharge comes from (mean_rain_m: m/year over the
    cells with data, a correctly rounded sum): mean rain and runoff
    (mm/year) and the bankfull discharge per km^2 of drainage area (m^3/s)."""
    runoff_m = float(mean_rain_m * params.runoff_coefficient)
    return {"rain_mean_mm_per_year": float(mean_rain_m * 1000.0), "runoff_mm_per_year": runoff_m * 1000.0,
            "mean_discharge_per_km2_m3_s": runoff_m * 1e6 / SECONDS_PER_YEAR,
            "bankfull_discharge_per_km2_m3_s": runoff_m * 1e6 / SECONDS_PER_YEAR * params.bankfull_discharge_ratio}


def network_statistics(h: np.ndarray, filled: np.ndarray, code: np.ndarray, area_m2: np.ndarray, data: np.ndarray,
                       dx: float, params, timings) -> tuple[dict, dict]:
    """Hack's law and whether the final terrain reads as eroded land (grid
    anisotropy, depressions, Strahler, Hack, theta ...)."""
    with timings.lap("hack_s"):
        hack = rivers_mod.hack_exponent(code, area_m2, dx, params.hack_min_area_m2)
    with timings.lap("terrain_statistics_s"):
        terrain_stats = terrain_statistics(h, filled, code, area_m2, dx, params.river_threshold_m2, data)
    return hack, terrain_stats
