"""The terrain mesh in tiles, each a payload with its own LODs.

In terrain.usdc, /World/Terrain/Ground (Xform) holds one Mesh per tile,
Tile_x<column>_y<row> (x east, y south, from the north-west corner), with
what every LOD shares: subdivisionScheme none, orientation, the extent of
all its LODs, the Ground material's binding, customData worldbake:tile
(lattice lines, bounds in metres, each LOD's vertical error), and a variant
set `lod` (LOD_STRIDES: full, half, quarter) whose variants each hold one
payload: the prim /Full, /Half or /Quarter of terrain/tile_x<i>_y<j>.usdc,
beside terrain.usdc. The world selects `full`; a DCC opens the world with
the tiles unloaded (Usd.Stage.LoadNone) and loads those it wants, at the
LOD it selects (dcc_layer.py selects coarser ones for far tiles).

Where the water (the hydrology's rivers and lakes) crosses a tile, its
coarse LODs are carved: the vertices of the triangles under a water point
whose surface would rise above the water are lowered until it is
WATER_CARVE_DEPTH_M under it (a coarse LOD spans a narrow valley above its
river, and a DCC that draws far tiles coarse would bury the rivers); the
lod_error_m the selection reads counts that lowering.

Each LOD mesh holds the geometry: points, triangles, vertex normals and
primvars st (over the whole world: the one ground texture still maps),
st_udim, st_detail and st_near when the ground has them, and the near
square's GeomSubset `Near` with `Rest`, the tile's other triangles (bound in
terrain.usdc: a payload cannot target a material outside itself). Its vertices are the whole lattice's own
(worldlib.terrain.mesh.terrain_tile): tiles share their border vertices
bitwise, and a coarse LOD keeps its border at full resolution, so tiles at
any LODs meet without cracks.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from worldlib.terrain.mesh import (LOD_STRIDES, TerrainMesh, TileMesh, carve_lod, lod_error_m, terrain_tile,
                                   tile_edges)

GROUND = "/World/Terrain/Ground"
TILES_DIR = "terrain"  # beside terrain.usdc: one layer per tile
TILE_KEY = "worldbake:tile"  # the tile prim's customData
DEFAULT_LOD = "full"
WATER = "/World/Water"  # the hydrology's water layer: river ribbons and lakes
# a coarse LOD's ground is lowered to this far under the water surface where it would rise above it (the
# full LOD's ground under a river is its bed, a bed depth down)
WATER_CARVE_DEPTH_M = 0.3


def water_points(water_layer: Path) -> np.ndarray:
    """(n, 3) float64: the centre of every face and every vertex of the
    water's meshes (river ribbons, lakes) in world coordinates: points on
    the water surface, inside it and on its banks."""
    from pxr import Usd

    from pipeline.usdio import mesh_in_world

    stage = Usd.Stage.Open(str(water_layer))
    root = stage.GetPrimAtPath(WATER)
    out = []
    for arrays in (mesh_in_world(prim) for prim in (Usd.PrimRange(root) if root else [])):
        if arrays is None:
            continue
        pts, counts, idx = arrays
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tri = counts >= 3  # each face's first three corners: their centre lies inside a convex face
        out += [pts, pts[idx[starts[tri, None] + np.arange(3)[None]]].mean(axis=1)]
    return np.concatenate(out) if out else np.zeros((0, 3))


def tile_name(col: int, row: int) -> str:
    return f"Tile_x{col}_y{row}"


def tile_file(col: int, row: int) -> str:
    return f"{TILES_DIR}/tile_x{col}_y{row}.usdc"


def lod_prim(lod: str) -> str:
    return "/" + lod.title()


def _vec2(values: np.ndarray):
    from pxr import Vt

    return Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(values, np.float32))


def _extent(ext: np.ndarray):
    from pxr import Gf, Vt

    return Vt.Vec3fArray([Gf.Vec3f(*map(float, ext[0])), Gf.Vec3f(*map(float, ext[1]))])


def author_lod_mesh(stage, path: str, tile: TileMesh, udim_tiles: int | None, detail: bool,
                    near: dict | None) -> bool:
    """The LOD's Mesh at path with its geometry and primvars (see the
    module); returns whether it has faces in the near square."""
    from pxr import Sdf, UsdGeom, Vt

    from .ground_near import author_near_subset, detail_primvar

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # the default catmullClark would ignore normals
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(tile.points))
    nfaces = len(tile.face_vertex_indices) // 3
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(nfaces, 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tile.face_vertex_indices))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(tile.normals))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateExtentAttr(_extent(tile.extent))
    pv = UsdGeom.PrimvarsAPI(mesh)
    pv.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(_vec2(tile.st))
    if udim_tiles is not None:
        pv.CreatePrimvar("st_udim", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
            _vec2(tile.st * np.float32(udim_tiles)))
    if detail:
        detail_primvar(mesh.GetPrim(), tile)
    return near is not None and author_near_subset(stage, mesh.GetPrim(), tile, near)


def write_tile_layer(path: Path, lods: dict[str, TileMesh], udim_tiles: int | None, detail: bool, near: dict | None,
                     provenance: dict) -> set[str]:
    """The tile's layer: one Mesh per LOD at lod_prim(lod), /Full the
    defaultPrim; returns the LODs with a near subset."""
    from pxr import Usd, UsdGeom

    from pipeline import usdio

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    usdio.set_provenance(stage.GetRootLayer(), provenance)
    with_near = {lod for lod, tile in lods.items()
                 if author_lod_mesh(stage, lod_prim(lod), tile, udim_tiles, detail, near)}
    stage.SetDefaultPrim(stage.GetPrimAtPath(lod_prim(DEFAULT_LOD)))
    stage.GetRootLayer().Save()
    return with_near


def write_terrain_tiles(stage, folder: Path, mesh: TerrainMesh, tile_quads: int, material, udim_tiles: int | None,
                        detail: bool, near: dict | None, near_material, provenance: dict,
                        water: np.ndarray | None = None) -> dict:
    """GROUND in `stage` (the terrain layer, at folder) and the tile layers
    under folder/TILES_DIR; returns metrics (tiles, vertices and triangles
    per LOD, largest LOD error, vertices lowered). water: points on the
    water surface (water_points): the coarse LODs are carved under them
    (worldlib.terrain.mesh.carve_lod), so a DCC that draws far tiles coarse
    still shows the rivers."""
    from pxr import Sdf, UsdGeom, UsdShade, Vt

    UsdGeom.Xform.Define(stage, GROUND)
    stage.Unload(GROUND)  # the tiles' payloads stay unloaded while they are authored here
    (folder / TILES_DIR).mkdir(exist_ok=True)
    nr, nc = mesh.lattice_shape
    rows, cols = tile_edges(nr, tile_quads), tile_edges(nc, tile_quads)
    counts = {lod: [0, 0] for lod in LOD_STRIDES}
    worst = {lod: 0.0 for lod in LOD_STRIDES}
    carved = {lod: 0 for lod in LOD_STRIDES}
    water = np.zeros((0, 3)) if water is None else np.asarray(water, np.float64)
    for j in range(len(rows) - 1):
        for i in range(len(cols) - 1):
            span_r, span_c = (int(rows[j]), int(rows[j + 1])), (int(cols[i]), int(cols[i + 1]))
            lods = {}
            for lod, s in LOD_STRIDES.items():
                lods[lod], lowered = carve_lod(mesh, terrain_tile(mesh, span_r, span_c, s), span_r, span_c, s, water,
                                               WATER_CARVE_DEPTH_M)
                carved[lod] += lowered
            errors = {lod: round(lod_error_m(mesh, t), 3) for lod, t in lods.items()}
            for lod, t in lods.items():
                counts[lod][0] += len(t.points)
                counts[lod][1] += len(t.face_vertex_indices) // 3
                worst[lod] = max(worst[lod], errors[lod])
            with_near = write_tile_layer(folder / tile_file(i, j), lods, udim_tiles, detail, near, provenance)
            prim_path = f"{GROUND}/{tile_name(i, j)}"
            geom = UsdGeom.Mesh.Define(stage, prim_path)
            geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            ext = np.stack([np.min([t.extent[0] for t in lods.values()], 0),  # a carved LOD reaches lower
                            np.max([t.extent[1] for t in lods.values()], 0)])
            geom.CreateExtentAttr(_extent(ext))
            prim = geom.GetPrim()
            UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)
            bounds = [float(mesh.points[rows[j] * nc + cols[i], 0]), float(mesh.points[rows[j] * nc + cols[i], 2]),
                      float(mesh.points[rows[j + 1] * nc + cols[i + 1], 0]),
                      float(mesh.points[rows[j + 1] * nc + cols[i + 1], 2])]
            prim.SetCustomDataByKey(TILE_KEY, {"rows": Vt.IntArray(list(span_r)), "cols": Vt.IntArray(list(span_c)),
                                               "bounds_xz_m": Vt.DoubleArray(bounds),
                                               "height_m": Vt.DoubleArray([float(ext[0][1]), float(ext[1][1])]),
                                               "lod_error_m": {k: float(v) for k, v in errors.items()},
                                               "lod_stride": {k: int(v) for k, v in LOD_STRIDES.items()}})
            vset = prim.GetVariantSets().AddVariantSet("lod")
            for lod in LOD_STRIDES:
                vset.AddVariant(lod)
                vset.SetVariantSelection(lod)
                with vset.GetVariantEditContext():
                    prim.GetPayloads().AddPayload(Sdf.Payload("./" + tile_file(i, j), Sdf.Path(lod_prim(lod))))
            vset.SetVariantSelection(DEFAULT_LOD)
            if with_near:
                from .ground_near import NEAR_SUBSET_NAME, REST_SUBSET_NAME

                for name, bound in ((NEAR_SUBSET_NAME, near_material), (REST_SUBSET_NAME, material)):
                    UsdShade.MaterialBindingAPI.Apply(stage.OverridePrim(f"{prim_path}/{name}")).Bind(bound)
    return {"terrain_tiles": [len(rows) - 1, len(cols) - 1], "terrain_tile_quads": int(tile_quads),
            "terrain_lods": {lod: {"vertices": v, "triangles": t, "max_error_m": worst[lod],
                                   "lowered_under_water": carved[lod]} for lod, (v, t) in counts.items()}}


def tile_prims(stage) -> list:
    """The tile prims of a composed world (loaded or not), in name order."""
    from pxr import Usd

    ground = stage.GetPrimAtPath(GROUND)
    if not ground:
        return []
    kids = ground.GetFilteredChildren(Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract)  # unloaded too
    return [p for p in kids if p.GetCustomDataByKey(TILE_KEY)]
