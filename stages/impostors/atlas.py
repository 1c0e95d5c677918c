"""The view atlas of a plant: N x N orthographic frames rendered with
worldlib.render, one per direction of the (hemi-)octahedral grid
(octahedral.py), each looking at the plant's bounding sphere (centre c,
radius R) so every frame holds the whole plant at the same scale.

Per frame, F x F texels (F = frame_px), channels:
    albedo RGB  premultiplied linear albedo (the renderer's), A its coverage;
    normal XYZ  the plant-frame (object space) shading normal;
    depth Z     metres from the frame's plane through c toward the viewer
                (a point p of the plant: (p - c) . d), so a view between
                frames can be reprojected (sampler.py);
    ao Y        ambient occlusion (share of open hemisphere).
Padding: in every texel that nothing covers (alpha = 0), normal, depth and
ao hold the values of the nearest covered texel of the same frame (never
another frame's), so filtering at a silhouette reads plausible data; the
straight albedo of the PNG copy is padded the same way (no dark halos
when it is alpha-tested). Premultiplied colour is 0 there by definition.

Mip levels are built per frame: each level halves every frame on its own
(2 x 2 boxes of one frame only), as long as the frame's side stays an
integer; frames are F = m 2^L texels so that L + 1 levels are per frame,
and the atlas is padded to a power of two so a GPU's level l is exactly
the per-frame level l. Levels past L (a few texels per frame) box-filter
the whole atlas, as any mip chain does, and the header says from which
level that happens. Frame (column i, row j) occupies columns [i F, (i+1) F)
and rows [j F, (j+1) F) from the top.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worldlib.render import Camera, Prepared, Settings

from . import octahedral

CHANNELS = ("albedo.R", "albedo.G", "albedo.B", "albedo.A", "normal.X", "normal.Y", "normal.Z", "depth.Z", "ao.Y")
COLOUR = slice(0, 4)
PADDED = slice(4, 9)  # the channels padding fills into alpha = 0 texels


def frame_layout(atlas_px: int, frames: int, min_frame_mip_px: int = 4) -> tuple[int, int]:
    """(frame_px, per-frame mip levels): the largest F = m 2^L <= atlas_px //
    frames whose halvings stay integers down to about min_frame_mip_px."""
    f0 = atlas_px // frames
    if f0 < 1:
        raise ValueError(f"{frames} frames do not fit in {atlas_px} texels")
    halvings = max(0, int(math.floor(math.log2(max(f0 / min_frame_mip_px, 1.0)))))
    step = 2 ** halvings
    return (f0 // step) * step, halvings + 1


def frame_size(target_px: float, frames: int, atlas_px: int, min_frame_px: int = 4) -> int:
    """The smallest frame side of the form 2^k or 3 2^k (sides whose halvings
    stay integers, so the per-frame mip levels stay inside the frames) that
    is at least target_px and min_frame_px; at most the frame that
    frame_layout(atlas_px, frames) gives."""
    largest = frame_layout(atlas_px, frames)[0]
    need = max(float(target_px), float(min_frame_px))
    sizes = sorted({m << k for m in (1, 3) for k in range(2, 16) if 4 <= (m << k) <= largest})
    return next((s for s in sizes if s >= need), largest)


def atlas_side(frames: int, frame_px: int) -> int:
    """The power-of-two atlas side that holds frames x frames frames of frame_px."""
    return 1 << max(0, math.ceil(math.log2(frames * frame_px)))


@dataclass
class Atlas:
    layout: str
    frames: int
    frame_px: int
    atlas_px: int
    centre: np.ndarray
    radius: float
    levels: list[np.ndarray]  # per level (side, side, 9) float32, CHANNELS
    frame_levels: int  # levels 0 .. frame_levels-1 are per frame
    straight_rgb: np.ndarray  # (atlas_px, atlas_px, 3) straight linear albedo, padded (the PNG copy)
    directions: np.ndarray  # (frames, frames, 3) [row j, column i]

    def frame_alpha(self) -> np.ndarray:
        """(frames * frames, F, F) level-0 coverage of every frame."""
        return _frames_view(self.levels[0], self.frames, self.frame_px)[..., 3]

    def frame(self, i: int, j: int, level: int = 0) -> np.ndarray:
        f = self.frame_px >> level
        return self.levels[level][j * f:(j + 1) * f, i * f:(i + 1) * f]


def frame_camera(direction: np.ndarray, centre: np.ndarray, radius: float) -> tuple[Camera, float]:
    """The orthographic camera of a frame and the distance from the eye plane
    to the frame's plane through the centre."""
    right, up = octahedral.frame_basis(direction)
    back = radius * 1.05 + 0.01
    eye = centre + direction * back
    return Camera(tuple(eye), tuple(-direction), tuple(up), ortho_height_m=2.0 * radius), back


