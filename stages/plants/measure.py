"""What a plant looks like, measured: foliage and wood surface areas, leaf
area index over the crown's footprint, and crown opacity from the side.

    foliage area  one-sided area of the foliage that is there: card area x the
                  card texture's coverage (alpha >= 0.5) / cards per cluster (a
                  crossed pair shows one cluster twice: counted once), leaf and
                  blade meshes at their area;
    wood area     the woody solid's surface;
    LAI           foliage area / area of the 2-D convex hull of the foliage's
                  ground projection (x-z);
    crown opacity orthographic side views at 8 azimuths (worldlib.render): of
                  the pixels inside the 2-D convex hull of the foliage's
                  projection (alpha >= 0.5), the share that foliage or wood
                  covers with alpha >= 0.5; the mean over the azimuths
                  (opposite azimuths see the same lines of sight: 4 renders).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull

from worldlib.render import Camera, Scene, Settings
from worldlib.render import Prepared

from .mesh import Part


def surface_area(part: Part | None) -> float:
    if part is None or part.n_tris == 0:
        return 0.0
    p = part.verts[:, 0:3].astype(np.float64)[part.tris]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


def foliage_area(parts: dict[str, Part], card_coverage: float | None, cards_per_cluster: int = 1) -> float:
    leaves = surface_area(parts.get("Leaves"))
    if card_coverage is not None:
        leaves *= card_coverage / cards_per_cluster
    return leaves + surface_area(parts.get("Blades")) + surface_area(parts.get("Cards"))


def _hull_area_xz(points: np.ndarray) -> float:
    if len(points) < 3:
        return 0.0
    try:
        return float(ConvexHull(points[:, [0, 2]]).volume)
    except Exception:  # collinear points: no area
        return 0.0


def leaf_area_index(parts: dict[str, Part], card_coverage: float | None, cards_per_cluster: int = 1) -> float:
    pts = [p.verts[:, 0:3] for k, p in parts.items() if k != "Wood" and p.n_tris]
    if not pts:
        return 0.0
    foot = _hull_area_xz(np.concatenate(pts).astype(np.float64))
    return foliage_area(parts, card_coverage, cards_per_cluster) / foot if foot > 0 else 0.0


def cards_per_cluster(spec, has_cards: bool) -> int:
    """2 for a species whose clusters are crossed card pairs, else 1."""
    return 2 if has_cards and spec.foliage is not None and spec.foliage.crossed else 1


def plant_scene(parts: dict[str, Part], spec, card_rgba: np.ndarray | None, bark_rgb: np.ndarray | None,
                foliage_only: bool = False, size: int = 256, slices_rgba: np.ndarray | None = None) -> Scene:
    """A render scene of one LOD: wood with its bark texture, foliage cards
    with their card texture (alpha-tested), the grass slice tuft with its
    atlas, other foliage in its colours."""
    stack = [np.ones((size, size, 4), np.float32), np.ones((size, size, 4), np.float32), np.ones((size, size, 4), np.float32)]
    if slices_rgba is not None:
        stack[2] = _resized(slices_rgba, size)
    if card_rgba is not None:
        stack[0] = _resized(card_rgba, size)
    if bark_rgb is not None:
        stack[1] = np.concatenate([_resized(bark_rgb, size), np.ones((size, size, 1), np.float32)], -1)
    scenes = []
    for name, part in parts.items():
        if part.n_tris == 0 or (foliage_only and name == "Wood"):
            continue
        v = part.verts
        if name == "Wood":
            tint, tex = (1.0, 1.0, 1.0) if bark_rgb is not None else spec.bark_color, 1 if bark_rgb is not None else -1
        elif name == "Leaves" and card_rgba is not None:
            tint, tex = (1.0, 1.0, 1.0), 0
        elif name == "Cards" and slices_rgba is not None:
            tint, tex = (1.0, 1.0, 1.0), 2
        else:  # blades, slice cards, leaf meshes: root to tip colour per triangle
            fl = v[part.tris, 9].mean(1)[:, None]
            tint = (1 - fl) * np.asarray(spec.leaf_color) + fl * np.asarray(spec.leaf_tip_color)
            tex = -1
        scenes.append(Scene(v[:, 0:3], v[:, 3:6], v[:, 6:8], part.tris, tint, tex, np.stack(stack)))
    return Scene.concat(scenes)


def _resized(img: np.ndarray, size: int) -> np.ndarray:
    h, w = img.shape[:2]
    if h == size and w == size:
        return img.astype(np.float32)
    ys = (np.arange(size) * h // size).astype(int)
    xs = (np.arange(size) * w // size).astype(int)
    return img[ys][:, xs].astype(np.float32)


def side_cameras(points: np.ndarray, azimuths: int = 8) -> list[Camera]:
    """Orthographic cameras looking horizontally at the plant's centre from
    `azimuths` directions, each view holding the whole plant."""
    lo, hi = points.min(0), points.max(0)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo)) * 1.05
    cams = []
    for k in range(azimuths):
        a = 2 * math.pi * k / azimuths
        d = np.array([math.cos(a), 0.0, math.sin(a)])
        eye = c - d * (r + 1.0)
        cams.append(Camera(tuple(eye), tuple(d), (0.0, 1.0, 0.0), ortho_height_m=2 * r))
    return cams


def _inside_hull(mask: np.ndarray) -> np.ndarray:
    """Pixels whose centres lie inside the convex hull of the covered pixels' corners."""
    ys, xs = np.nonzero(mask)
    if len(ys) < 3:
        return mask.copy()
    corners = np.concatenate([np.stack([xs + dx, ys + dy], 1) for dx in (0, 1) for dy in (0, 1)]).astype(np.float64)
    try:
        hull = ConvexHull(corners)
    except Exception:
        return mask.copy()
    H, W = mask.shape
    gy, gx = np.mgrid[0:H, 0:W]
    pts = np.stack([gx.ravel() + 0.5, gy.ravel() + 0.5], 1)
    eq = hull.equations
    inside = (pts @ eq[:, :2].T + eq[:, 2] <= 1e-9).all(1)
    return inside.reshape(H, W)


