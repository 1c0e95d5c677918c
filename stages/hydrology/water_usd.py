"""The water layer: /World/Water (kind group) with
- Rivers (component): one UsdGeom.Mesh `Ribbons`, the river surfaces as
  quads between the banks at the water level (subdivisionScheme none, up
  normals, primvars st (s across, t along in units of 10 m) and discharge
  (bankfull, vertex)), customData worldbake:width_by_area (the width table);
- Lakes (component): one UsdGeom.Mesh per lake, a flat surface at the lake
  level, one quad per lake cell grown by one cell so it meets the shore;
- Looks: the water material (worldlib.materials.water_preview_surface) bound
  to every water mesh.
Paths are /World/... so the world stage can sublayer this file."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import usdio
from worldlib.materials import water_preview_surface

WIDTH_TABLE_KEY = "worldbake:width_by_area"


def lake_surface(cells: tuple[np.ndarray, np.ndarray], level: float, dx: float, origin: tuple[float, float]):
    """(points, counts, indices) of quads covering the cells (rows, cols) at
    y = level, wound counter-clockwise seen from +Y (USD rightHanded)."""
    rows, cols = (np.asarray(a, np.int64) for a in cells)
    corners = np.stack([np.stack([rows, cols], 1), np.stack([rows + 1, cols], 1),
                        np.stack([rows + 1, cols + 1], 1), np.stack([rows, cols + 1], 1)], 1).reshape(-1, 2)
    uniq, inv = np.unique(corners, axis=0, return_inverse=True)
    pts = np.stack([origin[0] + uniq[:, 1] * dx, np.full(len(uniq), level), origin[1] + uniq[:, 0] * dx], 1)
    return pts.astype(np.float32), np.full(len(rows), 4, np.int32), inv.reshape(-1).astype(np.int32)


def _mesh(stage, path: str, pts: np.ndarray, counts: np.ndarray, idx: np.ndarray, material):
    """A flat-shaded water mesh (up normals) with its extent and material."""
    from pxr import Gf, UsdGeom, UsdShade, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pts, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(counts, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(idx, np.int32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.tile(np.array([[0, 1, 0]], np.float32), (len(pts), 1))))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    return mesh


def write(path: Path, provenance: dict, ribbons, width_table: list, lakes: list[tuple[int, float, np.ndarray]],
          dx: float, origin: tuple[float, float]) -> dict:
    """The layer: the river ribbons (channels.Ribbons), the width table
    (channels.width_table) and the lakes ((id, level, (rows, cols) of its cells) each)."""
    from pxr import Kind, Sdf, Usd, UsdGeom, Vt

    stage, _ = usdio.create_stage(path, provenance)
    water = UsdGeom.Xform.Define(stage, "/World/Water")
    Usd.ModelAPI(water).SetKind(Kind.Tokens.group)
    UsdGeom.Scope.Define(stage, "/World/Water/Looks")
    material = water_preview_surface(stage, "/World/Water/Looks/Water")
    info = {"usd_river_meshes": 0, "usd_river_quads": 0, "usd_lakes": 0, "usd_lake_quads": 0}

    rivers = UsdGeom.Xform.Define(stage, "/World/Water/Rivers")
    Usd.ModelAPI(rivers).SetKind(Kind.Tokens.component)
    if width_table:  # columns of floats (an open upper bound is -1)
        rivers.GetPrim().SetCustomDataByKey(WIDTH_TABLE_KEY, {
            k: Vt.DoubleArray([float(r[k]) if r[k] is not None else -1.0 for r in width_table]) for k in width_table[0]})
    if len(ribbons.counts):
        mesh = _mesh(stage, "/World/Water/Rivers/Ribbons", ribbons.points, ribbons.counts, ribbons.indices, material)
        pv = UsdGeom.PrimvarsAPI(mesh)
        pv.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec2fArray.FromNumpy(ribbons.st))
        pv.CreatePrimvar("discharge", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
            Vt.FloatArray.FromNumpy(ribbons.discharge))
        info.update(usd_river_meshes=1, usd_river_quads=int(len(ribbons.counts)))

    lakes_x = UsdGeom.Xform.Define(stage, "/World/Water/Lakes")
    Usd.ModelAPI(lakes_x).SetKind(Kind.Tokens.component)
    for lid, level, cells in lakes:
        pts, counts, idx = lake_surface(cells, level, dx, origin)
        mesh = _mesh(stage, f"/World/Water/Lakes/Lake_{lid:05d}", pts, counts, idx, material)
        mesh.GetPrim().SetCustomDataByKey("worldbake:water_level_m", float(level))
        info["usd_lakes"] += 1
        info["usd_lake_quads"] += int(len(counts))
    stage.GetRootLayer().Save()
    return info