def render_frames(prepared: Prepared, centre: np.ndarray, radius: float, frames: int, frame_px: int, layout: str,
                  samples: int, ao_rays: int, seed: int, progress=None,
                  ao_radius: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """(frames F, frames F, 9) level-0 texels before padding, and the directions."""
    dirs = octahedral.frame_directions(frames, layout)
    side = frames * frame_px
    out = np.zeros((side, side, len(CHANNELS)), np.float32)
    settings = Settings(frame_px, frame_px, samples=samples, ao_rays=ao_rays, ao_radius_m=ao_radius * radius,
                        seed=seed & 0xFFFFFFFF)
    for j in range(frames):
        if progress is not None:
            progress(j / frames)
        for i in range(frames):
            cam, back = frame_camera(dirs[j, i], centre, radius)
            img = prepared.render(cam, settings)
            t = out[j * frame_px:(j + 1) * frame_px, i * frame_px:(i + 1) * frame_px]
            t[..., 0:3] = img.albedo
            t[..., 3] = img.alpha
            t[..., 4:7] = img.normal
            t[..., 7] = np.where(np.isfinite(img.depth), back - img.depth, 0.0)
            t[..., 8] = img.ao
    return out, dirs


def _frames_view(img: np.ndarray, frames: int, f: int) -> np.ndarray:
    """(frames*frames, f, f, c) view of the top-left frames x frames grid."""
    c = img.shape[-1]
    return img[:frames * f, :frames * f].reshape(frames, f, frames, f, c).transpose(0, 2, 1, 3, 4).reshape(-1, f, f, c)


def _from_frames(tiles: np.ndarray, frames: int) -> np.ndarray:
    n, f, _, c = tiles.shape
    return tiles.reshape(frames, frames, f, f, c).transpose(0, 2, 1, 3, 4).reshape(frames * f, frames * f, c)


def pad_frames(tiles: np.ndarray, values: np.ndarray, padding_px: int) -> np.ndarray:
    """Fill every alpha = 0 texel of each frame (tiles: (n, f, f) alpha;
    values: (n, f, f, c)) with the value of the nearest covered texel of the
    same frame within padding_px, and beyond that with the frame's mean
    covered value. A frame nothing covers keeps its values."""
    from scipy import ndimage

    empty = tiles <= 0.0
    out = values.copy()
    # one distance transform over the stack; frames are a million texels apart
    dist, idx = ndimage.distance_transform_edt(empty, sampling=(1e6, 1.0, 1.0), return_indices=True)
    same = idx[0] == np.arange(len(tiles))[:, None, None]
    near = empty & same & (dist <= padding_px)
    out[near] = values[idx[0][near], idx[1][near], idx[2][near]]
    covered = ~empty
    counts = covered.sum((1, 2))
    means = np.where(counts[:, None] > 0, (values * covered[..., None]).sum((1, 2)) / np.maximum(counts, 1)[:, None], 0.0)
    far = empty & ~near & (counts[:, None, None] > 0)
    out[far] = np.broadcast_to(means[:, None, None, :], values.shape)[far]
    return out


def _halve(tiles: np.ndarray) -> np.ndarray:
    """One mip level per frame: premultiplied colour and alpha as 2 x 2 box
    means; normal, depth and ao alpha-weighted (plain means where the box is
    uncovered, i.e. the padding)."""
    n, f, _, c = tiles.shape
    h = f // 2
    b = tiles[:, :2 * h, :2 * h].reshape(n, h, 2, h, 2, c)
    out = np.empty((n, h, h, c), np.float32)
    out[..., COLOUR] = b[..., COLOUR].mean((2, 4))
    a = b[..., 3:4]
    wsum = a.sum((2, 4))
    weighted = (b[..., PADDED] * a).sum((2, 4)) / np.maximum(wsum, 1e-12)
    plain = b[..., PADDED].mean((2, 4))
    out[..., PADDED] = np.where(wsum > 0, weighted, plain)
    nrm = out[..., 4:7]
    out[..., 4:7] = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-6)
    return out