def _crop_camera(cam: Camera, rows: tuple[int, int], cols: tuple[int, int], size: int) -> Camera:
    """The orthographic view of pixels rows[0]:rows[1], cols[0]:cols[1] of
    `cam`'s size x size image: the same rays (up to float rounding)."""
    f = np.asarray(cam.forward, np.float64)
    f = f / np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam.up, np.float64))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    half = 0.5 * cam.ortho_height_m  # a square view: half width = half height
    cx = (cols[0] + cols[1]) / size - 1.0
    cy = 1.0 - (rows[0] + rows[1]) / size
    eye = np.asarray(cam.eye, np.float64) + cx * half * r + cy * half * u
    return Camera(tuple(eye), cam.forward, cam.up, ortho_height_m=cam.ortho_height_m * (rows[1] - rows[0]) / size,
                  ortho_width_m=cam.ortho_height_m * (cols[1] - cols[0]) / size)


def _foliage_key(parts: dict[str, Part], cams: list[Camera]) -> bytes:
    import hashlib

    h = hashlib.sha1()
    for name, part in sorted(parts.items()):
        if name != "Wood" and part.n_tris:
            h.update(name.encode())
            h.update(np.ascontiguousarray(part.verts).tobytes())
            h.update(np.ascontiguousarray(part.tris).tobytes())
    for cam in cams:
        h.update(cam.frame(1, 1).tobytes())
    return h.digest()


def crown_opacity(env, parts: dict[str, Part], spec, card_rgba: np.ndarray | None, azimuths: int = 8,
                  size: int = 128, slices_rgba: np.ndarray | None = None, hulls: dict | None = None) -> dict:
    """Crown opacity from the side (module docstring) and its value per
    azimuth, rendered on the OpenCL device `env`.

    Only the pixels inside a view's hull count, so the full render covers
    the hull's bounding rectangle only. `hulls` (optional, shared between
    the LODs of one plant) keeps the hull masks by foliage and cameras: a
    level whose foliage and views are those of a level before reuses them."""
    pts = np.concatenate([p.verts[:, 0:3] for p in parts.values() if p.n_tris]).astype(np.float64)
    has_wood = "Wood" in parts and parts["Wood"].n_tris > 0
    foliage = plant_scene(parts, spec, card_rgba, None, foliage_only=True, slices_rgba=slices_rgba)
    if foliage.n_triangles == 0:
        return {"mean": 0.0, "per_azimuth": [0.0] * azimuths}
    # An orthographic view from the opposite side has the same lines of sight
    # (mirrored), so the same covered pixels and hull: with an even number of
    # azimuths the first half is rendered and stands for the second.
    half = azimuths // 2 if azimuths % 2 == 0 else azimuths
    cams = side_cameras(pts, azimuths)[:half]
    key = _foliage_key(parts, cams) if hulls is not None else None
    masks = hulls.get(key) if hulls is not None else None
    pl = None
    if masks is None:
        pl = Prepared(env, foliage)
        s_hull = Settings(size, size, samples=1)  # the hull needs only which pixels the crown reaches
        masks = [_inside_hull(pl.render(cam, s_hull).alpha >= 0.5) for cam in cams]
        if hulls is not None:
            hulls[key] = masks
    # without wood the full scene is the foliage scene
    pf = (Prepared(env, plant_scene(parts, spec, card_rgba, None, slices_rgba=slices_rgba)) if has_wood
          else pl or Prepared(env, foliage))
    values = []
    for cam, hull in zip(cams, masks):
        n_hull = int(hull.sum())
        if n_hull == 0:
            values.append(0.0)
            continue
        ys, xs = np.nonzero(hull)
        rows, cols = (int(ys.min()), int(ys.max()) + 1), (int(xs.min()), int(xs.max()) + 1)
        alpha = pf.render(_crop_camera(cam, rows, cols, size),
                          Settings(cols[1] - cols[0], rows[1] - rows[0], samples=2)).alpha
        covered = alpha >= 0.5
        values.append(float((covered & hull[rows[0]:rows[1], cols[0]:cols[1]]).sum() / n_hull))
    if half < azimuths:
        values = values + values
    return {"mean": float(np.mean(values)), "per_azimuth": values}


