"""The bake's held-out measurements (heldout.py's views and comparison):
the mesh's reference views, rendered once per plant; the impostors seen
from the same directions (the atlas through the sampler, the slices
blended as seed 002's shader does and all at once as a USD viewer draws
them); the silhouette error in metres that sets the switch distances."""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from worldlib.render import Prepared, Settings

from . import heldout, octahedral, sampler, slices

# an impostor seen from a direction: direction -> (premultiplied rgba (size, size, 4), depth in m (size, size))
View = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class References:
    """The mesh's held-out views, rendered once and compared with every
    impostor of the plant (the atlas, the slices)."""

    def __init__(self, prepared: Prepared, ps, views: list[tuple[float, float]], size: int, samples: int):
        self.views, self.size = views, size
        self.images = []
        for az, el in views:
            m = heldout.mesh_view(prepared, octahedral.view_direction(az, el), ps.centre, ps.radius, size, samples)
            self.images.append((np.concatenate([m.albedo, m.alpha[..., None]], -1), m.depth))

    def measure(self, impostor: View) -> list:
        """Held-out errors of an impostor: `impostor(direction)` -> (rgba, depth)."""
        errors = []
        for (az, el), (mesh_rgba, mesh_depth) in zip(self.views, self.images):
            rgba, depth = impostor(octahedral.view_direction(az, el))
            errors.append(heldout.ViewError(az, el, *heldout.compare(mesh_rgba, mesh_depth, rgba, depth)))
        return errors


def atlas_view(at, size: int, depth_steps: int) -> View:
    """The view atlas `at` as the sampler draws it (depth-aware blend of depth_steps steps)."""
    def view(d):
        v = sampler.render_view(at, d, size, depth_steps)
        return v.rgba, v.depth
    return view


def blended_slices_view(billboards: dict, grass: bool, ps, size: int, settings: Settings) -> View:
    """The slice billboards blended: a grass tuft's quads together (seed 001,
    billboards[None]), a tree's two slicings nearest the view by
    slices.slicing_weights (seed 002 / Jakulin, billboards[row])."""
    def view(d):
        cam, _ = heldout.view_camera(d, ps.centre, ps.radius)
        blend = [(None, 1.0)] if grass else slices.slicing_weights(d)
        rgba = np.zeros((size, size, 4))
        depth = np.zeros((size, size))
        for row, w in blend:
            img = billboards[row].render(cam, settings)
            rgba += w * np.concatenate([img.albedo, img.alpha[..., None]], -1)
            depth += w * img.alpha * np.where(np.isfinite(img.depth), img.depth, 0.0)
        return rgba, np.where(rgba[..., 3] > 0, depth / np.maximum(rgba[..., 3], 1e-12), np.inf)
    return view


def drawn_view(drawn: Prepared, ps, settings: Settings) -> View:
    """Every quad of `drawn` at once, alpha-tested and nearest first: what a USD viewer draws."""
    def view(d):
        cam, _ = heldout.view_camera(d, ps.centre, ps.radius)
        img = drawn.render(cam, settings)
        return np.concatenate([img.albedo, img.alpha[..., None]], -1), img.depth
    return view


def silhouette_error_m(summary: dict, ps, size: int) -> float:
    """The median silhouette displacement of a held-out set, in metres: the
    mismatched share of the view (1 - IoU) over the plant's outline, taken as
    the outline of its bounding sphere's projection (a disc of the view's
    pixels), times the pixel size."""
    pixel_m = 2.0 * ps.radius / size
    disc_area_px = math.pi * (0.5 * size) ** 2
    disc_perimeter_px = math.pi * size
    mismatch_px = (1.0 - summary["alpha_iou"]["median"]) * disc_area_px * 0.5
    return mismatch_px / disc_perimeter_px * pixel_m
