"""The impostor as a real-time shader draws it, in numpy: a view of the
plant synthesised from its atlas (the reference for engines' shaders, and
what the held-out error measures).

For each pixel of an orthographic view looking along -v (v the direction
toward the viewer), the three frames of v's grid triangle
(octahedral.select_frames) are sampled and blended with their barycentric
weights, premultiplied colour and alpha alike (no dark fringes). Each frame
is sampled where the pixel's ray meets the frame's plane through the
bounding sphere's centre (the "virtual plane" projection of UE's and
Amplify's octahedral impostors), then, depth-aware, where the ray meets the
surface the frame's depth describes: a fixed-point search along the ray,
t <- (h0 - z(t)) / (v . d), that moves the sample by the parallax between
the frame's direction d and the view (Amplify's parallax option does one
step; `depth_steps` sets how many).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import atlas as atlas_mod
from . import octahedral


@dataclass
class View:
    rgba: np.ndarray  # (h, w, 4) premultiplied colour and alpha
    normal: np.ndarray  # (h, w, 3)
    depth: np.ndarray  # (h, w) distance from the eye plane along the view (inf where alpha is 0)


def ortho_rays(direction, centre, radius: float, size: int):
    """Pixel ray origins (size, size, 3) on the eye plane of an orthographic
    camera looking along -direction at the sphere (centre, radius), the
    same framing as the atlas's frames; and that camera's eye distance."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    right, up = octahedral.frame_basis(d)
    back = radius * 1.05 + 0.01
    s = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(s, -s)
    o = centre + d * back + radius * (x[..., None] * right + y[..., None] * up)
    return o, back


def mip_lod(frame_px: int, size: int, frame_levels: int) -> float:
    """The level of detail a GPU's trilinear filter uses when a frame of
    frame_px texels covers a view of size pixels (log2 of texels per pixel,
    clamped to the per-frame levels: later levels mix frames)."""
    return float(np.clip(np.log2(frame_px / size), 0.0, frame_levels - 1))


def render_view(at: "atlas_mod.Atlas", direction, size: int, depth_steps: int = 2, lod: float | None = None) -> View:
    """The impostor seen from `direction` in a size x size orthographic view
    framed like the atlas's frames (the held-out camera), filtered as a GPU
    does: trilinear between the two per-frame mip levels around lod (None:
    mip_lod for this view size, so a 512-texel frame seen in 64 pixels reads
    level 3, not level 0 point-sampled)."""
    v = np.asarray(direction, np.float64)
    v = v / np.linalg.norm(v)
    if lod is None:
        lod = mip_lod(at.frame_px, size, at.frame_levels)
    lo = int(np.floor(lod))
    frac = lod - lo
    rgba, normal, depth_sum = _blend(at, v, size, depth_steps, lo)
    if frac > 1e-6:
        upper = _blend(at, v, size, depth_steps, lo + 1)
        rgba, normal, depth_sum = ((1.0 - frac) * a + frac * b for a, b in zip((rgba, normal, depth_sum), upper))
    a = rgba[..., 3]
    depth = np.where(a > 0, depth_sum / np.maximum(a, 1e-12), np.inf)
    n = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-9)
    return View(rgba.astype(np.float32), n.astype(np.float32), depth.astype(np.float32))


def _blend(at: "atlas_mod.Atlas", v: np.ndarray, size: int, depth_steps: int, level: int):
    """The 3-frame blend at one mip level: premultiplied colour and alpha,
    alpha-weighted normal, alpha-weighted depth (sums, not yet divided)."""
    origins, _ = ortho_rays(v, at.centre, at.radius, size)
    idx, w = octahedral.select_frames(v, at.frames, at.layout)
    f = at.frame_px >> level
    img = at.levels[level]
    scale = f / (2.0 * at.radius)
    rgba = np.zeros((size, size, 4))
    normal = np.zeros((size, size, 3))
    depth_sum = np.zeros((size, size))
    rel = origins - at.centre
    for k in range(3):
        if w[k] <= 0.0:
            continue
        i, j = int(idx[k, 0]), int(idx[k, 1])
        d = at.directions[j, i]
        right, up = octahedral.frame_basis(d)
        cos = float(np.dot(v, d))
        if cos <= 1e-3:
            continue
        h0 = rel @ d  # height of each ray origin above the frame's plane
        t = h0 / cos  # where the ray meets the plane
        for _ in range(depth_steps + 1):
            q = rel - t[..., None] * v
            x = (q @ right + at.radius) * scale - 0.5
            y = (at.radius - q @ up) * scale - 0.5
            s = atlas_mod.sample_frame(img, f, i, j, x, y)
            if depth_steps == 0:
                break
            t = (h0 - s[..., 7]) / cos
        rgba += w[k] * s[..., 0:4]
        normal += w[k] * s[..., 3:4] * s[..., 4:7]
        depth_sum += w[k] * s[..., 3] * t
    return rgba, normal, depth_sum
