"""Local attributes of the terrain (seed 003 2.4): slope, aspect, curvature,
sky view and sunlight (kernel `attributes`), altitude, and moisture (from
hydrology, else the erosion stage, else the topographic position).

Sunlight is the mean insolation relative to open flat ground:
(1 - diffuse_fraction) * direct + diffuse_fraction * sky view, where direct
= sum over sun positions of w * max(0, n . s) where the sun clears the
horizon, divided by the same sum for a flat unshadowed cell. Sun positions:
the 15th of every other month, every hour with the sun above 2 degrees, at the
world's latitude; w = 0.7^(air mass) (clear-sky beam transmittance).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

F = np.float32


def directions(nd: int) -> np.ndarray:
    """(nd, 2) unit (east, north) vectors, azimuth 2 pi d / nd clockwise from north."""
    a = 2 * np.pi * np.arange(nd) / nd
    return np.stack([np.sin(a), np.cos(a)], -1).astype(F)


def march_steps(dx: float, distance_m: float, growth: float) -> np.ndarray:
    """Horizon sample distances in cells: 1, growth, growth^2 ... up to distance_m."""
    out, s = [], 1.0
    limit = max(distance_m / dx, 1.0)
    while s <= limit + 1e-9:
        out.append(s)
        s *= growth
    return np.asarray(out, F)


def sun_table(latitude_deg: float, nd: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(sun0 (k, 4): east, up, south, weight; sun1 (k, 4): azimuth in
    direction units, tan elevation, 0, 0; 1 / (flat open direct sum))."""
    phi = math.radians(latitude_deg)
    rows0, rows1 = [], []
    denom = 0.0
    for month in range(0, 12, 2):
        day = 15 + 30.44 * month
        dec = math.radians(23.44) * math.sin(2 * math.pi * (284 + day) / 365.0)
        for hour in range(24):
            H = math.radians(15.0 * (hour + 0.5 - 12.0))
            east = -math.cos(dec) * math.sin(H)
            north = math.sin(dec) * math.cos(phi) - math.cos(dec) * math.cos(H) * math.sin(phi)
            up = math.sin(dec) * math.sin(phi) + math.cos(dec) * math.cos(H) * math.cos(phi)
            if up <= math.sin(math.radians(2.0)):
                continue
            w = 0.7 ** (1.0 / up)
            az = math.atan2(east, north) % (2 * math.pi)
            rows0.append((east, up, -north, w))
            rows1.append((az / (2 * math.pi) * nd % nd, up / math.hypot(east, north), 0.0, 0.0))
            denom += w * up
    return np.asarray(rows0, F), np.asarray(rows1, F), 1.0 / denom


def compute(height: np.ndarray, dx: float, params, backend, local=None, window=None) -> dict[str, np.ndarray]:
    """The attributes of the world `height`, or of a tile's cells: `height`
    the tile with halo_cells() around it, `window` reference.Window.of(tile,
    that halo); the tile's values are then the whole world's, bit for bit."""
    if window is not None and window.margin(height.shape) < halo_cells(dx, params):
        raise ValueError(f"vegetation attributes: a window holds {window.margin(height.shape)} cells around its "
                         f"tile, the scan reaches {halo_cells(dx, params)}")
    nd = params.horizon_directions
    kc = curvature_cells(dx, params)
    sun0, sun1, inv = sun_table(params.latitude_deg, nd)
    slope, aspect, grad, curv, sky, sun = backend.attributes(
        height, dx, kc, 1.0 / (kc * dx) ** 2, directions(nd),
        march_steps(dx, params.horizon_distance_m, params.horizon_step_growth), sun0, sun1, inv,
        params.diffuse_fraction, local=local, window=window)
    return {"slope": slope, "aspect": aspect, "grad": grad, "curvature": curv, "sky_view": sky, "sunlight": sun}


def curvature_cells(dx: float, params) -> int:
    """The Laplacian's reach in cells (curvature_scale_m)."""
    return max(1, int(round(params.curvature_scale_m / dx)))


def halo_cells(dx: float, params) -> int:
    """The cells around a tile its attributes read: the horizon scan's
    farthest sample and the next cell of its bilinear, and the Laplacian's
    reach (1500 m of 1 m cells: 1501)."""
    steps = march_steps(dx, params.horizon_distance_m, params.horizon_step_growth)
    return max(int(math.ceil(float(steps[-1]))) + 1, curvature_cells(dx, params))


def fallback_moisture(height: np.ndarray, dx: float, radius_m: float, scale_m: float) -> np.ndarray:
    """Without hydrology: 0.5 - (height - mean height within radius) / (2 scale), clipped to [0, 1]."""
    k = 2 * max(1, int(round(radius_m / dx))) + 1
    mean = ndimage.uniform_filter(height.astype(np.float64), size=k, mode="nearest")
    return np.clip(0.5 - (height - mean) / (2.0 * scale_m), 0.0, 1.0).astype(F)
