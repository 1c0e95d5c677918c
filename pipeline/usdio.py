"""USD helpers: stage metadata, provenance, validation.

Conventions: metersPerUnit = 1, upAxis Y, defaultPrim /World of kind
assembly, provenance in customLayerData["worldbake"], asset paths relative
to the layer that authors them.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def create_stage(path: Path | str, provenance: dict[str, Any] | None = None, root: str = "/World", kind: str = "assembly"):
    """A new layer on disk with the conventions authored, and its root prim
    (an Xform) set as defaultPrim. Returns (stage, root_prim)."""
    from pxr import Kind, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    prim = UsdGeom.Xform.Define(stage, root).GetPrim()
    Usd.ModelAPI(prim).SetKind(getattr(Kind.Tokens, kind))
    stage.SetDefaultPrim(prim)
    if provenance is not None:
        set_provenance(stage.GetRootLayer(), provenance)
    return stage, prim


def write_root_layer(path: Path | str, provenance: dict[str, Any], sublayers: list[str], root: str = "/World") -> None:
    """A layer that only composes others: the conventions, /World (kind
    assembly) as defaultPrim, and the sublayers, strongest first. Written with
    Sdf alone so nothing is composed (the relative paths may only resolve once
    the layer is moved into place)."""
    from pxr import Kind, Sdf, UsdGeom

    layer = Sdf.Layer.CreateNew(str(path))
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, UsdGeom.Tokens.y)
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
    prim = Sdf.PrimSpec(layer, root.strip("/"), Sdf.SpecifierDef, "Xform")
    prim.SetInfo("kind", Kind.Tokens.assembly)
    layer.defaultPrim = prim.name
    layer.subLayerPaths = list(sublayers)
    set_provenance(layer, provenance)
    layer.Save()


def set_provenance(layer, provenance: dict[str, Any]) -> None:
    """Stage, version, key, params and seed in customLayerData. Params go in
    as canonical JSON text so any dictionary shape round-trips exactly."""
    data = dict(layer.customLayerData)
    data["worldbake"] = {k: (v if isinstance(v, (str, int, float, bool)) else json.dumps(v, sort_keys=True))
                         for k, v in provenance.items()}
    layer.customLayerData = data


def mesh_in_world(prim):
    """A UsdGeom.Mesh prim's (points in world space float64, face vertex
    counts, face vertex indices); None for another prim or a mesh without
    points or faces."""
    import numpy as np
    from pxr import Usd, UsdGeom

    if not prim.IsA(UsdGeom.Mesh):
        return None
    mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(mesh.GetPointsAttr().Get() or [], np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
    if not len(pts) or not len(counts):
        return None
    xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()), np.float64)
    return pts @ xf[:3, :3] + xf[3, :3], counts, idx  # USD matrices act on row vectors


def relative_asset_path(target: Path | str, layer_path: Path | str) -> str:
    """A path to `target` relative to the folder of the layer that will author
    it, with forward slashes and a leading ./ as USD expects for relative
    anchoring."""
    rel = os.path.relpath(Path(target).resolve(), Path(layer_path).resolve().parent)
    rel = rel.replace(os.sep, "/")
    return rel if rel.startswith("../") else "./" + rel


def validate(path: Path | str) -> list[str]:
    """Every registered pxr.UsdValidation validator over the stage; returns
    the error messages (warnings are ignored)."""
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    registry = UsdValidation.ValidationRegistry()
    validators = registry.GetOrLoadAllValidators()
    context = UsdValidation.ValidationContext(validators)
    errors = []
    for err in context.Validate(stage):
        if err.GetType() == UsdValidation.ValidationErrorType.Error:
            sites = ", ".join(str(s.GetPrim().GetPath()) if s.GetPrim() else str(s.GetLayer().identifier if s.GetLayer() else "")
                              for s in err.GetSites())
            errors.append(f"{err.GetName()}: {err.GetMessage()} [{sites}]")
    return errors
