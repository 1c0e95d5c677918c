"""A plant asset as the plants stage wrote it (USD), read back into render
Scenes: what the baking stages that start from the assets (volumes,
impostors, bench pictures) render or voxelize, through the same materials a
DCC tool reads.

Each LOD variant becomes one Scene with one row per triangle corner;
texture 0 is the foliage card atlas, 1 the bark, 2 the grass blades, 3 the
grass slices (read from the materials' UsdUVTexture PNG, sRGB decoded to
linear, alpha kept); untextured meshes keep their displayColor. `parts`
names, per triangle, the mesh it came from (Wood, Leaves, Blades, Cards).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .scene import Scene, linear_from_srgb

LOOK_SLOTS = {"FoliageCards": 0, "Bark": 1, "Blades": 2, "GrassSlices": 3}


@dataclass
class AssetLevel:
    scene: Scene
    parts: np.ndarray  # (triangles,) the mesh name of each triangle


def read_png_linear(path: Path) -> np.ndarray:
    """An 8-bit sRGB PNG as linear RGBA float32 (alpha 1 when it has none)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.FLOAT)
    rgb = px[..., :3]
    lin = linear_from_srgb(rgb)
    alpha = px[..., 3] if px.shape[2] > 3 else np.ones(px.shape[:2])
    return np.concatenate([lin, alpha[..., None]], -1).astype(np.float32)


def resized(img: np.ndarray, size: int) -> np.ndarray:
    """Nearest-texel resampling to size x size."""
    h, w = img.shape[:2]
    ys = (np.arange(size) * h // size).astype(int)
    xs = (np.arange(size) * w // size).astype(int)
    return img[ys][:, xs]


def load_asset(usdc: Path, size: int = 256, levels: list[int] | None = None) -> list[AssetLevel]:
    """Per LOD (all, or the indices in `levels`) the asset's Scene and the
    mesh name of each triangle."""
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(usdc))
    root = stage.GetDefaultPrim()
    stack = np.ones((len(LOOK_SLOTS), size, size, 4), np.float32)
    for look, k in LOOK_SLOTS.items():
        tex = stage.GetPrimAtPath(root.GetPath().AppendPath(f"Looks/{look}/AlbedoTexture"))
        if tex:
            f = UsdShade.Shader(tex).GetInput("file").Get()
            stack[k] = resized(read_png_linear(Path(f.resolvedPath)), size)
    vset = root.GetVariantSets().GetVariantSet("lod")
    names = vset.GetVariantNames()
    out = []
    for i, name in enumerate(names):
        if levels is not None and i not in levels:
            continue
        vset.SetVariantSelection(name)
        scenes, parts = [], []
        for prim in Usd.PrimRange(root):
            if not prim.IsA(UsdGeom.Mesh):
                continue
            mesh = UsdGeom.Mesh(prim)
            pts = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
            idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), np.int64).reshape(-1, 3)
            if len(idx) == 0:
                continue
            pv = UsdGeom.PrimvarsAPI(mesh)
            st = pv.GetPrimvar("st")
            nrm = pv.GetPrimvar("normals")
            # corner-wise (faceVarying) arrays: flatten everything to one row per corner
            st_c = np.asarray(st.ComputeFlattened(), np.float64)
            n_c = np.asarray(nrm.ComputeFlattened(), np.float64)
            if st.GetInterpolation() == UsdGeom.Tokens.vertex:
                st_c, n_c = st_c[idx.ravel()], n_c[idx.ravel()]
            P = pts[idx.ravel()]
            mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
            tex = LOOK_SLOTS.get(mat.GetPrim().GetName() if mat else "", -1)
            if tex >= 0:
                tint = np.ones((len(idx), 3))
            else:
                col = np.asarray(pv.GetPrimvar("displayColor").ComputeFlattened(), np.float64)
                tint = np.broadcast_to(col[0], (len(idx), 3)) if len(col) == 1 else col[idx].mean(1)
            scenes.append(Scene(P, n_c, st_c, np.arange(len(P)).reshape(-1, 3), tint, tex, stack))
            parts.append(np.full(len(idx), prim.GetName(), dtype=object))
        out.append(AssetLevel(Scene.concat(scenes), np.concatenate(parts) if parts else np.zeros(0, object)))
    vset.SetVariantSelection(names[0] if names else "")
    return out
