"""The numpy reference of the ground albedo kernel (ground.cl, run by
ground_device.GroundAlbedo): the same taps (ground.texel_weights), the same
detail texels, the colour sum as one BLAS product."""
from __future__ import annotations

import numpy as np

from .ground import GROUND_COLOURS, texel_weights, tile_positions


def albedo(weights: np.ndarray, x_m: np.ndarray, z_m: np.ndarray, tables: np.ndarray, texel_m: float) -> np.ndarray:
    """Linear RGB: the weights (types, rows, cols) blend each type's colour
    times its detail (looked up in its periodic table at the nearest texel;
    x_m along the columns, z_m along the rows)."""
    p = tables.shape[1]
    i = np.floor(np.asarray(x_m, np.float64).ravel() / texel_m).astype(np.int64) % p
    j = np.floor(np.asarray(z_m, np.float64).ravel() / texel_m).astype(np.int64) % p
    blend = tables[:, j][:, :, i]
    blend *= weights  # (types, rows, cols): weight times detail
    out = np.tensordot(GROUND_COLOURS.T, blend, axes=(1, 0))  # (3, rows, cols), one BLAS product
    return np.moveaxis(np.clip(out, 0.0, 1.0, out=out), 0, -1)


def tile_albedo(splat: np.ndarray, cell_m: float, origin_m: tuple[float, float], tiles: int, tile_texels: int,
                u: int, v: int, tables: np.ndarray, texel_m: float) -> np.ndarray:
    """The albedo of UDIM tile (u, v) (tile_positions), weights from
    texel_weights (bilinear between cell centres). The reference of the
    ground.cl kernel (ground_device.GroundAlbedo)."""
    x, z = tile_positions(cell_m, splat.shape[:2], tiles, tile_texels, u, v)
    w = texel_weights(splat, z / cell_m - 0.5, x / cell_m - 0.5, types_first=True)
    return albedo(w, origin_m[0] + x, origin_m[1] + z, tables, texel_m)
