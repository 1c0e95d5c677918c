"""A volume's error against its mesh, from view directions the bake never
used: the mesh rendered by worldlib/render (alpha-tested cards, n x n
samples a pixel) and the volume composited front to back (kernels.cl
composite) from the same orthographic camera, compared as

    alpha IoU   |mesh alpha >= 0.5 and volume alpha >= 0.5| / |either|
    PSNR        of premultiplied linear albedo (peak 1), over the whole view
    alpha RMSE
"""
from __future__ import annotations

import math

import numpy as np

from worldlib.render import Camera, Prepared, Scene, Settings
from worldlib.volumes.dense import VolumeLevel

# (azimuth, elevation) in degrees: between the 45-degree azimuths plants
# measures its crown from, and at elevations it does not look from; the
# first two (what the bake measures by default) are the most different:
# nearly level and steeply from above
HELD_OUT_VIEWS = ((22.5, 5.0), (292.5, 60.0), (112.5, 30.0), (202.5, 15.0))


def view_cameras(lo, hi, views=HELD_OUT_VIEWS) -> list[Camera]:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo)) * 1.02
    cams = []
    for az, el in views:
        a, e = math.radians(az), math.radians(el)
        d = np.array([math.cos(e) * math.cos(a), -math.sin(e), math.cos(e) * math.sin(a)])
        cams.append(Camera(tuple(c - d * (r + 1.0)), tuple(d), (0.0, 1.0, 0.0), ortho_height_m=2 * r))
    return cams


def compare(mesh_alpha, mesh_rgb, vol_alpha, vol_rgb) -> dict:
    m, v = mesh_alpha >= 0.5, vol_alpha >= 0.5
    union = int((m | v).sum())
    mse = float(np.mean((mesh_rgb.astype(np.float64) - vol_rgb) ** 2))
    return {"alpha_iou": float((m & v).sum() / union) if union else 1.0,
            "psnr_db": 10 * math.log10(1.0 / mse) if mse > 0 else 99.0,
            "alpha_rmse": float(np.sqrt(np.mean((mesh_alpha.astype(np.float64) - vol_alpha) ** 2)))}


def mesh_views(env, scene: Scene, cams: list[Camera], size: int, samples: int = 2):
    """The mesh from each camera, rendered on the OpenCL device `env`."""
    prepared = Prepared(env, scene)
    return [prepared.render(cam, Settings(size, size, samples=samples)) for cam in cams]


def level_views(level: VolumeLevel, cams: list[Camera], size: int, backend) -> list[tuple[np.ndarray, np.ndarray]]:
    grid = composite_grid(level)
    if hasattr(backend, "composite_views"):  # the device: the grid is sent once for every view
        return backend.composite_views([cam.frame(size, size) for cam in cams], size, size, grid, level.origin,
                                       level.voxel_m, 0.5 * level.voxel_m)
    return [backend.composite(cam.frame(size, size), size, size, grid, level.origin, level.voxel_m, 0.5 * level.voxel_m)
            for cam in cams]


def composite_grid(level: VolumeLevel) -> np.ndarray:
    """(nz, ny, nx, 7) float32, what the compositor reads per voxel:
    premultiplied albedo, density, surface x mean normal."""
    return np.concatenate([level.albedo, level.density[..., None], level.normal * level.surface[..., None]],
                          axis=-1).astype(np.float32)


def level_errors(meshes, composites) -> dict:
    """The worst view's figures and every view's."""
    per = [compare(m.alpha, m.albedo, a, c) for m, (a, c) in zip(meshes, composites)]
    return {"alpha_iou_min": min(p["alpha_iou"] for p in per), "psnr_db_min": min(p["psnr_db"] for p in per),
            "alpha_rmse_max": max(p["alpha_rmse"] for p in per), "views": per}
