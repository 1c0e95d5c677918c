"""USD meshes and their materials read into render Scenes: the one reader
behind every picture or bake that starts from USD (the plant assets for the
volumes and impostors stages and the bench pictures, whole worlds for
world_view.py), so each sees what a DCC tool opening the file sees.

Only what USD says is read: each UsdGeom.Mesh (fan-triangulated, composed
transform, invisible and proxy/guide-purpose subtrees skipped) and the
UsdPreviewSurface bound to it: diffuseColor from a UsdUVTexture (its file,
UDIM tiles included, sourceColorSpace, the primvar its st reads; sRGB made
linear, alpha kept as the cut-out; its scale applied as authored, less the
foliage translucency gain of worldlib.materials.bake_translucency, since
the display light passes that light itself), from a UsdPrimvarReader (that
primvar, e.g. displayColor), or a constant; primvars:displayColor without
a material. Normal maps are not read: shading uses the meshes' normals.
One Scene row per triangle corner.

    levels = load_asset("conifer.usdc")            # per LOD variant: Scene and mesh name per triangle
    plant = load_plant(plants_usda, "/Plants/conifer")   # one variant, in the layer's space, with its bounds
"""
from __future__ import annotations

import glob
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.exr import linear_from_srgb

# The sublayer a DCC renders with (stages/world/dcc_layer.py): a fixed `lod` per tile and far plants as crowns,
# coarser terrain tiles far away. Our renderers draw every instance as a billboard at any distance and the terrain
# at its full LOD, so they compose the world without it.
DCC_SELECTION_LAYER = "dcc.usdc"


def mute_dcc_selection(stage) -> None:
    """Mutes the DCC selection layer wherever it is in the layer stack (the
    world stage's root layer, itself a sublayer of a world's world.usda)."""
    for layer in stage.GetLayerStack(includeSessionLayers=False):
        if Path(layer.realPath or layer.identifier).name == DCC_SELECTION_LAYER:
            stage.MuteLayer(layer.identifier)

from .scene import Scene

TEXTURE_PX = 256  # the plant readers' texture stack side (the renderer's stack has one size)


@dataclass
class Look:
    colour: tuple[float, float, float]  # linear constant albedo (untextured)
    texture: str | None  # file (absolute; may hold <UDIM>)
    colour_space: str  # sRGB, raw or auto
    st_name: str  # the primvar the texture reads
    alpha_test: bool
    primvar: str | None = None  # the colour comes from this primvar (a UsdPrimvarReader)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)  # the texture's rgb scale, less a translucency gain


def shader_look(prim) -> Look | None:
    """diffuseColor of the UsdPreviewSurface bound to prim."""
    from pxr import UsdShade

    mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not mat:
        return None
    surf = mat.ComputeSurfaceSource()[0]
    if not surf:
        return None
    diffuse = surf.GetInput("diffuseColor")
    if not diffuse:
        return None
    opacity = surf.GetInput("opacity")
    alpha_test = bool(opacity and opacity.HasConnectedSource())
    if diffuse.HasConnectedSource():
        src = diffuse.GetConnectedSource()[0]
        tex = UsdShade.Shader(src.GetPrim())
        shader_id = str(tex.GetIdAttr().Get() or "")
        if shader_id == "UsdUVTexture":
            file_in = tex.GetInput("file")
            asset = file_in.Get() if file_in else None
            if asset is None:
                raise FileNotFoundError(f"{prim.GetPath()}: its albedo texture names no file")
            path = asset.resolvedPath
            if not path:  # a UDIM pattern resolves to nothing: relative to the layer that authored it
                layer = file_in.GetAttr().GetPropertyStack()[0].layer
                path = str(Path(layer.realPath).parent / asset.path)
            cs = tex.GetInput("sourceColorSpace")
            st_name = "st"
            st_in = tex.GetInput("st")
            if st_in and st_in.HasConnectedSource():
                reader = UsdShade.Shader(st_in.GetConnectedSource()[0].GetPrim())
                var = reader.GetInput("varname")
                st_name = str(var.Get()) if var and var.Get() else "st"
            return Look((1.0, 1.0, 1.0), path, str(cs.Get()) if cs and cs.Get() else "auto", st_name, alpha_test,
                        scale=texture_scale(tex))
        if shader_id.startswith("UsdPrimvarReader"):
            var = tex.GetInput("varname")
            return Look((0.5, 0.5, 0.5), None, "raw", "st", False, str(var.Get()) if var and var.Get() else "displayColor")
        return Look((0.5, 0.5, 0.5), None, "raw", "st", False)
    v = diffuse.Get()
    return Look(tuple(float(c) for c in v) if v is not None else (0.5, 0.5, 0.5), None, "raw", "st", False)


