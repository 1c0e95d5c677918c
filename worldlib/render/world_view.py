"""A picture of a whole world as its `world.usda` composes it: the meshes
(terrain, water) with their materials' colour textures, and every
PointInstancer's instances, rendered with this package's ray caster.

    rgba = render_world(env, "build/worlds/default/world.usda", width=1600, height=900)

(`env`: the OpenCL device, a pipeline.opencl.CL.)
    save_png("world.png", rgba)

Only what USD says is read: meshes and their bound UsdPreviewSurface
(diffuseColor from a UsdUVTexture, UDIM tiles included, or a constant, or
primvars:displayColor), PointInstancers' prototypes, instance transforms
(UsdGeom.PointInstancer.ComputeInstanceTransformsAtTime) and their
per-instance primvars:tint (a colour factor, interpolation vertex).

Distant instances are drawn as what a game draws far away: each prototype is
rendered once from two sides and from above (its default variants, i.e. its most detailed
level, with AO) into a cell of a billboard atlas, and every instance becomes
two crossed alpha-tested quads and a horizontal one (its top view) of its
prototype's size, turned and scaled by its transform and multiplied by its
tint. So a world of a million plants is
six million triangles, not billions. Prototypes whose instances would be
shorter than `min_instance_height_m` (grass tufts, flowers: a fraction of a
pixel in a view of a whole world) are left to the ground's colour.
Prototypes are told apart by their prim name (an instancer per tile points to
its own prototype prim of one asset; the same name is the same asset).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.exr import srgb8

from . import Prepared
from .scene import Camera, Image, Scene, Settings
from .usd_asset import load_texture, mute_dcc_selection, resized, subtree_scene, with_stack
from .ground_detail import with_ground_detail

ATLAS_SIZE = 1024  # texels per side of every texture the world picture uses (the ground's and the billboard atlas)


@dataclass
class _Billboard:
    cell: tuple[int, int, int]  # atlas cell of the first of the two views, cells per side, texels per cell
    radius: float  # half width of the prototype (m, its own space)
    y0: float
    y1: float


def _bake_billboards(env, protos: dict, cells_per_side: int, cell_px: int, tex_stacks: dict) -> tuple[np.ndarray, dict]:
    """Render each prototype's scene from +z, from +x and from above
    (orthographic, AO) into atlas cells 3k, 3k + 1 and 3k + 2."""
    atlas = np.zeros((ATLAS_SIZE, ATLAS_SIZE, 4), np.float32)  # cells_per_side * cell_px <= ATLAS_SIZE
    boards = {}
    for k, (name, scene) in enumerate(protos.items()):
        p = scene.positions.astype(np.float64)
        r = float(np.sqrt(p[:, 0] ** 2 + p[:, 2] ** 2).max()) * 1.02
        y0, y1 = float(p[:, 1].min()), float(p[:, 1].max())
        h = max(y1 - y0, 1e-3)
        prepared = Prepared(env, scene)
        for view, (eye, fwd, up) in enumerate((((0.0, 0.5 * (y0 + y1), 10 * r + 1), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
                                               ((10 * r + 1, 0.5 * (y0 + y1), 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
                                               ((0.0, y1 + 10 * r + 1, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0)))):
            cam = (Camera(eye, fwd, up, ortho_height_m=h, ortho_width_m=2 * r) if view < 2
                   else Camera(eye, fwd, up, ortho_height_m=2 * r, ortho_width_m=2 * r))
            img = prepared.render(cam, Settings(cell_px, cell_px, samples=2, ao_rays=4, ao_radius_m=0.15 * h, seed=k))
            a = img.alpha
            rgb = img.albedo / np.maximum(a, 1e-6)[..., None] * (0.5 + 0.5 * img.ao)[..., None]
            c = 3 * k + view
            r0, c0 = (c // cells_per_side) * cell_px, (c % cells_per_side) * cell_px
            atlas[r0:r0 + cell_px, c0:c0 + cell_px] = np.concatenate([np.clip(rgb, 0, 1), a[..., None]], -1)
        boards[name] = _Billboard((3 * k, cells_per_side, cell_px), r, y0, y1)
    return atlas, boards


def _cell_uv(c: int, n: int, cell_px: int) -> tuple[float, float, float, float]:
    """uv rectangle of atlas cell c (row-major from the top, n per row, of
    cell_px texels), inset half a texel."""
    row, col = divmod(c, n)
    cell = cell_px / ATLAS_SIZE
    eps = 0.5 / ATLAS_SIZE
    u0, u1 = col * cell + eps, (col + 1) * cell - eps
    v1, v0 = 1.0 - row * cell - eps, 1.0 - (row + 1) * cell + eps
    return u0, u1, v0, v1


def _billboard_instances(board: _Billboard, xforms: np.ndarray, tints: np.ndarray, tex_id: int) -> Scene:
    """Two crossed vertical quads and a horizontal one through the crown per
    instance (row-vector transforms (n, 4, 4)): the side views hold up
    from low cameras, the top view from high ones."""
    r, y0, y1 = board.radius, board.y0, board.y1
    n = board.cell[1]
    quads, uvs, nrms = [], [], []
    for view in range(3):
        u0, u1, v0, v1 = _cell_uv(board.cell[0] + view, n, board.cell[2])
        if view == 0:  # seen from +z: image x is +x
            q = [(-r, y0, 0), (r, y0, 0), (r, y1, 0), (-r, y1, 0)]
            side = [(-1, 0, 0), (1, 0, 0), (1, 0, 0), (-1, 0, 0)]
        elif view == 1:  # seen from +x: image x is -z
            q = [(0, y0, r), (0, y0, -r), (0, y1, -r), (0, y1, r)]
            side = [(0, 0, 1), (0, 0, -1), (0, 0, -1), (0, 0, 1)]
        else:  # seen from above: image x is +x, image up is -z; the quad at 60 % of the height
            yh = y0 + 0.6 * (y1 - y0)
            q = [(-r, yh, r), (r, yh, r), (r, yh, -r), (-r, yh, -r)]
            side = [(0, 0, 0)] * 4
        quads += q
        uvs += [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        # normals lean out and up, so the crossed quads shade like a rounded crown
        nrms += [tuple(0.7 * np.asarray(s) + np.array([0.0, 1.0 if view == 2 else 0.25 if j < 2 else 0.8, 0.0]))
                 for j, s in enumerate(side)]
    Q = np.asarray(quads, np.float64)  # (12, 3)
    Nq = np.asarray(nrms, np.float64)
    m = len(xforms)
    P = np.einsum("vk,nkj->nvj", Q, xforms[:, :3, :3]) + xforms[:, None, 3, :3]
    inv_t = np.linalg.inv(xforms[:, :3, :3]).transpose(0, 2, 1)
    N = np.einsum("vk,nkj->nvj", Nq, inv_t)
    N /= np.maximum(np.linalg.norm(N, axis=2, keepdims=True), 1e-20)
    base = (np.arange(m) * 12)[:, None]
    local = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [8, 9, 10], [8, 10, 11]])
    tris = (base[:, None, :] + local[None]).reshape(-1, 3)
    uv = np.tile(np.asarray(uvs), (m, 1))
    tint = np.repeat(np.asarray(tints, np.float64), 6, axis=0)
    return Scene(P.reshape(-1, 3), N.reshape(-1, 3), uv, tris, tint, tex_id, np.ones((tex_id + 1, 1, 1, 4), np.float32))


def default_camera(lo: np.ndarray, hi: np.ndarray, azimuth_deg: float = 200.0, elevation_deg: float = 32.0,
                   fov_y_deg: float = 38.0, aspect: float = 16 / 9) -> Camera:
    """An oblique perspective view that holds the whole box (lo, hi), from
    the side the azimuth names (degrees clockwise from north = -z... +x east)."""
    c = 0.5 * (lo + hi)
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    back = np.array([math.sin(a) * math.cos(e), math.sin(e), -math.cos(a) * math.cos(e)])
    radius = 0.5 * float(np.linalg.norm((hi - lo)[[0, 2]]))
    half = math.radians(0.5 * fov_y_deg)
    dist = radius / math.sin(min(half, math.atan(math.tan(half) * aspect))) * 0.72
    eye = c + back * dist
    return Camera(tuple(eye), tuple(-back), (0.0, 1.0, 0.0), fov_y_deg=fov_y_deg)


def build_world_scene(env, world_usda: str | Path, min_instance_height_m: float = 0.8, max_instances: int | None = None,
                      progress=print) -> tuple[Scene, dict]:
    """The world as one render Scene (meshes + billboard instances) and a
    summary (instances per prototype, triangles, bounds)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world_usda))
    if not stage:
        raise FileNotFoundError(f"cannot open {world_usda}")
    mute_dcc_selection(stage)
    textures: dict = {}
    meshes = subtree_scene(stage.GetPseudoRoot(), None, textures)
    lo = np.min([s.positions.min(0) for s in meshes], 0) if meshes else np.zeros(3)
    hi = np.max([s.positions.max(0) for s in meshes], 0) if meshes else np.ones(3)
    # instancers
    cache = UsdGeom.XformCache()
    groups: dict[str, list] = {}  # prototype name -> [(xforms (n,4,4) world, tints (n,3))]
    proto_scene: dict[str, Scene] = {}
    proto_tex: dict = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.PointInstancer):
            continue
        pi = UsdGeom.PointInstancer(prim)
        targets = pi.GetPrototypesRel().GetTargets()
        idx = pi.GetProtoIndicesAttr().Get()
        if not targets or idx is None or len(idx) == 0:
            continue
        idx = np.asarray(idx)
        xf = np.asarray(pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default()), np.float64)
        xf = xf @ np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)
        tint_pv = UsdGeom.PrimvarsAPI(pi).GetPrimvar("tint")
        tints = (np.asarray(tint_pv.Get(), np.float64) if tint_pv and tint_pv.HasValue() and
                 tint_pv.GetInterpolation() in ("vertex", "varying") else np.ones((len(idx), 3)))
        if len(tints) != len(idx):
            tints = np.ones((len(idx), 3))
        for k, target in enumerate(targets):
            proto = stage.GetPrimAtPath(target)
            name = proto.GetName()
            if name not in proto_scene:
                inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(proto), np.float64))
                parts = subtree_scene(proto, inv, proto_tex, skip_instancers=True)
                proto_scene[name] = with_stack(parts, proto_tex, 256) if parts else None
            sel = idx == k
            if proto_scene[name] is not None and sel.any():
                groups.setdefault(name, []).append((xf[sel], tints[sel]))
    progress(f"world view: meshes and instancers read ({sum(len(p[0]) for g in groups.values() for p in g):,} "
             f"instances)")
    # which prototypes are tall enough to see
    keep = {}
    summary = {"instances": {}, "skipped_small": {}}
    for name, parts in groups.items():
        xf = np.concatenate([p[0] for p in parts])
        tn = np.concatenate([p[1] for p in parts])
        s = proto_scene[name]
        height = float(s.positions[:, 1].max() - s.positions[:, 1].min()) * np.linalg.norm(xf[:, 1, :3], axis=1)
        big = height >= min_instance_height_m
        if max_instances is not None and big.sum() > max_instances:
            big &= np.cumsum(big) <= max_instances
        if big.any():
            keep[name] = (xf[big], tn[big])
        summary["instances"][name] = int(big.sum())
        summary["skipped_small"][name] = int((~big).sum())
    cells = max(1, math.ceil(math.sqrt(3 * max(len(keep), 1))))
    cell_px = min(ATLAS_SIZE // cells, 256)  # a billboard is a few pixels tall in a view of the whole world
    progress(f"world view: billboards of {sorted(keep)} ({cell_px} px cells)")
    atlas, boards = _bake_billboards(env, {n: proto_scene[n] for n in keep}, cells, cell_px, proto_tex)
    # the texture stack: the meshes' textures, then the atlas
    stack = [np.zeros((ATLAS_SIZE, ATLAS_SIZE, 4), np.float32)] * (len(textures) + 1)
    udim_tiles = {}
    for f, (k, cs) in textures.items():
        img, tiles = load_texture(f, cs)
        stack[k] = resized(img, ATLAS_SIZE)
        udim_tiles[k] = tiles
    stack[len(textures)] = atlas
    stack = np.stack(stack)
    for s in meshes:  # uv of UDIM textures: the mosaic's
        for k, tiles in udim_tiles.items():
            if tiles > 1:
                on = np.repeat(s.texture == k, 3)
                s.uv[on] /= tiles
    parts = [Scene(s.positions, s.normals, s.uv, s.triangles, s.tint, s.texture, stack) for s in meshes]
    for name, (xf, tn) in keep.items():
        b = _billboard_instances(boards[name], xf, tn, len(textures))
        parts.append(Scene(b.positions, b.normals, b.uv, b.triangles, b.tint, b.texture, stack))
    progress("world view: billboards placed")
    scene = Scene.concat(parts)
    summary.update(triangles=scene.n_triangles, bounds=[lo.tolist(), hi.tolist()])
    return scene, summary


_CACHE: dict = {}  # (device, path, mtime) -> (Scene, summary, Prepared): several views of one world build it once


def render_world(env, world_usda: str | Path, width: int = 1600, height: int = 900, camera: Camera | None = None,
                 samples: int = 2, ao_rays: int = 2, sun=(-0.45, 0.75, 0.5), azimuth_deg: float = 200.0,
                 elevation_deg: float = 32.0, zoom: float = 1.0, stats: dict | None = None,
                 progress=print) -> np.ndarray:
    """The world seen from `camera` (default: default_camera at the azimuth
    and elevation, moved `zoom` times closer to the world's centre):
    (height, width, 4) uint8 sRGB RGBA, alpha 255 where something is hit
    (elsewhere the shaded sky). `stats`, when given, receives the scene
    summary and the seconds spent. The last world's scene and BVH stay
    cached, so more views of it cost only their rendering."""
    import time

    t0 = time.perf_counter()
    key = (env, str(Path(world_usda).resolve()), Path(world_usda).stat().st_mtime_ns)
    if key not in _CACHE:
        _CACHE.clear()
        scene, summary = build_world_scene(env, world_usda, progress=progress)
        _CACHE[key] = (scene, summary, Prepared(env, scene))
    scene, summary, prepared = _CACHE[key]
    t1 = time.perf_counter()
    lo, hi = np.asarray(summary["bounds"][0]), np.asarray(summary["bounds"][1])
    cam = camera or default_camera(lo, hi, azimuth_deg, elevation_deg, aspect=width / height)
    if camera is None and zoom != 1.0:
        c = 0.5 * (lo + hi)
        cam = Camera(tuple(c + (np.asarray(cam.eye) - c) / zoom), cam.forward, cam.up, fov_y_deg=cam.fov_y_deg)
    progress(f"world view: {scene.n_triangles:,} triangles, instances {summary['instances']}")
    img: Image = prepared.render(cam, Settings(width, height, samples=samples, ao_rays=ao_rays,
                                                      ao_radius_m=25.0, seed=1))
    img = with_ground_detail(img, world_usda, cam, width, height)  # the ground's detail layer up close
    shaded = img.shaded(sun=sun, sky=0.5, background=(0.55, 0.68, 0.85))
    alpha = np.round(np.clip(img.alpha, 0.0, 1.0) * 255.0).astype(np.uint8)
    if stats is not None:
        stats.update(summary, scene_s=round(t1 - t0, 2), render_s=round(time.perf_counter() - t1, 2))
    return np.concatenate([srgb8(shaded), alpha[..., None]], -1)


def save_png(path: str | Path, rgba: np.ndarray, keep_alpha: bool = False) -> None:
    import OpenImageIO as oiio

    data = rgba if keep_alpha else rgba[..., :3]
    if not oiio.ImageBuf(np.ascontiguousarray(data)).write(str(path)):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