def mip_chain(tiles: np.ndarray, frames: int, atlas_px: int, frame_levels: int) -> list[np.ndarray]:
    """Every mip level of the atlas from its padded level-0 frames (n, F, F,
    9): levels below frame_levels halve each frame on its own, the rest the
    whole atlas. Atlas texels outside the frames are transparent."""
    levels = []
    level_tiles = tiles
    for level in range(int(math.log2(atlas_px)) + 1):
        side = atlas_px >> level
        if level < frame_levels:
            img = np.zeros((side, side, len(CHANNELS)), np.float32)
            img[..., 6] = 1.0  # unused atlas texels: transparent, normal +z, depth 0, open
            img[..., 8] = 1.0
            used = _from_frames(level_tiles, frames)
            img[:used.shape[0], :used.shape[1]] = used
            if level + 1 < frame_levels:
                level_tiles = _halve(level_tiles)
        else:  # a few texels per frame: the whole atlas box-filtered
            img = _halve(levels[-1][None, :2 * side, :2 * side])[0]
        levels.append(img.astype(np.float32))
    return levels


def build(prepared: Prepared, centre: np.ndarray, radius: float, frames: int, atlas_px: int, layout: str,
          samples: int, ao_rays: int, padding_px: int, seed: int, progress=None, ao_radius: float = 0.08,
          frame_px: int | None = None) -> Atlas:
    """The atlas of frames x frames frames: the largest that fit atlas_px
    (frame_layout), or frames of frame_px texels in the smallest power-of-two
    atlas that holds them (atlas_side; frame_size picks such sizes)."""
    if frame_px is None:
        frame_px, frame_levels = frame_layout(atlas_px, frames)
    else:
        frame_levels = frame_layout(frame_px, 1)[1]
        if frame_layout(frame_px, 1)[0] != frame_px:
            raise ValueError(f"frame_px = {frame_px} does not halve to integers (use frame_size)")
        atlas_px = atlas_side(frames, frame_px)
    raw, dirs = render_frames(prepared, centre, radius, frames, frame_px, layout, samples, ao_rays, seed, progress,
                              ao_radius)
    tiles = _frames_view(raw, frames, frame_px)
    alpha = tiles[..., 3]
    straight = tiles[..., 0:3] / np.maximum(alpha, 1e-6)[..., None]
    filled = pad_frames(alpha, np.concatenate([straight, tiles[..., PADDED]], -1), padding_px)
    tiles = tiles.copy()
    tiles[..., PADDED] = filled[..., 3:]
    nrm = tiles[..., 4:7]
    tiles[..., 4:7] = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-6)
    levels = mip_chain(tiles, frames, atlas_px, frame_levels)
    straight_img = np.zeros((atlas_px, atlas_px, 3), np.float32)
    s = _from_frames(filled[..., 0:3].astype(np.float32), frames)
    straight_img[:s.shape[0], :s.shape[1]] = np.clip(s, 0.0, 1.0)
    return Atlas(layout, frames, frame_px, atlas_px, np.asarray(centre, np.float64), float(radius), levels,
                 frame_levels, straight_img, dirs)


