"""Static slice billboards: geometry any viewer draws, textured with renders
of slabs of the plant.

Trees and shrubs (seed 002, after Jakulin 2000): 3 orientations (0, 120,
240 degrees about y) x front and back x N slabs, and one horizontal
orientation (d = +y: slabs by height, seen from above and from below) for
the views seed 002 has none for (its slicings fail from above: at 80 deg
elevation the conifer's blend kept 0.16 of the silhouette). For
orientation k with direction d_k, the plant's extent along d_k (its
vertices' projections) is cut into N equal slabs of space (a card crossing
a slab's face is cut by it). Each slab is rendered orthographically from
the front (viewer on the +d_k side) and from the back (a real render, not
a mirror) onto a quad at the mean depth of the slab's content, spanning the plant's
extent across and up; the front quad faces +d_k, the back quad -d_k, 1 mm
apart, so a viewer with back-face culling sees the render made from its
side. Sheet layout: rows 2k (front) and 2k + 1 (back), column i for slab
i; rows 6 and 7 the horizontal slabs (seen from above, from below).

Grass (seed 001): 4 vertical quads, two parallel plates per axis (the
near and far half of the tuft seen from the front, then from the side),
in a 4:1 strip of square tiles, and 1 horizontal quad at half height
carrying the tuft seen from above, in a square sheet of its own.

Tile texels: straight linear albedo padded into transparent texels, alpha
(coverage), tangent-space normal of the tile's quad (one covered sample's,
not their mean: _one_sample_normal). Each quad is cut to
its tile's covered texels (and one more around them), with its uv.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from worldlib.render import Camera, Prepared, Scene, Settings

from . import octahedral

GAP_M = 0.001  # between a slab's front and back quads


@dataclass
class Sheet:
    name: str
    rows: int
    cols: int
    tile_px: int
    rgba: np.ndarray  # (rows T, cols T, 4): straight padded RGB, alpha
    normal: np.ndarray  # (rows T, cols T, 3) tangent space of each tile's quad
    positions: list = field(default_factory=list)  # per quad (4, 3), counter-clockwise seen from its viewer
    uvs: list = field(default_factory=list)  # per quad (4, 2) in the sheet
    tiles: list = field(default_factory=list)  # per quad (row, col)

    def mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(points (4q, 3), st (4q, 2), triangles (2q, 3), tile (q,) index row * cols + col)."""
        p = np.concatenate(self.positions)
        st = np.concatenate(self.uvs)
        base = 4 * np.arange(len(self.positions))[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
        tiles = np.array([r * self.cols + c for r, c in self.tiles])
        return p, st, tris, tiles


def _render_slab(prepared: Prepared, eye, forward, up, width: float, height: float, tile_px: int, samples: int,
                 thickness: float = math.inf):
    """(straight RGB + alpha, normal, mean depth) of the part of the plant
    within `thickness` of the eye's plane, seen orthographically along
    `forward` (mean depth: of its covered samples from the eye's plane,
    half the thickness when none).
    One BVH serves every slab: the rays start on the slab's near face (so
    nothing in front of it is seen) and a sample whose nearest hit lies
    beyond the far face counts as uncovered. Samples are rendered one per
    pixel at samples x the tile's side and box-filtered, so each sample is
    kept or dropped on its own (the n x n supersampling of a tile render)."""
    n = tile_px * samples
    cam = Camera(tuple(eye), tuple(forward), tuple(up), ortho_height_m=height, ortho_width_m=width)
    img = prepared.render(cam, Settings(n, n, samples=1, max_depth_m=thickness))
    # the kernel ends rays at the float32 nearest the far face: the face itself is this float64 test's
    keep = ((img.alpha > 0) & (img.depth <= thickness)).astype(np.float32)

    def box(a):
        return a.reshape(tile_px, samples, tile_px, samples, *a.shape[2:]).mean((1, 3))

    alpha = box(keep)
    albedo = box(img.albedo * keep[..., None])
    normal = _one_sample_normal(img.normal, keep, tile_px, samples)
    rgb = albedo / np.maximum(alpha, 1e-6)[..., None]
    depth = float(img.depth[keep > 0].mean()) if keep.any() else (0.5 * thickness if math.isfinite(thickness) else 0.0)
    return np.concatenate([rgb, alpha[..., None]], -1).astype(np.float32), normal.astype(np.float32), depth


def _one_sample_normal(normal: np.ndarray, keep: np.ndarray, tile_px: int, samples: int) -> np.ndarray:
    """Per texel the normal of its covered sample nearest the texel's centre
    ((0, 0, 0) where none is): the texels' normals are then drawn from the
    needles' and leaves' own, so the mean of their Lambert terms is the
    mesh's. The texels' mean normals would shade as a smooth surface: a
    crown's needles face every way, their mean faces the viewer, and that
    lit by a sun in front is brighter than the needles are (the luminance
    check of tests/dcc/test_blender.py, impostor against mesh in Cycles)."""
    n = normal.reshape(tile_px, samples, tile_px, samples, 3).transpose(0, 2, 1, 3, 4).reshape(tile_px, tile_px, -1, 3)
    k = keep.reshape(tile_px, samples, tile_px, samples).transpose(0, 2, 1, 3).reshape(tile_px, tile_px, -1)
    centre = 0.5 * (samples - 1)
    sy, sx = np.divmod(np.arange(samples * samples), samples)
    order = np.argsort((sy - centre) ** 2 + (sx - centre) ** 2, kind="stable")  # a fixed order, centre first
    first = order[np.argmax(k[..., order] > 0, axis=-1)]  # the first covered sample in that order
    picked = np.take_along_axis(n, first[..., None, None], axis=2)[:, :, 0]
    return np.where(k.any(-1)[..., None], picked, 0.0)


def _pad(rgba: np.ndarray, normal: np.ndarray) -> None:
    """Colour and normal of the nearest covered texel into uncovered ones (in place)."""
    from scipy import ndimage

    empty = rgba[..., 3] <= 0
    if empty.all() or not empty.any():
        return
    _, (iy, ix) = ndimage.distance_transform_edt(empty, return_indices=True)
    rgba[..., :3] = rgba[iy, ix, :3]
    normal[:] = normal[iy, ix]


def _sheet(name: str, rows: int, cols: int, tile_px: int) -> Sheet:
    return Sheet(name, rows, cols, tile_px, np.zeros((rows * tile_px, cols * tile_px, 4), np.float32),
                 np.zeros((rows * tile_px, cols * tile_px, 3), np.float32))


def _place(sheet: Sheet, row: int, col: int, rgba, normal, corners: np.ndarray, right, up, view) -> None:
    """The tile into the sheet, its normals turned into the quad's tangent
    space (x along u, y along v, z toward the viewer; what a material's
    normal map holds), and the quad with its uv rectangle."""
    t = sheet.tile_px
    rgba = rgba.copy()
    normal = np.ascontiguousarray(normal @ np.stack([right, up, view], 1))
    normal[rgba[..., 3] <= 0] = (0.0, 0.0, 1.0)
    (s0, s1), (t0, t1) = _covered_span(rgba[..., 3])
    _pad(rgba, normal)
    sheet.rgba[row * t:(row + 1) * t, col * t:(col + 1) * t] = rgba
    sheet.normal[row * t:(row + 1) * t, col * t:(col + 1) * t] = normal
    u0, u1 = col / sheet.cols, (col + 1) / sheet.cols
    v0, v1 = 1.0 - (row + 1) / sheet.rows, 1.0 - row / sheet.rows
    # the quad cut to the tile's covered texels: fewer empty layers for a ray to cross (a DCC's path tracer
    # stops after a few transparent hits: Cycles' 8 by default, and draws black past them)
    c = np.asarray(corners, np.float64)
    du, dv = c[1] - c[0], c[3] - c[0]
    sheet.positions.append(np.array([c[0] + s * du + q * dv for s, q in ((s0, t0), (s1, t0), (s1, t1), (s0, t1))]))
    su, sv = u1 - u0, v1 - v0
    sheet.uvs.append(np.array([[u0 + s0 * su, v0 + t0 * sv], [u0 + s1 * su, v0 + t0 * sv],
                               [u0 + s1 * su, v0 + t1 * sv], [u0 + s0 * su, v0 + t1 * sv]]))
    sheet.tiles.append((row, col))


def _covered_span(alpha: np.ndarray, margin: int = 1) -> tuple[tuple[float, float], tuple[float, float]]:
    """((s0, s1), (t0, t1)): the part of a tile (0..1 across, 0..1 up; rows
    run down) that holds its covered texels and `margin` more on each side,
    on texel edges (a bilinear fetch at the silhouette reads the padding
    inside); the whole tile when nothing is covered."""
    rows, cols = np.nonzero(alpha > 0)
    h, w = alpha.shape
    if len(rows) == 0:
        return (0.0, 1.0), (0.0, 1.0)
    c0, c1 = max(int(cols.min()) - margin, 0), min(int(cols.max()) + 1 + margin, w)
    r0, r1 = max(int(rows.min()) - margin, 0), min(int(rows.max()) + 1 + margin, h)
    return (c0 / w, c1 / w), (1.0 - r1 / h, 1.0 - r0 / h)


def _slab_edges(scene: Scene, direction: np.ndarray, slabs: int) -> np.ndarray:
    """The edges of N equal slabs along direction spanning the plant."""
    depth = scene.positions.astype(np.float64) @ direction
    return np.linspace(float(depth.min()), float(depth.max()), slabs + 1)


def _quad(origin_along: float, direction, right, up, a0, a1, b0, b1) -> np.ndarray:
    base = origin_along * direction
    return np.array([base + a0 * right + b0 * up, base + a1 * right + b0 * up,
                     base + a1 * right + b1 * up, base + a0 * right + b1 * up])


ORIENTATIONS = (0.0, 120.0, 240.0)  # azimuths of the vertical slicings (seed 002)
# elevations over which the blend moves to the horizontal slicing (held-out median IoU of the blend,
# conifer / broadleaf: 45-75 deg 0.749 / 0.822, 30-60 deg 0.783 / 0.823, 20-50 deg 0.785 / 0.818 with a
# broadleaf worst view of 0.59)
HORIZONTAL_FROM_DEG, HORIZONTAL_TO_DEG = 30.0, 60.0


def tree_slices(prepared: Prepared, slabs: int, tile_px: int, samples: int, orientations=ORIENTATIONS,
                name: str = "slices") -> Sheet:
    """Each slab's two quads lie at the mean depth of what its two renders
    see (the midpoint of the front and the back render's mean along d),
    not at the slab's middle: a viewer off the slicing's axis sees a
    slab's content shifted sideways by its distance from the quad, so a
    trunk or a dense part of the crown off the middle would show twice
    (held-out IoU as drawn, 36 views, 3 slabs: conifer 0.72 -> 0.78,
    broadleaf 0.75 -> 0.78)."""
    scene = prepared.scene
    sheet = _sheet(name, 2 * len(orientations) + 2, slabs, tile_px)
    p = scene.positions.astype(np.float64)
    directions = [octahedral.view_direction(theta, 0.0) for theta in orientations] + [np.array([0.0, 1.0, 0.0])]
    for k, d in enumerate(directions):
        edges = _slab_edges(scene, d, slabs)
        frames = []
        for sign in (1.0, -1.0):
            view = sign * d  # toward this side's viewer
            right, up = octahedral.frame_basis(view)
            a, b = p @ right, p @ up
            frames.append((sign, view, right, up, float(a.min()), float(a.max()), float(b.min()), float(b.max())))
        for i in range(slabs):
            rendered, at = [], []
            for sign, view, right, up, a0, a1, b0, b1 in frames:
                near = edges[i + 1] if sign > 0 else edges[i]  # the slab's face toward this side's viewer
                eye = near * d + 0.5 * (a0 + a1) * right + 0.5 * (b0 + b1) * up
                rgba, nrm, depth = _render_slab(prepared, eye, -view, up, a1 - a0, b1 - b0, tile_px, samples,
                                                edges[i + 1] - edges[i])
                rendered.append((rgba, nrm))
                at.append(near - sign * depth)
            middle = float(np.clip(0.5 * (at[0] + at[1]), edges[i] + GAP_M, edges[i + 1] - GAP_M))
            for side, ((sign, view, right, up, a0, a1, b0, b1), (rgba, nrm)) in enumerate(zip(frames, rendered)):
                corners = _quad(middle + sign * 0.5 * GAP_M, d, right, up, a0, a1, b0, b1)
                _place(sheet, 2 * k + side, i, rgba, nrm, corners, right, up, view)
    return sheet


def grass_slices(prepared: Prepared, tile_px: int, samples: int) -> tuple[Sheet, Sheet]:
    """(the 4:1 strip of vertical plates, the top sheet)."""
    scene = prepared.scene
    strip = _sheet("tuft", 1, 4, tile_px)
    p = scene.positions.astype(np.float64)
    col = 0
    for theta in (90.0, 0.0):  # the front view looks along -z, the side view along -x
        d = octahedral.view_direction(theta, 0.0)
        edges = _slab_edges(scene, d, 2)
        right, up = octahedral.frame_basis(d)
        a, b = p @ right, p @ up
        a0, a1, b0, b1 = float(a.min()), float(a.max()), float(b.min()), float(b.max())
        for i in (1, 0):  # the front plate (nearer the viewer) first
            eye = edges[i + 1] * d + 0.5 * (a0 + a1) * right + 0.5 * (b0 + b1) * up
            rgba, nrm, _ = _render_slab(prepared, eye, -d, up, a1 - a0, b1 - b0, tile_px, samples,
                                        edges[i + 1] - edges[i])
            _place(strip, 0, col, rgba, nrm, _quad(0.5 * (edges[i] + edges[i + 1]), d, right, up, a0, a1, b0, b1), right, up, d)
            col += 1
    top = _sheet("tuft_top", 1, 1, tile_px)
    d = np.array([0.0, 1.0, 0.0])
    right, up = octahedral.frame_basis(d)
    a, b = p @ right, p @ up
    a0, a1, b0, b1 = float(a.min()), float(a.max()), float(b.min()), float(b.max())
    half = 0.5 * (float(p[:, 1].min()) + float(p[:, 1].max()))
    eye = (float(p[:, 1].max()) + 1.0) * d + 0.5 * (a0 + a1) * right + 0.5 * (b0 + b1) * up
    rgba, nrm, _ = _render_slab(prepared, eye, -d, up, a1 - a0, b1 - b0, tile_px, samples)
    _place(top, 0, 0, rgba, nrm, _quad(half, d, right, up, a0, a1, b0, b1), right, up, d)
    return strip, top


def sheet_scene(sheets: list[Sheet], rows: tuple[int, ...] | None = None) -> Scene:
    """The billboards as a render scene (alpha-tested, one texture per tile);
    `rows`: only the quads of these sheet rows (one slicing of a tree)."""
    size = max(s.tile_px for s in sheets)
    P, N, UV, T, TEX, stack = [], [], [], [], [], []
    first = 0  # vertex rows so far
    for s in sheets:
        t = s.tile_px
        for q in range(len(s.positions)):
            r, c = s.tiles[q]
            if rows is not None and r not in rows:
                continue
            tile = s.rgba[r * t:(r + 1) * t, c * t:(c + 1) * t]
            if t != size:
                idx = (np.arange(size) * t // size)
                tile = tile[idx][:, idx]
            stack.append(tile)
            corners = s.positions[q]
            n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
            n /= max(np.linalg.norm(n), 1e-12)
            P.append(corners)
            N.append(np.tile(n, (4, 1)))
            # the quad's uv in its own tile (a quad cut to the covered texels spans part of it)
            UV.append((np.asarray(s.uvs[q], np.float64) - [c / s.cols, 1.0 - (r + 1) / s.rows]) * [s.cols, s.rows])
            T.append(np.array([[0, 1, 2], [0, 2, 3]]) + first)
            TEX += [len(stack) - 1] * 2
            first += 4
    return Scene(np.concatenate(P), np.concatenate(N), np.concatenate(UV), np.concatenate(T), np.ones((len(TEX), 3)),
                 np.array(TEX), np.stack(stack))


def slab_spacing(positions: np.ndarray, direction: np.ndarray, slabs: int) -> float:
    """The spacing of N slabs along a view direction: (max - min of the
    points' projections) / N (seed 002's sanity check: positive for any
    direction, no diagonal stepping)."""
    d = np.asarray(direction, np.float64)
    proj = np.asarray(positions, np.float64) @ (d / np.linalg.norm(d))
    return float(proj.max() - proj.min()) / slabs


def slicing_weights(direction, orientations=ORIENTATIONS) -> list[tuple[int, float]]:
    """The blend of static slicings for a view direction: Jakulin's two
    vertical slicings (sheet rows: orientation k front = 2k, back = 2k + 1,
    facing azimuths theta_k and theta_k + 180) whose azimuths bracket the
    view's, weighted linearly, w = 1 - |delta azimuth| / spacing; from 30 to
    60 deg of elevation they hand over (smoothstep) to the horizontal
    slicing seen from the viewer's side (row 2K from above, 2K + 1 from below)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    elevation = math.degrees(math.asin(float(np.clip(d[1], -1.0, 1.0))))
    t = float(np.clip((abs(elevation) - HORIZONTAL_FROM_DEG) / (HORIZONTAL_TO_DEG - HORIZONTAL_FROM_DEG), 0.0, 1.0))
    w_top = t * t * (3.0 - 2.0 * t)
    top_row = 2 * len(orientations) + (0 if elevation >= 0.0 else 1)
    if w_top >= 1.0:
        return [(top_row, 1.0)]
    phi = np.degrees(np.arctan2(d[2], d[0])) % 360.0
    facing = {2 * k + side: (theta + 180.0 * side) % 360.0 for k, theta in enumerate(orientations) for side in (0, 1)}
    order = sorted(facing, key=lambda r: facing[r])
    spacing = 360.0 / len(order)
    vertical = [(order[0], 1.0)]
    for a, b in zip(order, order[1:] + order[:1]):
        delta = (phi - facing[a]) % 360.0
        if delta <= spacing + 1e-9:
            w = delta / spacing
            vertical = [(a, 1.0 - w), (b, w)]
            break
    out = [(r, (1.0 - w_top) * w) for r, w in vertical]
    return out + [(top_row, w_top)] if w_top > 0.0 else out
