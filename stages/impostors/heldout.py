"""The impostor's error against the mesh from view directions the bake did
not use (no impostor tool publishes this; we do).

For each held-out direction, the mesh (worldlib.render) and the impostor
(sampler.py, or a slice billboard set rendered as geometry) are seen by the
same orthographic camera, framed on the plant's bounding sphere:
    PSNR      of the premultiplied colour (peak 1) over the union of the two
              alpha masks (alpha >= 0.5 in either);
    IoU       of the alpha masks at 0.5;
    depth     RMSE (m) over the pixels both cover.
Directions: azimuth every 5 degrees, elevation 0 to 80 every 10 degrees
(hemi) or -80 to 80 (octahedral): 72 x 9 = 648 views for hemi. The bake
measures a stratified share of that set (lattice): 1/stride of the
azimuths at every elevation, shifted by 4 azimuth steps from one elevation
to the next (stride 9 on hemi: each of the 72 azimuths once, 8 per
elevation; stride 18: 4 per elevation, 36 views); bench/impostors.py
--agreement measures the whole set beside it. A direction within half a degree of a
baked frame is not held out and is skipped.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worldlib.render import Camera, Image, Prepared, Settings

from . import octahedral


@dataclass(frozen=True)
class ViewError:
    azimuth_deg: float
    elevation_deg: float
    psnr_db: float
    iou: float
    depth_rmse_m: float


def directions(layout: str, azimuth_step_deg: float = 5.0, elevation_step_deg: float = 10.0,
               subsample: int = 1, offset: int = 0) -> list[tuple[float, float]]:
    azimuths = np.arange(0.0, 360.0, azimuth_step_deg)[offset % subsample::subsample]
    top = 80.0
    bottom = 0.0 if layout == "hemi" else -80.0
    elevations = np.arange(bottom, top + 1e-9, elevation_step_deg)
    return [(float(a), float(e)) for e in elevations for a in azimuths]


def lattice(layout: str, stride: int = 1) -> list[tuple[float, float]]:
    """The 5-degree set's views (azimuth index i, elevation index e) with
    (i + 4 e) mod stride = 0: every elevation's azimuths every stride-th,
    shifted by 4 steps per elevation (so the elevations see different
    azimuths; with a stride of 9, prime to 4, every azimuth once)."""
    full = directions(layout)
    azimuths = sorted({a for a, _ in full})
    elevations = sorted({e for _, e in full})
    return [(a, e) for e in elevations for a in azimuths
            if (azimuths.index(a) + 4 * elevations.index(e)) % stride == 0]


def held_out(views: list[tuple[float, float]], frame_dirs: np.ndarray | None) -> list[tuple[float, float]]:
    """The views not within half a degree of a baked direction."""
    if frame_dirs is None:
        return views
    fd = frame_dirs.reshape(-1, 3)
    keep = []
    for a, e in views:
        d = octahedral.view_direction(a, e)
        if np.degrees(np.arccos(np.clip((fd @ d).max(), -1, 1))) > 0.5:
            keep.append((a, e))
    return keep


def view_camera(direction: np.ndarray, centre: np.ndarray, radius: float) -> tuple[Camera, float]:
    right, up = octahedral.frame_basis(direction)
    back = radius * 1.05 + 0.01
    return Camera(tuple(centre + direction * back), tuple(-direction), tuple(up), ortho_height_m=2.0 * radius), back


def compare(mesh_rgba: np.ndarray, mesh_depth: np.ndarray, imp_rgba: np.ndarray, imp_depth: np.ndarray) -> tuple[float, float, float]:
    """(PSNR dB, alpha IoU at 0.5, depth RMSE m) of one view."""
    ma, ia = mesh_rgba[..., 3] >= 0.5, imp_rgba[..., 3] >= 0.5
    union = ma | ia
    inter = ma & ia
    iou = float(inter.sum() / union.sum()) if union.any() else 1.0
    if union.any():
        mse = float(np.mean((mesh_rgba[union, :3].astype(np.float64) - imp_rgba[union, :3]) ** 2))
        psnr = 10.0 * math.log10(1.0 / max(mse, 1e-12))
    else:
        psnr = 120.0
    both = inter & np.isfinite(mesh_depth) & np.isfinite(imp_depth)
    rmse = float(np.sqrt(np.mean((mesh_depth[both].astype(np.float64) - imp_depth[both]) ** 2))) if both.any() else 0.0
    return psnr, iou, rmse


def mesh_view(prepared: Prepared, direction, centre, radius: float, size: int, samples: int) -> Image:
    cam, _ = view_camera(np.asarray(direction, np.float64), np.asarray(centre, np.float64), radius)
    return prepared.render(cam, Settings(size, size, samples=samples))


def summarize(errors: list[ViewError], plant_height_m: float) -> dict:
    """Median, mean and worst of each measure, and the worst view (lowest IoU)."""
    if not errors:
        return {"views": 0}
    psnr = np.array([e.psnr_db for e in errors])
    iou = np.array([e.iou for e in errors])
    rmse = np.array([e.depth_rmse_m for e in errors])
    worst = min(errors, key=lambda e: (e.iou, e.psnr_db))
    return {
        "views": len(errors),
        "psnr_db": {"median": float(np.median(psnr)), "mean": float(psnr.mean()), "min": float(psnr.min())},
        "alpha_iou": {"median": float(np.median(iou)), "mean": float(iou.mean()), "min": float(iou.min())},
        "depth_rmse_m": {"median": float(np.median(rmse)), "max": float(rmse.max()),
                         "median_fraction_of_height": float(np.median(rmse) / max(plant_height_m, 1e-9))},
        "worst_view": {"azimuth_deg": worst.azimuth_deg, "elevation_deg": worst.elevation_deg,
                       "psnr_db": worst.psnr_db, "alpha_iou": worst.iou, "depth_rmse_m": worst.depth_rmse_m},
    }