def texture_scale(tex) -> tuple[float, float, float]:
    """The rgb factor a colour UsdUVTexture applies (its scale; a bias would
    need a texture of its own: refused), divided by the translucency gain
    recorded on it (worldlib.materials.TRANSLUCENCY_GAIN)."""
    from worldlib.materials import TRANSLUCENCY_GAIN

    bias = tex.GetInput("bias")
    if bias and bias.Get() is not None and any(float(b) != 0.0 for b in list(bias.Get())[:3]):
        raise ValueError(f"{tex.GetPath()}: a bias on a colour texture is not read by the renderer")
    scale = tex.GetInput("scale")
    rgb = [float(c) for c in list(scale.Get())[:3]] if scale and scale.Get() is not None else [1.0, 1.0, 1.0]
    gain = float(tex.GetPrim().GetCustomDataByKey(TRANSLUCENCY_GAIN) or 1.0)
    return tuple(c / gain for c in rgb)


def read_image(path: str, colour_space: str) -> np.ndarray:
    """(H, W, 4) linear RGBA; rows top first."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # the colour as stored (straight, as PNG defines it), not times alpha
    buf = oiio.ImageBuf(str(path), 0, 0, config)
    if buf.has_error:
        raise FileNotFoundError(f"cannot read texture {path}: {buf.geterror()}")
    px = np.asarray(buf.get_pixels(oiio.FLOAT), np.float32)
    if px.ndim == 2:
        px = px[..., None]
    rgb = px[..., :3] if px.shape[2] >= 3 else np.repeat(px[..., :1], 3, -1)
    srgb = colour_space == "sRGB" or (colour_space == "auto" and not str(path).lower().endswith(".exr"))
    if srgb:
        rgb = linear_from_srgb(rgb)
    alpha = px[..., 3] if px.shape[2] >= 4 else np.ones(px.shape[:2], np.float32)
    return np.concatenate([rgb, alpha[..., None]], -1).astype(np.float32)


def load_texture(path: str, colour_space: str) -> tuple[np.ndarray, int]:
    """The texture (UDIM tiles joined into one mosaic) and its tiles per
    side (1 without UDIM): the mosaic's uv is the primvar's uv / tiles."""
    if "<UDIM>" not in path:
        return read_image(path, colour_space), 1
    pattern = re.escape(path).replace(re.escape("<UDIM>"), r"(\d{4})")
    tiles = {}
    for f in glob.glob(path.replace("<UDIM>", "[0-9][0-9][0-9][0-9]")):
        m = re.fullmatch(pattern, f)
        if m:
            k = int(m.group(1)) - 1001
            tiles[(k % 10, k // 10)] = f
    if not tiles:
        raise FileNotFoundError(f"no UDIM tiles for {path}")
    n = max(max(u, v) for u, v in tiles) + 1
    first = read_image(next(iter(tiles.values())), colour_space)
    th, tw = first.shape[:2]
    mosaic = np.zeros((n * th, n * tw, 4), np.float32)
    for (u, v), f in tiles.items():
        img = first if f == next(iter(tiles.values())) else read_image(f, colour_space)
        r0 = (n - 1 - v) * th  # tile v = 0 is the bottom row of the mosaic
        mosaic[r0:r0 + th, u * tw:(u + 1) * tw] = img[:th, :tw]
    return mosaic, n


def resized(img: np.ndarray, size: int, box: bool = True) -> np.ndarray:
    """size x size: box-filtered down where the sides divide (box), else
    nearest texel (the plant readers ask for nearest: a cut-out's alpha
    stays the texture's own values, as the alpha test reads them)."""
    h, w = img.shape[:2]
    if box and h % size == 0 and w % size == 0:
        return img.reshape(size, h // size, size, w // size, -1).mean(axis=(1, 3)).astype(np.float32)
    ys = (np.arange(size) * h // size).astype(int)
    xs = (np.arange(size) * w // size).astype(int)
    return np.ascontiguousarray(img[ys][:, xs], np.float32)


def corners(values: np.ndarray, interp: str, vidx: np.ndarray, corner: np.ndarray, face: np.ndarray | None = None
            ) -> np.ndarray:
    """A primvar's flattened values per triangle corner (vidx: the corner's
    point, corner: its faceVarying index, face: its face, for uniform)."""
    if interp == "faceVarying":
        return values[corner]
    if interp in ("vertex", "varying"):
        return values[vidx]
    if interp == "uniform" and face is not None and len(values) > int(face.max(initial=0)):
        return values[face]
    return np.broadcast_to(values[0], (len(vidx),) + values.shape[1:])


def mesh_scene(prim, to_world: np.ndarray, textures: dict) -> Scene | None:
    """A UsdGeom.Mesh as a render Scene in world space (to_world: row-vector
    4x4, USD's convention). textures: file -> (stack index, colour space),
    grown here; the stack itself is built by the caller (with_stack)."""
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    pts = mesh.GetPointsAttr().Get()
    counts = mesh.GetFaceVertexCountsAttr().Get()
    fvi = mesh.GetFaceVertexIndicesAttr().Get()
    if pts is None or counts is None or fvi is None or len(counts) == 0:
        return None
    pts = np.asarray(pts, np.float64)
    counts = np.asarray(counts, np.int64)
    fvi = np.asarray(fvi, np.int64)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # fan triangulation: corner ids (into faceVarying data) of every triangle
    fan = np.maximum(counts - 2, 0)
    tri_face = np.repeat(np.arange(len(counts)), fan)
    k = np.arange(len(tri_face)) - np.repeat(np.cumsum(fan) - fan, fan)
    corner = np.stack([start[tri_face], start[tri_face] + k + 1, start[tri_face] + k + 2], 1).ravel()
    face = np.repeat(tri_face, 3)
    vidx = fvi[corner]
    P = pts[vidx]
    pv = UsdGeom.PrimvarsAPI(mesh)
    nrm_pv = pv.GetPrimvar("normals")
    if nrm_pv and nrm_pv.HasValue():
        N = corners(np.asarray(nrm_pv.ComputeFlattened(), np.float64), nrm_pv.GetInterpolation(), vidx, corner, face)
    elif mesh.GetNormalsAttr().HasValue():
        N = corners(np.asarray(mesh.GetNormalsAttr().Get(), np.float64), mesh.GetNormalsInterpolation(), vidx, corner,
                    face)
    else:
        t = P.reshape(-1, 3, 3)
        fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        N = np.repeat(fn, 3, axis=0)
    m = np.asarray(to_world, np.float64)
    P = P @ m[:3, :3] + m[3, :3]
    N = N @ np.linalg.inv(m[:3, :3]).T
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-20)
    look = shader_look(prim)
    ntri = len(P) // 3
    uv = np.zeros((len(P), 2))
    tex_id = -1
    if look is not None and look.texture is not None:
        st_pv = pv.GetPrimvar(look.st_name)
        if st_pv and st_pv.HasValue():
            if look.texture not in textures:
                textures[look.texture] = (len(textures), look.colour_space)
            tex_id = textures[look.texture][0]
            uv = corners(np.asarray(st_pv.ComputeFlattened(), np.float64), st_pv.GetInterpolation(), vidx, corner, face)
    colour_pv = "displayColor" if look is None else look.primvar
    if colour_pv is not None:
        dc = pv.GetPrimvar(colour_pv)
        col = np.asarray(dc.ComputeFlattened(), np.float64).reshape(-1, 3) if dc and dc.HasValue() else np.full((1, 3), 0.5)
        tint = (np.broadcast_to(col[0], (ntri, 3)) if len(col) == 1 or dc.GetInterpolation() == "constant"
                else corners(col, dc.GetInterpolation(), vidx, corner, face).reshape(-1, 3, 3).mean(1))
    elif look.texture is None:
        tint = np.broadcast_to(np.asarray(look.colour), (ntri, 3))
    else:
        tint = np.broadcast_to(np.asarray(look.scale, np.float64), (ntri, 3))
    tris = np.arange(len(P)).reshape(-1, 3)
    # the texture index is local to `textures`; the stack is filled by the caller (placeholder 1-texel stack here)
    return Scene(P, N, uv, tris, np.clip(tint, 0.0, None), np.full(ntri, tex_id),
                 np.ones((max(len(textures), 1), 1, 1, 4), np.float32))


def subtree_scene(root, root_to_world_inv: np.ndarray | None, textures: dict, skip_instancers=True,
                  names: list | None = None) -> list[Scene]:
    """Every mesh under root (inactive and invisible prims, proxy and guide
    purposes skipped), in world space or, given the inverse of root's world
    transform, in root's space; `names` gains each mesh's prim name."""
    from pxr import Usd, UsdGeom

    cache = UsdGeom.XformCache()
    out = []
    # into instanceable prims too: the world's instancer prototypes are instances of one asset per species
    it = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies()))
    for prim in it:
        img = UsdGeom.Imageable(prim)
        if img and img.ComputeVisibility() == UsdGeom.Tokens.invisible:
            it.PruneChildren()
            continue
        if skip_instancers and prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            continue
        if img and img.GetPurposeAttr().Get() in (UsdGeom.Tokens.proxy, UsdGeom.Tokens.guide):
            it.PruneChildren()
            continue
        if prim.IsA(UsdGeom.Mesh):
            m = np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)
            if root_to_world_inv is not None:
                m = m @ root_to_world_inv
            s = mesh_scene(prim, m, textures)
            if s is not None and s.n_triangles:
                out.append(s)
                if names is not None:
                    names.append(prim.GetName())
    return out


