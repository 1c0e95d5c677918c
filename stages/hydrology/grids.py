"""The stage's grids: float32 maps with NaN on no-data cells, and the preview picture."""
from __future__ import annotations

import numpy as np

from pipeline.grid import Grid
from worldlib.flow import reference as ref
from worldlib.terrain.hillshade import hillshade

from .routing import Flow, Land, Surfaces


def preview(h: Grid, lake_depth: np.ndarray, river: np.ndarray, hmin: float | None = None) -> np.ndarray:
    """Hillshade with lakes and rivers; no-data shaded as the lowest height
    (hmin: the world's, when h is a window of it)."""
    if hmin is None:
        hmin = float(np.nanmin(h.data)) if np.isfinite(h.data).any() else 0.0
    img = hillshade(Grid(np.nan_to_num(h.data, nan=hmin), h.cell_size_m)).astype(np.float32)
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
    """Every artifact but the stats, in the declaration's order."""
    arrays = grid_arrays(land.data, surfaces.filled, surfaces.routing, flow.code, flow.area_m2, discharge,
                         lakes.depth, lakes.level, lakes.lake_id, riv.mask, riv.width, riv.order, water.wet, twi,
                         moisture, water.ground)
    out = {name: Grid(a, land.dx, GRID_CHANNELS[name], land.origin_m) for name, a in arrays.items()}
    out["hydrology.water"] = usd_path
    out["hydrology.preview"] = preview(Grid(land.h, land.dx, ("height",), land.origin_m), lakes.depth,
                                       river_shown(riv.mask, water.wet, lakes.depth))
    return {name: out[name] for name in ARTIFACT_ORDER}


GRID_CHANNELS = {
    "hydrology.filled": ("height",), "hydrology.conditioned": ("height",),
    "hydrology.flow": ("flow.x", "flow.z", "flow.d8"),
    "hydrology.accumulation": ("flow.accumulation", "flow.discharge"),
    "hydrology.lakes": ("lake.depth", "lake.level", "lake.id"),
    "hydrology.rivers": ("river.mask", "river.width", "river.order"),
    "hydrology.wetness": ("wetness",), "hydrology.moisture": ("moisture",), "hydrology.ground": ("height",),
}
ARTIFACT_ORDER = (*GRID_CHANNELS, "hydrology.water", "hydrology.preview")


def river_shown(river_mask: np.ndarray, wet: np.ndarray, lake_depth: np.ndarray) -> np.ndarray:
    """The river mask's cells: the network and every cell under a river surface off the lakes."""
    return river_mask | (wet & (lake_depth <= 0))


def grid_arrays(data, filled, routing, code, area_m2, discharge, lake_depth, lake_level, lake_id, river_mask,
                river_width, river_order, wet, twi, moisture, ground) -> dict[str, np.ndarray]:
    """The stage's grids as float32 arrays (NaN on no-data cells), of a
    world or of a tile of it: cell by cell, so a tile's are the world's there."""
    def f32(a):
        return np.ascontiguousarray(np.asarray(a), dtype=np.float32)

    nan = np.float32(np.nan)
    shown = river_shown(river_mask, wet, lake_depth)
    return {
        "hydrology.filled": f32(np.where(data, filled, nan)),
        "hydrology.conditioned": f32(np.where(data, routing, nan)),
        "hydrology.flow": f32(flow_vectors(code, data)),
        "hydrology.accumulation": f32(np.stack([np.where(data, area_m2, nan), np.where(data, discharge, nan)], -1)),
        "hydrology.lakes": f32(np.stack([np.where(data, lake_depth, nan), np.where(lake_depth > 0, lake_level, nan),
                                         lake_id.astype(np.float32)], -1)),
        "hydrology.rivers": f32(np.stack([shown.astype(np.float32), np.where(river_mask, river_width, 0.0),
                                          river_order.astype(np.float32)], -1)),
        "hydrology.wetness": f32(twi),
        "hydrology.moisture": f32(moisture),
        "hydrology.ground": f32(np.where(data, ground, nan)),
    }
