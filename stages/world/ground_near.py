"""The ground's detail layer in the world's files and USD.

Files beside terrain.usdc (worldlib.ground_detail makes the textures):
- detail/<type>_albedo.png (8-bit sRGB) and detail/<type>_normal.png
  (tangent space, 0..1, raw) per ground type, tiling over the type's tile_m;
- splat_a.exr (rock, scree, grass) and splat_b.exr (dry grass, mud, snow):
  the splat weights over the terrain's st, one texel per height cell;
- near_albedo.png / near_normal.png: the blended detail baked over a square
  near a point (the world centre by default), for DCCs whose materials
  cannot blend (plain UsdPreviewSurface).

USD: the blend network sits in the ground material as a NodeGraph
(DETAIL_GRAPH) with one UsdUVTexture per type and map (wrap repeat, st from
primvar st_detail = (x, -z) in metres through a UsdTransform2d scaling by
1 / tile_m) and the two splat textures, and outputs <type>_albedo,
<type>_normal and <type>_weight a DCC wires into its own blend (MaterialX in
Houdini or Omniverse: sum of weight x albedo, triplanar where it can). The
near square is a GeomSubset `Near` of each terrain tile's mesh at each LOD
with triangles in it (materialBind; terrain_tiles.py) bound to
GroundNear, a plain UsdPreviewSurface reading the baked near textures
through primvar st_near.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from worldlib import ground_detail, images
from worldlib.ground import GROUND_TYPES

DETAIL_GRAPH = "/World/Terrain/Looks/Ground/Detail"
NEAR_MATERIAL = "/World/Terrain/Looks/GroundNear"
NEAR_SUBSET_NAME = "Near"  # the GeomSubset under each terrain tile mesh that has near triangles
REST_SUBSET_NAME = "Rest"  # beside it, the tile's other triangles (bound to the ground material)
SPLAT_FILES = (("splat_a.exr", GROUND_TYPES[:3]), ("splat_b.exr", GROUND_TYPES[3:]))


def write_detail_files(folder: Path, textures: dict, read_splat, shape: tuple[int, int], provenance: dict,
                       band_rows: int = 256) -> list[str]:
    """The detail textures (ground_detail.detail_textures) and splat
    textures (read_splat(row0, col0, rows, cols): the splat weights of a
    window, types in SPLAT_FILES' order, written band by band of rows);
    their names relative to folder."""
    (folder / "detail").mkdir(exist_ok=True)
    names = []
    for t, (albedo, normal) in textures.items():
        images.write_png(folder / "detail" / f"{t}_albedo.png", albedo, srgb=True)
        images.write_png(folder / "detail" / f"{t}_normal.png", normal, srgb=False)
        names += [f"detail/{t}_albedo.png", f"detail/{t}_normal.png"]
    rows, cols = shape
    writers = [images.MipmappedWriter(folder / name, rows, cols, len(types), provenance) for name, types in SPLAT_FILES]
    try:
        for r0 in range(0, rows, band_rows):
            band = read_splat(r0, 0, min(band_rows, rows - r0), cols)
            for i, out in enumerate(writers):
                out.write_rows(band[..., 3 * i:3 * i + 3])
    finally:
        for out in writers:
            out.close()
    return names + [name for name, _ in SPLAT_FILES]


def near_square(mesh, size_m: float, offset_m: tuple[float, float]) -> tuple[float, float, float, float]:
    """(x0, x1, z0, z1) of the near square: size_m around the mesh's centre
    moved by offset_m (east, south), rounded to whole lattice quads (the
    lattice is evenly spaced) and kept inside the mesh."""
    nr, nc = mesh.lattice_shape
    P = mesh.points.reshape(nr, nc, 3)
    xs, zs = P[0, :, 0].astype(np.float64), P[:, 0, 2].astype(np.float64)
    cx = 0.5 * (xs[0] + xs[-1]) + offset_m[0]
    cz = 0.5 * (zs[0] + zs[-1]) + offset_m[1]

    def span(v, c):  # the whole quads nearest to size_m around c (at least one)
        step = (v[-1] - v[0]) / (len(v) - 1)
        quads = int(np.clip(round(size_m / step), 1, len(v) - 1))
        lo = int(np.clip(round((c - 0.5 * quads * step - v[0]) / step), 0, len(v) - 1 - quads))
        return float(v[lo]), float(v[lo + quads])

    return (*span(xs, cx), *span(zs, cz))


def near_faces(mesh, square) -> np.ndarray:
    """Indices of the mesh triangles inside the square (all three corners)."""
    x0, x1, z0, z1 = square
    tri = mesh.face_vertex_indices.reshape(-1, 3)
    p = mesh.points[tri].astype(np.float64)
    eps = 1e-3
    inside = ((p[..., 0] >= x0 - eps) & (p[..., 0] <= x1 + eps) & (p[..., 2] >= z0 - eps)
              & (p[..., 2] <= z1 + eps)).all(1)
    return np.flatnonzero(inside).astype(np.int32)


def _lattice_bilinear(mesh, values: np.ndarray, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    nr, nc = mesh.lattice_shape
    P = mesh.points.reshape(nr, nc, 3).astype(np.float64)
    xs, zs = P[0, :, 0], P[:, 0, 2]
    ci = np.interp(x, xs, np.arange(nc))
    ri = np.interp(z, zs, np.arange(nr))
    return ground_detail.splat_bilinear(values.reshape(nr, nc, -1), ri, ci)


def bake_near(layer: ground_detail.DetailLayer, splat: np.ndarray, height: np.ndarray, cell_m: float,
              origin_m: tuple[float, float], mesh, square, texels: int,
              rows_per_chunk: int = 128, window: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """(albedo linear RGB, normal encoded 0..1), (texels, texels, 3) each,
    row 0 the square's north edge: the triplanar blend (ground_detail.blend)
    at each texel's point on the mesh, the normal tilted from the height
    grid's and written in the tangent frame of the mesh's (s east, t north),
    as a DCC's UsdPreviewSurface reads it. splat and height may be a window
    of the world's whose first cell is `window` (row, col), with a cell
    around the square's for the gradient (near_window); origin_m is the
    world's, so the taps are the whole grid's, shifted exactly."""
    from worldlib.terrain.mesh import height_on_mesh

    x0, x1, z0, z1 = square
    tx, tz = (x1 - x0) / texels, (z1 - z0) / texels
    x = x0 + (np.arange(texels) + 0.5) * tx
    gz, gx = np.gradient(np.asarray(height, np.float64), cell_m)
    grid_n = np.stack([-gx, np.ones_like(gx), -gz], -1)
    albedo = np.zeros((texels, texels, 3), np.float32)
    normal = np.zeros((texels, texels, 3), np.float32)
    for r0 in range(0, texels, rows_per_chunk):
        z = z0 + (np.arange(r0, min(r0 + rows_per_chunk, texels)) + 0.5) * tz
        X, Z = (a.ravel() for a in np.meshgrid(x, z))
        rows = (Z - origin_m[1]) / cell_m - 0.5 - window[0]  # an integer off a float: exact
        cols = (X - origin_m[0]) / cell_m - 0.5 - window[1]
        pos = np.stack([X, height_on_mesh(mesh, X, Z), Z], -1)
        n = ground_detail.splat_bilinear(grid_n, rows, cols)
        w = ground_detail.splat_bilinear(splat, rows, cols)
        a, nw = ground_detail.blend(layer, w, pos, n, np.full(len(X), min(tx, tz)))
        nm = _lattice_bilinear(mesh, mesh.normals.astype(np.float64), X, Z)
        nm /= np.linalg.norm(nm, axis=1, keepdims=True)
        t_axis = np.array([1.0, 0.0, 0.0]) - nm[:, :1] * nm  # s (east) along the surface
        t_axis /= np.linalg.norm(t_axis, axis=1, keepdims=True)
        b_axis = np.cross(nm, t_axis)  # t (north): n x s points north for an upward n
        ts = np.stack([(nw * t_axis).sum(1), (nw * b_axis).sum(1), (nw * nm).sum(1)], -1)
        k = slice(r0, r0 + len(z))
        albedo[k] = a.reshape(len(z), texels, 3)
        normal[k] = (0.5 * ts / np.linalg.norm(ts, axis=1, keepdims=True) + 0.5).reshape(len(z), texels, 3)
    return albedo, normal


def author_detail_graph(stage, folder_files: dict) -> None:
    """The detail NodeGraph in the ground material (its meshes carry
    primvar st_detail: detail_primvar). folder_files: {"detail/<type>_albedo.png":
    ..., splat files}: the relative names (each authored as "./name")."""
    from pxr import Sdf, UsdShade

    graph = UsdShade.NodeGraph.Define(stage, DETAIL_GRAPH)
    graph.GetPrim().SetDocumentation(
        "Ground detail: per ground type albedo and normal textures tiling in metres (st_detail / tile_m) and "
        "splat weights (st). Blend: albedo = sum_k weight_k * albedo_k, normal = the same sum of the tangent "
        "normals; triplanar on steep ground (project x-z, z-y, x-y by |normal|^4). Plain UsdPreviewSurface "
        "cannot blend: it shows the UDIM bake, and the GroundNear subset the blend baked.")
    base = DETAIL_GRAPH
    reader = _shader(stage, f"{base}/StDetail", "UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st_detail")
    st_reader = _shader(stage, f"{base}/St", "UsdPrimvarReader_float2")
    st_reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    for name, types in SPLAT_FILES:
        tex = _texture(stage, f"{base}/{Path(name).stem.title().replace('_', '')}", name, "raw", st_reader, "clamp")
        for c, t in zip("rgb", types):
            out = tex.CreateOutput(c, Sdf.ValueTypeNames.Float)
            graph.CreateOutput(f"{t}_weight", Sdf.ValueTypeNames.Float).ConnectToSource(out)
    for t in GROUND_TYPES:
        xf = _shader(stage, f"{base}/{t}_st", "UsdTransform2d")
        xf.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        scale = 1.0 / ground_detail.DETAIL_SETS[t].tile_m
        xf.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set((scale, scale))
        xf.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        albedo = _texture(stage, f"{base}/{t}_albedo", f"detail/{t}_albedo.png", "sRGB", xf, "repeat")
        graph.CreateOutput(f"{t}_albedo", Sdf.ValueTypeNames.Color3f).ConnectToSource(
            albedo.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
        nmap = _texture(stage, f"{base}/{t}_normal", f"detail/{t}_normal.png", "raw", xf, "repeat", normal=True)
        graph.CreateOutput(f"{t}_normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
            nmap.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))


def detail_primvar(mesh_prim, mesh) -> None:
    """Primvar st_detail = (x, -z) in metres of a ground mesh."""
    from pxr import Sdf, UsdGeom, Vt

    p = mesh.points.astype(np.float64)
    UsdGeom.PrimvarsAPI(mesh_prim).CreatePrimvar("st_detail", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.vertex).Set(
        Vt.Vec2fArray.FromNumpy(np.stack([p[:, 0], -p[:, 2]], -1).astype(np.float32)))


def _shader(stage, path: str, shader_id: str):
    from pxr import UsdShade

    s = UsdShade.Shader.Define(stage, path)
    s.CreateIdAttr(shader_id)
    return s


def _texture(stage, path: str, file: str, colour_space: str, st_source, wrap: str, normal: bool = False):
    from pxr import Gf, Sdf

    tex = _shader(stage, path, "UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./" + file)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
    tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap)
    tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(wrap)
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_source.ConnectableAPI(), "result")
    if normal:  # stored 0..1: to -1..1 (UsdPreviewSurface's normal input)
        tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2.0, 2.0, 2.0, 1.0))
        tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(-1.0, -1.0, -1.0, 0.0))
    return tex


def author_near_subset(stage, mesh_prim, mesh, near: dict) -> bool:
    """Primvar st_near and the GeomSubset NEAR_SUBSET_NAME of the mesh's
    triangles inside near["square"] (none: nothing authored, False), and
    REST_SUBSET_NAME of the others; the caller binds them to
    author_near_material's material and the ground's. The rest has its
    subset because Blender 5.0, given material subsets, draws the faces
    outside them with the first subset's material, not the mesh's."""
    from pxr import Sdf, UsdGeom, UsdShade, Vt

    faces = near_faces(mesh, near["square"])
    if not len(faces):
        return False
    x0, x1, z0, z1 = near["square"]
    p = mesh.points.astype(np.float64)
    st = np.stack([(p[:, 0] - x0) / (x1 - x0), 1.0 - (p[:, 2] - z0) / (z1 - z0)], -1).astype(np.float32)
    UsdGeom.PrimvarsAPI(mesh_prim).CreatePrimvar("st_near", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.vertex).Set(Vt.Vec2fArray.FromNumpy(st))
    geom = UsdGeom.Mesh(mesh_prim)
    rest = np.setdiff1d(np.arange(len(mesh.face_vertex_indices) // 3, dtype=np.int32), faces)
    for name, indices in ((NEAR_SUBSET_NAME, faces), (REST_SUBSET_NAME, rest)):
        if len(indices):
            subset = UsdGeom.Subset.Define(stage, mesh_prim.GetPath().AppendChild(name))
            subset.CreateElementTypeAttr(UsdGeom.Tokens.face)
            subset.CreateFamilyNameAttr(UsdShade.Tokens.materialBind)
            subset.CreateIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
    UsdGeom.Subset.SetFamilyType(geom, UsdShade.Tokens.materialBind, UsdGeom.Tokens.partition)
    return True


def author_near_material(stage, near: dict):
    """GroundNear: a plain UsdPreviewSurface reading the near square's baked
    textures through primvar st_near."""
    from pxr import Sdf, UsdShade

    material = UsdShade.Material.Define(stage, NEAR_MATERIAL)
    surface = _shader(stage, f"{NEAR_MATERIAL}/Surface", "UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(near["roughness"]))
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    reader = _shader(stage, f"{NEAR_MATERIAL}/StNearReader", "UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st_near")
    albedo = _texture(stage, f"{NEAR_MATERIAL}/Albedo", near["albedo"], "sRGB", reader, "clamp")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        albedo.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    nmap = _texture(stage, f"{NEAR_MATERIAL}/Normal", near["normal"], "raw", reader, "clamp", normal=True)
    surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
        nmap.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


def near_texels_m(square, texels: int) -> float:
    return max(square[1] - square[0], square[3] - square[2]) / max(texels, 1)


def near_window(square, shape: tuple[int, int], cell_m: float, origin_m: tuple[float, float],
                margin: int = 2) -> tuple[int, int, int, int]:
    """(row0, col0, rows, cols) of the cells bake_near reads for the square:
    its bilinear taps and `margin` cells around them (the gradient's
    neighbours), within the world."""
    x0, x1, z0, z1 = square

    def span(lo_m, hi_m, o, n):
        lo = int(np.floor((lo_m - o) / cell_m - 0.5)) - margin
        hi = int(np.floor((hi_m - o) / cell_m - 0.5)) + 1 + margin
        return max(lo, 0), min(hi, n - 1) + 1

    r0, r1 = span(z0, z1, origin_m[1], shape[0])
    c0, c1 = span(x0, x1, origin_m[0], shape[1])
    return r0, c0, r1 - r0, c1 - c0


def write_near(folder: Path, layer, read_splat, read_height, shape: tuple[int, int], cell_m, origin_m, mesh, size_m,
               offset_m, max_texels, texel_m) -> dict:
    """Bake and write the near square's textures at texel_m, at most
    max_texels per side, from the splat and height windows around it
    (read_*(row0, col0, rows, cols)); the dict author_detail takes (without
    roughness)."""
    square = near_square(mesh, size_m, offset_m)
    texels = int(min(max_texels, math.ceil(max(square[1] - square[0], square[3] - square[2]) / texel_m - 1e-9)))
    window = near_window(square, shape, cell_m, origin_m)
    albedo, normal = bake_near(layer, read_splat(*window), read_height(*window), cell_m, origin_m, mesh, square, texels,
                               window=window[:2])
    images.write_png(folder / "near_albedo.png", albedo, srgb=True)
    images.write_png(folder / "near_normal.png", normal, srgb=False)
    return {"square": [float(v) for v in square], "albedo": "near_albedo.png", "normal": "near_normal.png",
            "texel_m": near_texels_m(square, texels)}