def with_stack(parts: list[Scene], textures: dict, size: int, box: bool = True) -> Scene:
    """Join meshes with their textures resized to one size (resized)."""
    stack = np.ones((max(len(textures), 1), size, size, 4), np.float32)
    for f, (k, cs) in textures.items():
        stack[k] = resized(load_texture(f, cs)[0], size, box)
    return Scene.concat([Scene(s.positions, s.normals, s.uv, s.triangles, s.tint, s.texture, stack) for s in parts])


@dataclass
class AssetLevel:
    scene: Scene
    parts: np.ndarray  # (triangles,) the mesh name of each triangle


def _level(root, size: int) -> AssetLevel:
    """The meshes under root in root's own space, textures nearest-resampled to size."""
    from pxr import UsdGeom

    inv = np.linalg.inv(np.asarray(UsdGeom.XformCache().GetLocalToWorldTransform(root), np.float64))
    textures: dict = {}
    names: list = []
    parts = subtree_scene(root, inv, textures, names=names)
    if not parts:
        return AssetLevel(Scene.concat([]), np.zeros(0, object))
    per_triangle = np.concatenate([np.full(s.n_triangles, n, dtype=object) for s, n in zip(parts, names)])
    return AssetLevel(with_stack(parts, textures, size, box=False), per_triangle)


