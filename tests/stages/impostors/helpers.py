"""A tiny plants layer in the plants stage's layout, written with USD alone
(so the impostor tests do not build L-systems): /Plants (kind group) with
`tree` (a box trunk and a crown of leaf quads, displayColor) and `grass`
(a tuft of blade quads), each referencing its own file with a `lod`
variant set (LOD0, LOD1) and customData worldbake:lods."""
import json
from pathlib import Path

import numpy as np


def _mesh(stage, path, points, quads, colour):
    from pxr import Gf, UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tris.ravel(), np.int32)))
    mesh.CreateDoubleSidedAttr(True)
    mesh.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*colour)]))
    lo, hi = points.min(0), points.max(0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))


def _box(c, h):
    c, h = np.asarray(c, float), np.asarray(h, float)
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    return c + s * h, quads


def _leaves(rng, n, centre, radius, size):
    pts, quads = [], []
    for k in range(n):
        p = centre + radius * rng.uniform(-1, 1, 3) * np.array([1, 0.8, 1])
        a, b = rng.normal(size=3), rng.normal(size=3)
        a /= np.linalg.norm(a)
        b -= a * (a @ b)
        b /= np.linalg.norm(b)
        pts += [p - size * a - size * b, p + size * a - size * b, p + size * a + size * b, p - size * a + size * b]
        quads.append(np.arange(4) + 4 * k)
    return np.array(pts), np.array(quads)


def _asset(folder: Path, name: str, levels):
    from pxr import Kind, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(folder / f"{name}.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdGeom.Xform.Define(stage, f"/{name}")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root).SetKind(Kind.Tokens.component)
    vset = root.GetPrim().GetVariantSets().AddVariantSet("lod")
    for k, parts in enumerate(levels):
        vset.AddVariant(f"LOD{k}")
        vset.SetVariantSelection(f"LOD{k}")
        with vset.GetVariantEditContext():
            UsdGeom.Xform.Define(stage, f"/{name}/Geom")
            for part, (pts, quads, colour) in parts.items():
                _mesh(stage, f"/{name}/Geom/{part}", pts, quads, colour)
    vset.SetVariantSelection("LOD0")
    root.GetPrim().SetCustomDataByKey("worldbake:lods", json.dumps(
        [{"level": k, "hausdorff_m": 0.02 * k} for k in range(len(levels))]))
    stage.GetRootLayer().Save()


def make_plants(folder: Path, leaves: int = 300) -> Path:
    """plants.usda in `folder`; returns its path."""
    from pxr import Kind, Usd, UsdGeom

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(5)
    trunk = _box((0, 1.0, 0), (0.12, 1.0, 0.12))
    crown = _leaves(rng, leaves, np.array([0, 2.6, 0]), 1.1, 0.18)
    tree0 = {"Wood": (*trunk, (0.3, 0.2, 0.1)), "Leaves": (*crown, (0.1, 0.35, 0.08))}
    tree1 = {"Wood": (*trunk, (0.3, 0.2, 0.1)), "Leaves": (crown[0], crown[1][::2], (0.1, 0.35, 0.08))}
    _asset(folder, "tree", [tree0, tree1])
    blades, quads = [], []
    for k in range(24):
        a = 2 * np.pi * k / 24
        base = 0.04 * np.array([np.cos(a), 0, np.sin(a)])
        side = 0.006 * np.array([-np.sin(a), 0, np.cos(a)])
        tip = base * 4 + np.array([0, 0.35 + 0.05 * np.sin(3 * a), 0])
        blades += [base - side, base + side, tip + side * 0.2, tip - side * 0.2]
        quads.append(np.arange(4) + 4 * k)
    grass0 = {"Blades": (np.array(blades), np.array(quads), (0.15, 0.4, 0.1))}
    _asset(folder, "grass", [grass0, grass0])
    stage = Usd.Stage.CreateNew(str(folder / "plants.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdGeom.Xform.Define(stage, "/Plants")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root).SetKind(Kind.Tokens.group)
    for name in ("tree", "grass"):
        UsdGeom.Xform.Define(stage, f"/Plants/{name}").GetPrim().GetReferences().AddReference(f"./{name}.usda")
    stage.GetRootLayer().Save()
    return folder / "plants.usda"
