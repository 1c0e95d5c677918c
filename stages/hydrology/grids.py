"""The stage's grids: float32 maps with NaN on no-data cells, and the preview picture."""
from __future__ import annotations

import numpy as np

from pipeline.grid import Grid
from worldlib.flow import reference as ref
from worldlib.terrain.hillshade import hillshade

from .routing import Flow, Land, Surfaces


def preview(h: Grid, lake_depth: np.ndarray, river: np.ndarray) -> np.ndarray:
    img = hillshade(Grid(np.nan_to_num(h.data, nan=float(np.nanmin(h.data)) if np.isfinite(h.data).any() else 0.0),
                         h.cell_size_m)).astype(np.float32)
    water = np.array([40, 90, 160], np.float32)
    lake = (lake_depth > 0)[..., None]
    img = np.where(lake, 0.3 * img + 0.7 * water, img)
    img = np.where(river[..., None], 0.2 * img + 0.8 * np.array([30, 110, 220], np.float32), img)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def flow_vectors(code: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Unit flow vector (x east, z south) and the D8 code per cell, NaN on no-data."""
    k = np.clip(code, 0, 7)
    fx = np.where(code >= 0, ref.DC[k], 0).astype(np.float32)
    fz = np.where(code >= 0, ref.DR[k], 0).astype(np.float32)
    norm = np.maximum(np.hypot(fx, fz), 1)
    flow = np.stack([fx / norm, fz / norm, code.astype(np.float32)], axis=-1)
    flow[~data] = np.float32(np.nan)
    return flow


def output_grids(land: Land, surfaces: Surfaces, flow: Flow, discharge: np.ndarray, lakes, riv, twi: np.ndarray,
                 moisture: np.ndarray, usd_path, water) -> dict:
    """Every artifact but the stats, in the declaration's order; the river
    mask holds the network and every cell under a river surface (water.wet)."""
    def grid(a, channels):
        return Grid(np.ascontiguousarray(np.asarray(a), dtype=np.float32), land.dx, channels, land.origin_m)

    nan = np.float32(np.nan)
    data, lake_depth = land.data, lakes.depth
    depth32 = np.where(data, lake_depth, nan)
    lakes_grid = np.stack([depth32, np.where(lake_depth > 0, lakes.level, nan), lakes.lake_id.astype(np.float32)], -1)
    wet = riv.mask | (water.wet & (lake_depth <= 0))
    rivers_grid = np.stack([wet.astype(np.float32), np.where(riv.mask, riv.width, 0.0), riv.order.astype(np.float32)], -1)
    acc_grid = np.stack([np.where(data, flow.area_m2, nan), np.where(data, discharge, nan)], -1)
    return {
        "hydrology.filled": grid(np.where(data, surfaces.filled, nan), ("height",)),
        "hydrology.conditioned": grid(np.where(data, surfaces.routing, nan), ("height",)),
        "hydrology.flow": grid(flow_vectors(flow.code, data), ("flow.x", "flow.z", "flow.d8")),
        "hydrology.accumulation": grid(acc_grid, ("flow.accumulation", "flow.discharge")),
        "hydrology.lakes": grid(lakes_grid, ("lake.depth", "lake.level", "lake.id")),
        "hydrology.rivers": grid(rivers_grid, ("river.mask", "river.width", "river.order")),
        "hydrology.wetness": grid(twi, ("wetness",)),
        "hydrology.moisture": grid(moisture, ("moisture",)),
        "hydrology.ground": grid(np.where(data, water.ground, nan), ("height",)),
        "hydrology.water": usd_path,
        "hydrology.preview": preview(grid(land.h, ("height",)), lake_depth, wet),
    }