def load_asset(usdc: Path, size: int = TEXTURE_PX, levels: list[int] | None = None) -> list[AssetLevel]:
    """Per LOD variant of the file's default prim (all, or the indices in
    `levels`) its Scene and the mesh name of each triangle."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(usdc))
    root = stage.GetDefaultPrim()
    vset = root.GetVariantSets().GetVariantSet("lod")
    names = vset.GetVariantNames()
    out = []
    for i, name in enumerate(names):
        if levels is not None and i not in levels:
            continue
        vset.SetVariantSelection(name)
        out.append(_level(root, size))
    vset.SetVariantSelection(names[0] if names else "")
    return out


@dataclass
class PlantScene:
    scene: Scene
    centre: np.ndarray  # the bounding sphere of the points (m)
    radius: float
    lo: np.ndarray  # the axis-aligned bounds (m)
    hi: np.ndarray
    parts: dict[str, int]  # mesh name -> triangles


def load_plant(layer: Path, prim_path: str, lod: str = "LOD0", size: int = TEXTURE_PX) -> PlantScene:
    """The plant at `prim_path` of `layer` with its `lod` variant selected,
    in the prim's own frame (y up, metres), with its bounds. Raises
    LookupError when the prim is missing or holds no mesh."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(layer))
    prim = stage.GetPrimAtPath(prim_path)
    if not prim:
        raise LookupError(f"{layer} has no prim {prim_path}")
    vset = prim.GetVariantSets().GetVariantSet("lod")
    if vset and lod in vset.GetVariantNames():
        vset.SetVariantSelection(lod)
    level = _level(prim, size)
    if level.scene.n_triangles == 0:
        raise LookupError(f"{layer} {prim_path} ({lod}) holds no mesh to render")
    p = level.scene.positions.astype(np.float64)
    lo, hi = p.min(0), p.max(0)
    centre = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(p - centre, axis=1).max())
    names, counts = np.unique(level.parts, return_counts=True)
    return PlantScene(level.scene, centre, radius, lo, hi, {str(n): int(c) for n, c in zip(names, counts)})
