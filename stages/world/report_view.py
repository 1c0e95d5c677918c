"""The report's picture of the world: a perspective view of the composed
world.usda's ground meshes (terrain and water, not the plants) in their
ground colours, rendered with worldlib.render. Declared in STAGE.report
(pipeline.contract.ReportPicture); the one call to switch for a view with
plants (worldlib.render.world_view)."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

VIEW_SIZE = (960, 540)


def world_picture(world_usda: Path, out_png: Path, cl, size: tuple[int, int] = VIEW_SIZE) -> str:
    """Render the view into `out_png` on the OpenCL device `cl`
    (pipeline.opencl.CL); returns a caption."""
    from pipeline.exr import write_png
    from worldlib.render import Camera, Scene, Settings, render, srgb8

    scene = Scene.concat(_ground_scenes(world_usda))
    lo, hi = scene.positions.min(0).astype(np.float64), scene.positions.max(0).astype(np.float64)
    centre = 0.5 * (lo + hi)
    span = float(max(hi[0] - lo[0], hi[2] - lo[2]))
    direction = np.array([0.55, -0.5, -0.67])  # from the south-west, looking north-east and down
    direction /= np.linalg.norm(direction)
    eye = centre - direction * 1.6 * span
    eye[1] = max(eye[1], hi[1] + 0.3 * span)
    forward = centre - eye
    camera = Camera(tuple(eye), tuple(forward / np.linalg.norm(forward)), fov_y_deg=40.0)
    img = render(cl, scene, camera, Settings(size[0], size[1], samples=2, ao_rays=0))
    write_png(out_png, np.ascontiguousarray(srgb8(img.shaded(sun=(0.5, 0.7, 0.3))), np.uint8))
    return (f"{scene.n_triangles:,} triangles of the ground and water meshes, worldlib.render "
            f"(perspective, 2x2 samples); plants not drawn")


def _ground_scenes(world_usda: Path) -> list:
    """A worldlib.render Scene per mesh outside the point instancers (a
    terrain's tiles, the meshes of one parent and material, welded into
    one): water dark blue, the ground in its material's colours (grey
    without)."""
    from pxr import Usd, UsdGeom, UsdShade

    from worldlib.render import Scene

    from pipeline.usdio import mesh_in_world
    from worldlib.render.usd_asset import mute_dcc_selection

    stage = Usd.Stage.Open(str(world_usda))
    mute_dcc_selection(stage)  # the ground as it is (full terrain LODs), without the crowns a DCC draws for far plants
    parts: dict[tuple, list] = {}  # (parent, material) -> [(points, triangles, tints)]: a terrain's tiles together
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            continue
        arrays = mesh_in_world(prim)  # None: not a mesh, or an empty one
        if arrays is None:
            continue
        pts, counts, idx = arrays
        tris = _triangulate(counts, idx)
        water = "water" in str(prim.GetPath()).lower()
        tint = np.tile([0.05, 0.12, 0.25] if water else [0.3, 0.3, 0.28], (len(tris), 1))
        if not water:
            colours = _ground_colours(prim, pts, tris)
            if colours is not None:
                tint = colours
        material = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
        key = (str(prim.GetPath()) if water else str(prim.GetParent().GetPath()), str(material.GetPath()) if material else "")
        parts.setdefault(key, []).append((pts, tris, tint))
    scenes = []
    for group in parts.values():
        pts, tris, tint = group[0]
        if len(group) > 1:  # tiles: welded at their shared borders, so the normals there sum both sides' faces
            offsets = np.cumsum([0] + [len(p) for p, _, _ in group[:-1]])
            pts, inverse = np.unique(np.concatenate([p for p, _, _ in group]), axis=0, return_inverse=True)
            tris = inverse.reshape(-1)[np.concatenate([t + o for (_, t, _), o in zip(group, offsets)])]
            tint = np.concatenate([c for _, _, c in group])
        scenes.append(Scene(pts, _vertex_normals(pts, tris), np.zeros((len(pts), 2)), tris, tint, -1))
    if not scenes:
        raise ValueError("the world has no meshes to show")
    return scenes


def _vertex_normals(pts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Each face's upward normal summed at its three corners, normalised."""
    e1, e2 = pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]]
    fn = np.cross(e1, e2)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    fn[fn[:, 1] < 0] *= -1.0
    corners = tris.ravel()
    vn = np.stack([np.bincount(corners, np.repeat(fn[:, k], 3), len(pts)) for k in range(3)], axis=1)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
    return vn


