"""The water layer: /World/Water (kind group) with
- Rivers (component): one UsdGeom.BasisCurves, linear, per-vertex widths,
  primvars discharge (vertex) and strahler (uniform);
- Lakes (component): one UsdGeom.Mesh per lake, a flat surface at the lake
  level (subdivisionScheme none, normals, extent), one quad per lake cell
  grown by one cell so it meets the shore;
- Looks: a UsdPreviewSurface water material bound to both.
Paths are /World/... so the world stage can sublayer this file."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import usdio


def _material(stage, path: str, colour, opacity: float, roughness: float):
    from pxr import Gf, Sdf, UsdShade

    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, path + "/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(float(opacity))
    surface.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.33)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


def lake_surface(mask: np.ndarray, level: float, dx: float, origin: tuple[float, float]):
    """(points, counts, indices) of quads covering the mask's cells at y = level,
    wound counter-clockwise seen from +Y (USD rightHanded)."""
    rows, cols = np.nonzero(mask)  # (a full-grid mask; only its cells are used)
    corners = np.stack([np.stack([rows, cols], 1), np.stack([rows + 1, cols], 1),
                        np.stack([rows + 1, cols + 1], 1), np.stack([rows, cols + 1], 1)], 1).reshape(-1, 2)
    uniq, inv = np.unique(corners, axis=0, return_inverse=True)
    pts = np.stack([origin[0] + uniq[:, 1] * dx, np.full(len(uniq), level), origin[1] + uniq[:, 0] * dx], 1)
    return pts.astype(np.float32), np.full(len(rows), 4, np.int32), inv.reshape(-1).astype(np.int32)


def write(path: Path, provenance: dict, curves_pts: list[np.ndarray], curves_w: list[np.ndarray],
          curves_q: list[np.ndarray], curves_order: list[int], lakes: list[tuple[int, float, np.ndarray]],
          dx: float, origin: tuple[float, float], colour=(0.05, 0.16, 0.22), opacity=0.75, roughness=0.05) -> dict:
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, Vt

    stage, _ = usdio.create_stage(path, provenance)
    water = UsdGeom.Xform.Define(stage, "/World/Water")
    Usd.ModelAPI(water).SetKind(Kind.Tokens.group)
    info = {"usd_river_curves": 0, "usd_river_vertices": 0, "usd_lakes": 0, "usd_lake_quads": 0}

    rivers = UsdGeom.Xform.Define(stage, "/World/Water/Rivers")
    Usd.ModelAPI(rivers).SetKind(Kind.Tokens.component)
    UsdGeom.Scope.Define(stage, "/World/Water/Rivers/Looks")
    mat_r = _material(stage, "/World/Water/Rivers/Looks/RiverWater", colour, opacity, roughness)
    if curves_pts:
        pts = np.concatenate(curves_pts).astype(np.float32)
        widths = np.concatenate(curves_w).astype(np.float32)
        q = np.concatenate(curves_q).astype(np.float32)
        bc = UsdGeom.BasisCurves.Define(stage, "/World/Water/Rivers/Streams")
        bc.CreateTypeAttr(UsdGeom.Tokens.linear)
        bc.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.array([len(p) for p in curves_pts], np.int32)))
        bc.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        bc.CreateWidthsAttr(Vt.FloatArray.FromNumpy(widths))
        bc.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        pv = UsdGeom.PrimvarsAPI(bc)
        pv.CreatePrimvar("discharge", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(q))
        pv.CreatePrimvar("strahler", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(
            Vt.IntArray.FromNumpy(np.array(curves_order, np.int32)))
        ext = UsdGeom.BasisCurves.ComputeExtent(Vt.Vec3fArray.FromNumpy(pts), Vt.FloatArray.FromNumpy(widths))
        bc.CreateExtentAttr(ext)
        UsdShade.MaterialBindingAPI.Apply(bc.GetPrim()).Bind(mat_r)
        info.update(usd_river_curves=len(curves_pts), usd_river_vertices=int(len(pts)))

    lakes_x = UsdGeom.Xform.Define(stage, "/World/Water/Lakes")
    Usd.ModelAPI(lakes_x).SetKind(Kind.Tokens.component)
    UsdGeom.Scope.Define(stage, "/World/Water/Lakes/Looks")
    mat_l = _material(stage, "/World/Water/Lakes/Looks/LakeWater", colour, opacity, roughness)
    for lid, level, mask in lakes:
        pts, counts, idx = lake_surface(mask, level, dx, origin)
        mesh = UsdGeom.Mesh.Define(stage, f"/World/Water/Lakes/Lake_{lid:05d}")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(idx))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.tile(np.array([[0, 1, 0]], np.float32), (len(pts), 1))))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        mesh.GetPrim().SetCustomDataByKey("worldbake:water_level_m", float(level))
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat_l)
        info["usd_lakes"] += 1
        info["usd_lake_quads"] += int(len(counts))
    stage.GetRootLayer().Save()
    return info
