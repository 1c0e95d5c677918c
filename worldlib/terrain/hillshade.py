"""Previews for people: hillshade and colour ramps as 8-bit RGB arrays."""
from __future__ import annotations

import numpy as np

from pipeline.grid import Grid


def hillshade(height: Grid, azimuth_deg: float = 315.0, altitude_deg: float = 45.0, z_factor: float = 1.0) -> np.ndarray:
    """Lambertian hillshade of a height grid (the usual GIS definition, sun from
    the north-west at 45 degrees), as uint8 RGB of the grid's shape. Slopes are
    computed in metres, so the shading does not change with resolution."""
    h = height.channel(height.channels[0]).astype(np.float32) * np.float32(z_factor)
    dx = height.cell_size_m
    dz_dx = np.gradient(h, dx, axis=1) if h.shape[1] > 1 else np.zeros_like(h)
    dz_dy = -np.gradient(h, dx, axis=0) if h.shape[0] > 1 else np.zeros_like(h)  # row 0 is north
    az = np.radians(azimuth_deg)
    alt = np.radians(altitude_deg)
    sun = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)], dtype=np.float32)  # east, north, up
    n = np.stack([-dz_dx, -dz_dy, np.ones_like(h)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    # the dot product per cell, not a BLAS product: a window's cells get the whole grid's bits
    shade = np.clip(n[..., 0] * sun[0] + n[..., 1] * sun[1] + n[..., 2] * sun[2], 0.0, 1.0)
    grey = (shade * 255.0 + 0.5).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)
