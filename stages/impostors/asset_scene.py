"""A plant asset as the renderer sees it: the meshes of one `lod` variant of
a USD asset (the plants stage's layer), with their materials' albedo
textures (UsdUVTexture files: sRGB PNGs are made linear, their alpha is the
cut-out) or their displayColor where a material reads no texture.

Read through USD composition, so the impostor sees exactly what a DCC tool
opening the asset sees.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.render import Scene, linear_from_srgb

TEXTURE_PX = 256  # every texture of the stack is resampled to this size (the renderer's stack has one size)


@dataclass
class PlantScene:
    scene: Scene
    centre: np.ndarray  # the bounding sphere of the points (m)
    radius: float
    lo: np.ndarray  # the axis-aligned bounds (m)
    hi: np.ndarray
    parts: dict[str, int]  # mesh name -> triangles
    textures: list[str]  # the texture files read, in stack order


def _read_texture(path: Path, colour_space: str) -> np.ndarray:
    """(TEXTURE_PX, TEXTURE_PX, 4) linear RGB + alpha, nearest-resampled."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise InputError(f"impostors: cannot read texture {path}: {buf.geterror()}")
    px = np.asarray(buf.get_pixels(oiio.FLOAT), np.float64)
    if px.ndim == 2:
        px = px[..., None]
    rgb = px[..., :3] if px.shape[2] >= 3 else np.repeat(px[..., :1], 3, -1)
    alpha = px[..., 3] if px.shape[2] >= 4 else np.ones(px.shape[:2])
    if colour_space == "sRGB" or (colour_space != "raw" and path.suffix.lower() == ".png"):
        rgb = linear_from_srgb(np.asarray(rgb, np.float64))
    h, w = alpha.shape
    ys = (np.arange(TEXTURE_PX) * h // TEXTURE_PX).astype(int)
    xs = (np.arange(TEXTURE_PX) * w // TEXTURE_PX).astype(int)
    out = np.concatenate([rgb, alpha[..., None]], -1)[ys][:, xs]
    return np.ascontiguousarray(out, np.float32)


def _albedo_texture(mesh_prim):
    """(file path, colour space) of the UsdUVTexture feeding the bound
    material's diffuseColor, or None."""
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(mesh_prim).ComputeBoundMaterial()
    if not material:
        return None
    surface = material.ComputeSurfaceSource()[0]
    if not surface:
        return None
    colour = surface.GetInput("diffuseColor")
    if not colour or not colour.HasConnectedSource():
        return None
    source = colour.GetConnectedSource()[0]
    shader = UsdShade.Shader(source.GetPrim())
    if shader.GetIdAttr().Get() != "UsdUVTexture":
        return None
    file_input = shader.GetInput("file")
    asset = file_input.Get() if file_input else None
    if asset is None or not asset.resolvedPath:
        raise InputError(f"impostors: {mesh_prim.GetPath()}: its albedo texture {asset} does not resolve")
    cs = shader.GetInput("sourceColorSpace")
    return Path(asset.resolvedPath), (cs.Get() if cs else "auto") or "auto"


def _corners(primvar, tris_fv: np.ndarray, tris_v: np.ndarray, width: int) -> np.ndarray | None:
    """Per-corner values (m, 3, width) of a primvar (vertex, varying, faceVarying or constant)."""
    from pxr import UsdGeom

    if not primvar or not primvar.HasValue():
        return None
    values = np.asarray(primvar.Get(), np.float64).reshape(-1, width)
    interp = primvar.GetInterpolation()
    indices = primvar.GetIndices()
    if interp == UsdGeom.Tokens.constant:
        return np.broadcast_to(values[0], tris_v.shape + (width,)).copy()
    if indices:
        values = values[np.asarray(indices, np.int64)]
    if interp == UsdGeom.Tokens.faceVarying:
        return values[tris_fv]
    if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        return values[tris_v]
    if interp == UsdGeom.Tokens.uniform:
        return np.repeat(values[:, None, :], 3, 1)
    return None


def load(layer: Path, prim_path: str, lod: str = "LOD0") -> PlantScene:
    """The plant at `prim_path` of `layer` with its `lod` variant selected,
    in the asset's own frame (y up, metres)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(layer))
    prim = stage.GetPrimAtPath(prim_path)
    if not prim:
        raise InputError(f"impostors: {layer} has no prim {prim_path}")
    vset = prim.GetVariantSets().GetVariantSet("lod")
    if vset and lod in vset.GetVariantNames():
        vset.SetVariantSelection(lod)
    scenes, stack, files, parts = [], [], {}, {}
    xform_cache = UsdGeom.XformCache()
    for p in Usd.PrimRange(prim):
        if not p.IsA(UsdGeom.Mesh) or UsdGeom.Imageable(p).ComputePurpose() not in (UsdGeom.Tokens.default_,
                                                                                   UsdGeom.Tokens.render):
            continue
        mesh = UsdGeom.Mesh(p)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), np.int64)
        if len(counts) == 0:
            continue
        if np.any(counts != 3):
            raise InputError(f"impostors: {p.GetPath()} has faces that are not triangles")
        tris_v = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), np.int64).reshape(-1, 3)
        tris_fv = np.arange(3 * len(tris_v)).reshape(-1, 3)
        m = np.asarray(xform_cache.GetLocalToWorldTransform(p), np.float64).T  # column vectors
        pts = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
        pts = pts @ m[:3, :3].T + m[:3, 3]
        pv = UsdGeom.PrimvarsAPI(p)
        normals = _corners(pv.GetPrimvar("normals"), tris_fv, tris_v, 3)
        if normals is None:
            e = pts[tris_v]
            fn = np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0])
            normals = np.repeat(fn[:, None, :], 3, 1)
        else:
            normals = normals @ np.linalg.inv(m[:3, :3])
        uv = _corners(pv.GetPrimvar("st"), tris_fv, tris_v, 2)
        if uv is None:
            uv = np.zeros(tris_v.shape + (2,))
        tex = _albedo_texture(p)
        if tex is not None:
            key = str(tex[0])
            if key not in files:
                files[key] = len(stack)
                stack.append(_read_texture(*tex))
            tex_index, tint = files[key], np.ones((len(tris_v), 3))
        else:
            colour = _corners(pv.GetPrimvar("displayColor"), tris_fv, tris_v, 3)
            tint = colour.mean(1) if colour is not None else np.full((len(tris_v), 3), 0.5)
            tex_index = -1
        n = len(tris_v)
        scenes.append((pts[tris_v].reshape(-1, 3), normals.reshape(-1, 3), uv.reshape(-1, 2), np.clip(tint, 0, 1),
                       np.full(n, tex_index)))
        parts[p.GetName()] = n
    if not scenes:
        raise InputError(f"impostors: {layer} {prim_path} ({lod}) holds no mesh to render")
    textures = np.stack(stack) if stack else np.ones((1, 1, 1, 4), np.float32)
    n_rows = sum(len(s[0]) for s in scenes)
    scene = Scene(np.concatenate([s[0] for s in scenes]), np.concatenate([s[1] for s in scenes]),
                  np.concatenate([s[2] for s in scenes]), np.arange(n_rows).reshape(-1, 3),
                  np.concatenate([s[3] for s in scenes]), np.concatenate([s[4] for s in scenes]), textures)
    p = scene.positions.astype(np.float64)
    lo, hi = p.min(0), p.max(0)
    centre = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(p - centre, axis=1).max())
    return PlantScene(scene, centre, radius, lo, hi, parts, list(files))
