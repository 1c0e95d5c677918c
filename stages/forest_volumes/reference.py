"""The sector splat (kernels.cl `splat`) in plain numpy, for small forests:
the same float64 deposits, rounded to the same fixed point, so the tests
compare the two closely (splat.py says what a splat is)."""
from __future__ import annotations

import numpy as np

from worldlib.volumes.dense import VolumeLevel

from .splat import CHANNELS, FIXED, source_voxels


def splat(shape_xyz, origin, voxel: float, source: VolumeLevel, pos, rot, scale, acc: np.ndarray) -> None:
    """Add the deposits into acc ((8, voxels) int64 fixed point), in numpy
    (small scenes: tests)."""
    nx, ny, nz = shape_xyz
    centres, held = source_voxels(source)
    if len(centres) == 0 or len(pos) == 0:
        return
    S = np.asarray(scale, np.float64)
    R = np.asarray(rot, np.float64).reshape(-1, 3, 3)
    rc = ((R[:, None, :, 0] * centres[None, :, None, 0] + R[:, None, :, 1] * centres[None, :, None, 1])
          + R[:, None, :, 2] * centres[None, :, None, 2])  # (n, v, 3)
    u = (np.asarray(pos, np.float64)[:, None, :] + S[:, None, None] * rc - np.asarray(origin, np.float64)) / voxel
    r = np.minimum(0.5 * S * source.voxel_m / voxel, 0.5)[:, None, None]
    lo = np.floor(u - r)
    f = np.maximum(u + r - (lo + 1.0), 0.0) / (2.0 * r)
    i0 = lo.astype(np.int64)
    k = (S * S * ((source.voxel_m / voxel) ** 3))[:, None]
    val = np.empty(u.shape[:2] + (CHANNELS,))
    val[..., 0] = k * held[None, :, 0]
    for c in (1, 2, 3, 4):
        val[..., c] = k * held[None, :, c]
    hn = held[None, :, 5:8]
    for a in range(3):
        val[..., 5 + a] = val[..., 4] * ((R[:, None, a, 0] * hn[..., 0] + R[:, None, a, 1] * hn[..., 1])
                                         + R[:, None, a, 2] * hn[..., 2])
    for dk in (0, 1):
        for dj in (0, 1):
            for di in (0, 1):
                x, y, z = i0[..., 0] + di, i0[..., 1] + dj, i0[..., 2] + dk
                w = (((f[..., 0] if di else 1.0 - f[..., 0]) * (f[..., 1] if dj else 1.0 - f[..., 1]))
                     * (f[..., 2] if dk else 1.0 - f[..., 2]))
                ok = (x >= 0) & (y >= 0) & (z >= 0) & (x < nx) & (y < ny) & (z < nz) & (w > 0)
                at = ((z * ny + y) * nx + x)[ok]
                for c in range(CHANNELS):
                    np.add.at(acc[c], at, np.rint(w[ok] * val[..., c][ok] * FIXED).astype(np.int64))
