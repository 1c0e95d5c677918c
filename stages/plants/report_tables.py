"""The report's tables of the composed world.usda: instances per prototype
(over every PointInstancer) and the triangles each plant asset's `lod`
variants draw, with the distance each is drawn from. Declared in
STAGE.report (pipeline.contract.ReportTable)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.contract import Table

LOD_SET = "lod"  # the variant set of a plant asset (asset.py)
SWITCH_KEY = "worldbake:lod_switch_m"  # customData: the distance each variant is drawn from (impostors)


def instance_and_lod_tables(world_usda: Path) -> tuple[Table, ...]:
    """Instances per prototype with their triangles at LOD0, and the
    triangles of every asset's lod variants with their distances."""
    instances, lods = lod_counts(world_usda)
    tables = []
    if instances:
        tri_per = {r["asset"]: r["lods"] for r in lods}
        rows = []
        for r in instances:
            lod0 = next(iter(tri_per.get(r["prototype"], {}).values()), None)
            rows.append((r["prototype"], r["instances"], lod0 * r["instances"] if lod0 is not None else None))
        tables.append(Table(("prototype", "instances", "triangles at LOD0 (all instances)"), tuple(rows),
                            footer=("total", sum(r["instances"] for r in instances), "")))
    if lods:
        names = sorted({n for r in lods for n in r["lods"]})
        rows = []
        for r in lods:
            dist = r["from_m"]
            rows.append((r["asset"],) + tuple(
                None if n not in r["lods"] else (r["lods"][n], f"from {dist[n]:,.0f} m") if n in dist else r["lods"][n]
                for n in names))
        tables.append(Table(("asset",) + tuple(f"{n} triangles" for n in names), tuple(rows), note=(
            f"from: the distance from which the asset's LOD ladder draws that LOD (customData {SWITCH_KEY}, from "
            "each LOD's measured error at one pixel on the reference screen); a LOD without a distance is not on "
            "the ladder.")))
    return tuple(tables)


def lod_counts(world_usda: Path) -> tuple[list[dict], list[dict]]:
    """Instances per prototype (over every PointInstancer) and, for every
    prim of the composed world with a `lod` variant set (abstract prototype
    classes included), the triangles a renderer draws in each variant:
    active, visible meshes of purpose default or render."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world_usda))
    per_proto: dict[str, int] = {}
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            inst = UsdGeom.PointInstancer(prim)
            protos = inst.GetPrototypesRel().GetTargets()
            idx = np.asarray(inst.GetProtoIndicesAttr().Get() or [], np.int64)
            counts = np.bincount(idx, minlength=len(protos)) if len(idx) else np.zeros(len(protos), int)
            for p, n in zip(protos, counts):
                per_proto[p.name] = per_proto.get(p.name, 0) + int(n)
            it.PruneChildren()
    # payloads unloaded (tiles hold only instances of the prototypes); an instance shares its prototype's rows
    unloaded = Usd.Stage.Open(str(world_usda), Usd.Stage.LoadNone)
    with_lods = [p.GetPath() for p in Usd.PrimRange.AllPrims(unloaded.GetPseudoRoot())
                 if not p.IsInstance() and LOD_SET in p.GetVariantSets().GetNames()]
    lods = []
    if with_lods:
        # masked to those prims, the variant switches (in the session layer) recompose only them
        masked = Usd.Stage.OpenMasked(str(world_usda), Usd.StagePopulationMask(with_lods), Usd.Stage.LoadNone)
        masked.SetEditTarget(masked.GetSessionLayer())
        for path in with_lods:
            prim = masked.GetPrimAtPath(path)
            vset = prim.GetVariantSets().GetVariantSet(LOD_SET)
            row = {"asset": path.name, "lods": {}, "from_m": _switch_distances(prim)}
            for name in vset.GetVariantNames():
                vset.SetVariantSelection(name)
                row["lods"][name] = _drawn_triangles(masked.GetPrimAtPath(path))
            lods.append(row)
    instances = [{"prototype": k, "instances": v} for k, v in sorted(per_proto.items())]
    return instances, lods


def _switch_distances(prim) -> dict[str, float]:
    """The distance from which each `lod` variant is drawn, as the asset
    publishes it (customData worldbake:lod_switch_m: variant_m, else
    ladder_m); {} when it does not."""
    text = prim.GetCustomDataByKey(SWITCH_KEY)
    try:
        data = json.loads(text) if isinstance(text, str) else {}
        ladder = data["variant_m"] if "variant_m" in data else data["ladder_m"]
        return {str(k): float(v) for k, v in ladder.items() if isinstance(v, (int, float))}
    except (ValueError, KeyError, TypeError, AttributeError):
        return {}


def _drawn_triangles(prim) -> int:
    from pxr import Usd, UsdGeom

    tris = 0
    for p in Usd.PrimRange(prim, Usd.PrimIsActive & Usd.PrimIsDefined):  # prototypes are abstract classes
        if not p.IsA(UsdGeom.Mesh):
            continue
        imageable = UsdGeom.Imageable(p)
        if imageable.ComputeVisibility() == UsdGeom.Tokens.invisible or \
                imageable.ComputePurpose() not in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render):
            continue
        c = np.asarray(UsdGeom.Mesh(p).GetFaceVertexCountsAttr().Get() or [], np.int64)
        tris += int((c - 2).clip(0).sum())
    return tris
