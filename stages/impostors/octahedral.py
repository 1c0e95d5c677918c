"""Octahedral and hemi-octahedral view grids: which directions a view atlas
bakes, and which three frames (with which weights) an impostor blends for
a view direction.

Directions point from the plant toward the viewer, in the plant's frame
(y up). The grid is vertex-centred, as in UE's ImpostorBaker and Amplify:
with N frames per side, frame (i, j) (column i, row j) is the direction
whose grid coordinates are (i / (N - 1), j / (N - 1)) in [0, 1]^2, so the
poles and the horizon are baked exactly and a view between frames lies in
one grid cell, split into two triangles along its anti-diagonal; the three
frames of its triangle are blended with barycentric weights.

    octahedral       the whole sphere: (x, z) / (|x| + |y| + |z|), the
                     lower hemisphere folded over the diamond's edges;
                     the centre of the grid looks down from +y.
    hemi-octahedral  the upper hemisphere only (plants on the ground are
                     never seen from below, so every frame shows them from
                     above the horizon): the diamond |x| + |z| <= 1 turned
                     by 45 degrees to fill the square; the four edges of the
                     grid are the horizon. Views from below the horizon use
                     the horizon's frames.

Grid coordinates (gx, gz) run along world x and z before the turn: column
index i grows with gx, row index j with gz.
"""
from __future__ import annotations

import numpy as np

LAYOUTS = ("hemi", "octahedral")


def _as_dirs(d) -> np.ndarray:
    d = np.asarray(d, np.float64)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(n <= 0) or not np.all(np.isfinite(n)):
        raise ValueError("view directions must be finite and non-zero")
    return d / n


def encode(directions, layout: str) -> np.ndarray:
    """Grid coordinates in [0, 1]^2 (..., 2) of unit view directions (..., 3)."""
    d = _as_dirs(directions)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    if layout == "hemi":
        y = np.maximum(y, 0.0)  # below the horizon: the horizon's frames
        s = np.abs(x) + y + np.abs(z)
        px, pz = x / s, z / s
        u, v = px + pz, px - pz
    elif layout == "octahedral":
        s = np.abs(x) + np.abs(y) + np.abs(z)
        px, pz = x / s, z / s
        below = y < 0
        fx = (1.0 - np.abs(pz)) * np.where(px >= 0, 1.0, -1.0)
        fz = (1.0 - np.abs(px)) * np.where(pz >= 0, 1.0, -1.0)
        u, v = np.where(below, fx, px), np.where(below, fz, pz)
    else:
        raise ValueError(f"unknown layout {layout!r}; one of {LAYOUTS}")
    return np.clip(np.stack([u, v], -1) * 0.5 + 0.5, 0.0, 1.0)


def decode(grid, layout: str) -> np.ndarray:
    """Unit view directions (..., 3) of grid coordinates (..., 2) in [0, 1]^2."""
    g = np.asarray(grid, np.float64) * 2.0 - 1.0
    u, v = g[..., 0], g[..., 1]
    if layout == "hemi":
        px, pz = 0.5 * (u + v), 0.5 * (u - v)
        y = 1.0 - np.abs(px) - np.abs(pz)
    elif layout == "octahedral":
        y = 1.0 - np.abs(u) - np.abs(v)
        below = y < 0
        px = np.where(below, (1.0 - np.abs(v)) * np.where(u >= 0, 1.0, -1.0), u)
        pz = np.where(below, (1.0 - np.abs(u)) * np.where(v >= 0, 1.0, -1.0), v)
    else:
        raise ValueError(f"unknown layout {layout!r}; one of {LAYOUTS}")
    d = np.stack([px, y, pz], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def frame_directions(frames: int, layout: str) -> np.ndarray:
    """(frames, frames, 3): the view direction of frame (row j, column i)."""
    t = np.arange(frames) / (frames - 1)
    gx, gz = np.meshgrid(t, t)  # [j, i]
    return decode(np.stack([gx, gz], -1), layout)


def frame_basis(direction) -> tuple[np.ndarray, np.ndarray]:
    """(right, up) of the orthographic camera that looks along -direction:
    up is world +y made orthogonal to the direction; looking straight down
    or up, up is -z (right is then +x from above)."""
    d = _as_dirs(direction)
    world_up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), d.shape)
    up = world_up - (d * world_up).sum(-1, keepdims=True) * d
    n = np.linalg.norm(up, axis=-1, keepdims=True)
    polar = n[..., 0] < 1e-6
    up = np.where(polar[..., None], np.array([0.0, 0.0, -1.0]), up / np.maximum(n, 1e-300))
    right = np.cross(-d, up)  # the camera looks along -d
    return right / np.linalg.norm(right, axis=-1, keepdims=True), up


def select_frames(directions, frames: int, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """For each view direction (..., 3): the three frames of the grid
    triangle it falls in, as (..., 3, 2) integer (column i, row j), and their
    barycentric weights (..., 3), which sum to 1 and are each >= 0."""
    g = encode(directions, layout) * (frames - 1)
    cell = np.minimum(np.floor(g), frames - 2).astype(np.int64)
    f = g - cell
    fx, fz = f[..., 0], f[..., 1]
    lower = fx + fz <= 1.0
    i0, j0 = cell[..., 0], cell[..., 1]
    # lower triangle: (i, j), (i+1, j), (i, j+1); upper: (i+1, j+1), (i+1, j), (i, j+1)
    corner = np.stack([np.where(lower, i0, i0 + 1), np.where(lower, j0, j0 + 1)], -1)
    a = np.stack([i0 + 1, j0], -1)
    b = np.stack([i0, j0 + 1], -1)
    idx = np.stack([corner, a, b], -2)
    w = np.where(lower[..., None],
                 np.stack([1.0 - fx - fz, fx, fz], -1),
                 np.stack([fx + fz - 1.0, 1.0 - fz, 1.0 - fx], -1))
    return idx, np.clip(w, 0.0, 1.0)


def view_direction(azimuth_deg, elevation_deg) -> np.ndarray:
    """Unit direction toward a viewer at an azimuth (from +x toward +z) and
    an elevation above the horizon, degrees."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.stack(np.broadcast_arrays(np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)), -1)