def sample_frame(level_img: np.ndarray, frame_px: int, i, j, x, y) -> np.ndarray:
    """Bilinear samples of frames (i, j) of one mip level at texel
    coordinates (x, y) inside the frame (0 = the first texel's centre),
    clamped half a texel inside the frame, so no sample ever reads a
    neighbouring frame. Arrays broadcast; returns (..., channels)."""
    f = frame_px
    x = np.clip(np.asarray(x, np.float64), 0.0, f - 1.0)
    y = np.clip(np.asarray(y, np.float64), 0.0, f - 1.0)
    x0 = np.minimum(np.floor(x), max(f - 2, 0)).astype(np.int64)
    y0 = np.minimum(np.floor(y), max(f - 2, 0)).astype(np.int64)
    x1 = np.minimum(x0 + 1, f - 1)
    y1 = np.minimum(y0 + 1, f - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    ox, oy = np.asarray(i) * f, np.asarray(j) * f
    t00 = level_img[oy + y0, ox + x0]
    t10 = level_img[oy + y0, ox + x1]
    t01 = level_img[oy + y1, ox + x0]
    t11 = level_img[oy + y1, ox + x1]
    return (t00 * (1 - fx) + t10 * fx) * (1 - fy) + (t01 * (1 - fx) + t11 * fx) * fy


def cutout_polygon(alpha: np.ndarray, vertices: int = 8) -> np.ndarray:
    """The cut-out polygon of the frames (Amplify's 8-vertex billboard
    shape): a convex polygon of at most `vertices` corners, in frame uv
    (0..1, v down like the frame's rows), that contains every texel any
    frame covers (alpha (n, F, F) > 0) and the texels next to them, so an engine drawing the impostor
    on it instead of the square discards no covered texel and shades fewer
    empty ones. From the convex hull of the covered texels' corners, the
    edge whose removal adds the least area (its neighbours extended to meet)
    is removed while more than `vertices` corners remain and the meeting
    point stays inside the frame. Counter-clockwise in (u, v)."""
    from scipy.spatial import ConvexHull

    from scipy import ndimage

    n, f, _ = alpha.shape
    # one texel of margin: a bilinear fetch half a texel outside a covered texel still reads it
    covered = ndimage.binary_dilation((alpha > 0).any(0), iterations=1)
    if not covered.any():
        return np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    rows, cols = np.nonzero(covered)
    corners = np.concatenate([np.stack([cols + dx, rows + dy], 1) for dx in (0, 1) for dy in (0, 1)]).astype(np.float64)
    hull = ConvexHull(corners)
    poly = [p for p in corners[hull.vertices] / f]  # counter-clockwise (scipy's order in 2-D)

    def meet(i: int):
        """Where the edges before and after edge (i, i+1) meet, and the area that adds."""
        m = len(poly)
        a, b, c, d = poly[(i - 1) % m], poly[i], poly[(i + 1) % m], poly[(i + 2) % m]
        r, s = b - a, d - c
        den = r[0] * s[1] - r[1] * s[0]
        if abs(den) < 1e-12:
            return None, math.inf
        t = ((c - a)[0] * s[1] - (c - a)[1] * s[0]) / den
        if t < 1.0 - 1e-9:  # the extended edges meet behind: removing the edge would cut into the hull
            return None, math.inf
        x = a + t * r
        if (x < -1e-9).any() or (x > 1.0 + 1e-9).any():
            return None, math.inf
        area = 0.5 * abs((c - b)[0] * (x - b)[1] - (c - b)[1] * (x - b)[0])
        return x, area

    while len(poly) > vertices:
        best = min(range(len(poly)), key=lambda i: meet(i)[1])
        x, area = meet(best)
        if x is None:
            break
        m = len(poly)
        poly[best] = x
        del poly[(best + 1) % m]
    return np.asarray(poly)