def _triangulate(counts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    if (counts == 3).all():
        return idx.reshape(-1, 3)
    tris, start = [], 0
    for n in counts:
        f = idx[start:start + n]
        tris.extend((f[0], f[j], f[j + 1]) for j in range(1, n - 1))
        start += n
    return np.asarray(tris, np.int64).reshape(-1, 3)


def _ground_colours(prim, pts: np.ndarray, tris: np.ndarray) -> np.ndarray | None:
    """Linear albedo per triangle from the bound material's diffuse texture
    at the triangle's centre st (UDIM tiles resolved per tile)."""
    from pxr import Usd, UsdGeom, UsdShade

    material = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if not material or not st:
        return None
    file_attr = None
    for shader_prim in Usd.PrimRange(material.GetPrim()):
        surface_in = UsdShade.Shader(shader_prim).GetInput("diffuseColor")
        if surface_in and surface_in.HasConnectedSource():
            file_attr = surface_in.GetConnectedSource()[0].GetPrim().GetAttribute("inputs:file")
            break
    if file_attr is None or file_attr.Get() is None:
        return None
    st_values = np.asarray(st.ComputeFlattened(), np.float64)
    if len(st_values) != len(pts):
        return None
    asset = file_attr.Get()
    uv = st_values[tris].mean(axis=1)
    # the triangles the whole texture would hold at this density: a terrain tile covers a part of st
    share = float(np.prod(np.clip(st_values.max(0) - st_values.min(0), 1e-6, 1.0)))
    n_tris = len(tris) / share
    if "<UDIM>" in asset.path:
        layer_dir = Path(file_attr.GetPropertyStack()[0].layer.realPath).parent
        return _udim_colours((layer_dir / asset.path).resolve(), uv, n_tris)
    path = Path(asset.resolvedPath or "")
    if not path.is_file():
        return None
    return _sample(_read_level(path, math.sqrt(n_tris / 2.0)), uv)


def _udim_colours(path: Path, uv: np.ndarray, n_tris: float) -> np.ndarray | None:
    """Colours at `uv` from the UDIM tiles `path` names (<UDIM> in its name),
    a square of n x n tiles over the unit square."""
    pattern = re.escape(path.name).replace(re.escape("<UDIM>"), r"(\d{4})")
    tiles = {int(m.group(1)): f for f in path.parent.iterdir() if (m := re.fullmatch(pattern, f.name))}
    if not tiles:
        return None
    out = np.zeros((len(uv), 3))
    n = int(round(math.sqrt(len(tiles))))
    tu = np.clip(np.floor(uv[:, 0] * n), 0, n - 1).astype(int)
    tv = np.clip(np.floor(uv[:, 1] * n), 0, n - 1).astype(int)
    texels = math.sqrt(n_tris / 2.0) / n  # about one texel per mesh cell of the tile
    for tile, f in tiles.items():
        u0, v0 = (tile - 1001) % 10, (tile - 1001) // 10
        sel = (tu == u0) & (tv == v0)
        if sel.any():
            out[sel] = _sample(_read_level(f, texels), uv[sel] * n - [u0, v0])
    return out


def _read_level(path: Path, texels: float) -> np.ndarray:
    """The texture's pixels at its smallest MIP level still `texels` wide
    (a picture of the whole world needs one texel per mesh cell, not the 1 m
    tiles' full resolution)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    try:
        level = 0
        while inp.seek_subimage(0, level + 1) and inp.spec().width >= texels:
            level += 1
        inp.seek_subimage(0, level)
        return np.asarray(inp.read_image(oiio.FLOAT))
    finally:
        inp.close()


def _sample(pixels: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = pixels.shape[:2]
    c = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    r = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)  # t = 1 is the image's top row
    return pixels[r, c, :3].astype(np.float64)
