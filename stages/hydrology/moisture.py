"""Wetness and moisture (the stage's step 6): ln(a / tan b), open water and
the erosion stage's water presence (kernel wetness)."""
from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from worldlib.flow import device as dev

from .routing import Land


# open water moistens the ground out to this many decay lengths (exp(-8) = 3e-4) and no farther: a tile then
# needs the water within a bounded halo (water_reach_cells), not the whole world's
WATER_REACH_DECAYS = 8.0


def water_reach_cells(dx: float, decay_m: float) -> int:
    """The halo (cells) within which a cell's moistening water lies."""
    return int(np.ceil(WATER_REACH_DECAYS * decay_m / dx))


def water_proximity(open_water: np.ndarray, dx: float, decay_m: float) -> np.ndarray:
    """Moisture from open water: exp(-distance / decay_m) within
    WATER_REACH_DECAYS decay lengths of it, else 0. On a window with a halo
    of water_reach_cells, the window's inner cells get the whole world's values."""
    if not open_water.any():
        return np.zeros(open_water.shape)
    from scipy import ndimage

    dist = ndimage.distance_transform_edt(~open_water) * dx
    return np.where(dist <= WATER_REACH_DECAYS * decay_m, np.exp(-dist / decay_m), 0.0)


def erosion_moisture(ext, shape: tuple[int, int]) -> np.ndarray:
    """The erosion stage's running average of water presence, 0..1 (0 without it)."""
    if ext is None:
        return np.zeros(shape)
    M = ext.channel(ext.channels[0])
    if M.shape != shape:
        raise InputError(f"hydrology: erosion moisture is {M.shape}, the terrain {shape}")
    return clean_moisture(M)


def clean_moisture(values: np.ndarray) -> np.ndarray:
    """The erosion stage's moisture as the kernel takes it: float64, NaN 0, within 0..1."""
    return np.clip(np.nan_to_num(np.asarray(values).astype(np.float64), nan=0.0), 0.0, 1.0)


def wetness_and_moisture(env, land: Land, twi_area: np.ndarray, open_water: np.ndarray, ext, params):
    """The wetness index and moisture 0..1 per cell, on the OpenCL device `env`."""
    m_water = water_proximity(open_water, land.dx, params.moisture_water_distance_m)
    return wetness_kernel(env, land.h, land.kind, twi_area, m_water, erosion_moisture(ext, land.shape), land.dx,
                          params)


def wetness_kernel(env, h, kind, area_m2, m_water, m_ext, dx: float, params):
    """The wetness kernel on the OpenCL device `env` with the params' slope floor and wetness range."""
    return dev.wetness(env, h, kind, area_m2, m_water, m_ext, dx, params.wetness_min_slope, params.wetness_dry,
                       params.wetness_wet)