def _display_light():
    """(sun direction, sun gain G, share T of it through surfaces facing
    away) of the renderer's display light (Image.shaded's defaults), probed
    on two pixels so this stays what the pictures use."""
    import inspect

    from worldlib.render import Image

    sun = np.asarray(inspect.signature(Image.shaded).parameters["sun"].default, np.float32)
    sun /= np.linalg.norm(sun)
    n = np.stack([sun, -sun])[None]
    probe = Image(np.ones((1, 2, 3), np.float32), np.ones((1, 2), np.float32), n, np.zeros((1, 2), np.float32),
                  np.zeros((1, 2), np.float32))
    lit = probe.shaded(background=(0.0, 0.0, 0.0))[0, :, 1]
    return sun, float(lit[0]), float(lit[1] / lit[0])


def front_lit_camera(points: np.ndarray, sun: np.ndarray) -> Camera:
    """The orthographic camera of side_cameras on the sun's side of the
    plant: looking horizontally against the sun's azimuth (the sun behind
    the viewer, what a held-out view near the sun's azimuth sees)."""
    lo, hi = points.min(0), points.max(0)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo)) * 1.05
    d = -np.array([float(sun[0]), 0.0, float(sun[2])])
    d /= max(float(np.linalg.norm(d)), 1e-12)
    return Camera(tuple(c - d * (r + 1.0)), tuple(d), (0.0, 1.0, 0.0), ortho_height_m=2 * r)


def translucency_gains(env, parts: dict[str, Part], spec, card_rgba: np.ndarray | None,
                       slices_rgba: np.ndarray | None = None, azimuths: int = 4, size: int = 96) -> dict:
    """The foliage's transmitted light as a gain on its colour, by view: the
    factor by which it brightens the foliage in the renderer's display light
    (Image.shaded passes a share T of the sun through surfaces facing away
    from it), over the foliage pixels with ambient occlusion, the luminance
    of the shaded picture over that picture without the transmitted term.
    "side" over the side views, "front_lit"
    from the sun's side (front_lit_camera), and "dcc", their geometric mean,
    the one gain a DCC's opaque UsdPreviewSurface carries
    (materials.bake_translucency).

    A constant gain cannot follow the view: from the sun's side the leaves
    a viewer sees face the sun and pass it almost no light (the broadleaf's
    front_lit 1.01), across and against the sun many of them glow (its side
    mean 1.20). The geometric mean errs by the same factor
    sqrt(side / front_lit) both ways, about 9 % for the broadleaf, where
    the side mean alone put the whole error, 19 %, on a front-lit view.
    1 each without foliage."""
    from worldlib.render import Settings

    foliage = plant_scene(parts, spec, card_rgba, None, foliage_only=True, slices_rgba=slices_rgba)
    if foliage.n_triangles == 0:
        return {"side": 1.0, "front_lit": 1.0, "dcc": 1.0}
    sun, gain, share = _display_light()
    pts = foliage.positions.astype(np.float64)
    radius = 0.5 * float(np.linalg.norm(pts.max(0) - pts.min(0)))
    prepared = Prepared(env, foliage)
    lum = np.array([0.2126, 0.7152, 0.0722], np.float32)

    def ratio(cameras) -> float:
        full = without = 0.0
        for cam in cameras:
            img = prepared.render(cam, Settings(size, size, samples=2, ao_rays=4, ao_radius_m=0.1 * radius))
            shaded = img.shaded(background=(0.0, 0.0, 0.0)) @ lum
            nrm = img.normal / np.maximum(np.linalg.norm(img.normal, axis=2, keepdims=True), 1e-6)
            through = (img.albedo @ lum) * gain * share * np.clip(-(nrm @ sun), 0.0, None)
            full += float(shaded.sum())
            without += float((shaded - through).sum())
        return full / without if without > 0 else 1.0

    side, front = ratio(side_cameras(pts, azimuths)), ratio([front_lit_camera(pts, sun)])
    return {"side": side, "front_lit": front, "dcc": math.sqrt(side * front)}
