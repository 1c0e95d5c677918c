"""The instances layer (instances.usdc):

/World (assembly)
  Vegetation (Xform, kind group)
    Prototypes (class Scope: not drawn; one class prim per placed species)
      <species> (Xform, kind component): Placeholder (Cone, purpose proxy,
                 the species' height_m), customData asset hint
    q (Xform, kind group): the quadtree root tile; children q0 (north-west),
      q1 (north-east), q2 (south-west), q3 (south-east), q01 ... down to the
      leaves, each a payload of tiles/q<digits>.usdc (defaultPrim /Tile, kind
      group, so a viewer can open the world with the tiles unloaded and load
      the ones it wants), which holds
      <species> (PointInstancer, kind group): positions, orientations (half
                 quaternions), scales, protoIndices, ids, primvars age,
                 random and tint (per instance: interpolation vertex), extent
        Prototypes (Scope, kind group)
          <species> (Xform, kind component, instanceable) inherits
                    /World/Vegetation/Prototypes/<species>: every tile's
                    prototype shares one USD prototype, so the species'
                    meshes exist once however many tiles there are

Every tile carries extentsHint and customData (bounds in metres, instance
counts). The prototype of every instancer inherits one class prim per
species, so a stronger layer that adds a reference to the plant asset on
/World/Vegetation/Prototypes/<species> (and deactivates its Placeholder)
swaps the asset into every tile at once.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from worldlib.plant_asset import VEGETATION_PROTOTYPES, plant_asset_prim, prototype_prim

from .placement import Instances

TILES_DIR = "tiles"  # beside the layer: one payload file per leaf tile
FOREST_BY_SLOPE_KEY = "worldbake:forest_by_slope"  # customData of /World/Vegetation: sites.forest_by_slope
BANKS_KEY = "worldbake:plants_on_banks"  # customData of /World/Vegetation: sites.plants_on_banks

PALETTE = {  # displayColor of the placeholders and preview dots
    "conifer": (0.04, 0.22, 0.16), "broadleaf": (0.45, 0.80, 0.12), "shrub": (0.80, 0.55, 0.20),
    "grass": (0.60, 0.80, 0.35),
}


def colour(name: str, k: int) -> tuple[float, float, float]:
    if name in PALETTE:
        return PALETTE[name]
    rng = np.random.default_rng(k + 17)
    return tuple(float(v) for v in 0.2 + 0.6 * rng.random(3))


@dataclass
class Tile:
    path: str  # quadtree digits after "q"
    x0: float
    z0: float
    size: float
    index: dict[str, np.ndarray] = field(default_factory=dict)  # species -> instance indices
    children: list["Tile"] = field(default_factory=list)

    @property
    def count(self) -> int:
        return sum(len(v) for v in self.index.values())


def build_quadtree(sets: dict[str, Instances], x0: float, z0: float, size: float, max_instances: int,
                   min_size: float) -> Tile:
    """Split the square until a tile holds at most max_instances (or is at
    min_size). Points on a split line go to the east / south tile."""
    def split(tile: Tile) -> Tile:
        if tile.count <= max_instances or tile.size / 2 < min_size:
            return tile
        h = tile.size / 2
        quadrant = {}  # per species: child k = east + 2 south of each instance, its indices grouped by child
        for name, ii in tile.index.items():
            p = sets[name].positions[ii]
            q = (p[:, 0] >= tile.x0 + h).astype(np.int8) + 2 * (p[:, 2] >= tile.z0 + h).astype(np.int8)
            order = np.argsort(q, kind="stable")  # keeps each child's indices in their order
            quadrant[name] = (ii[order], np.searchsorted(q[order], np.arange(5)))
        for k, (ox, oz) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
            cx, cz = tile.x0 + ox * h, tile.z0 + oz * h
            idx = {}
            for name, (ii, bounds) in quadrant.items():
                if bounds[k + 1] > bounds[k]:
                    idx[name] = ii[bounds[k]:bounds[k + 1]]
            if idx:
                tile.children.append(split(Tile(tile.path + str(k), cx, cz, h, idx)))
        tile.index = {}
        return tile

    root = Tile("", x0, z0, size, {n: np.arange(len(s)) for n, s in sets.items() if len(s)})
    return split(root)


def _extent(inst: Instances, ii: np.ndarray, bound: float) -> np.ndarray:
    p = inst.positions[ii].astype(np.float64)
    s = inst.scales[ii, 0].astype(np.float64)[:, None] * bound
    return np.stack([(p - s).min(axis=0), (p + s).max(axis=0)]).astype(np.float32)


def write(path: Path, provenance: dict, sets: dict[str, Instances], heights: dict[str, float], kinds: dict[str, str],
          x0: float, z0: float, size: float, max_instances: int, min_size: float,
          tints: dict[str, np.ndarray] | None = None, custom: dict | None = None) -> dict:
    """Write the layer; `sets` holds only species with instances; tints:
    per species (n, 3) per-instance colour factors (tint.py), written as
    primvars:tint (color3f[], interpolation vertex: one per instance);
    custom: customData of /World/Vegetation (the forest by slope class and
    the plants on the banks, for the report's tables of the composed world)."""
    from pxr import Kind, Sdf, Usd, UsdGeom

    from pipeline import usdio

    (path.parent / TILES_DIR).mkdir(exist_ok=True)
    stage, _ = usdio.create_stage(path, provenance)
    veg = UsdGeom.Xform.Define(stage, "/World/Vegetation")
    Usd.ModelAPI(veg).SetKind(Kind.Tokens.group)
    for key, value in (custom or {}).items():
        veg.GetPrim().SetCustomDataByKey(key, value)
    protos = stage.DefinePrim(VEGETATION_PROTOTYPES, "Scope")
    protos.SetSpecifier(Sdf.SpecifierClass)
    names = [n for n in sets if len(sets[n])]
    bounds = {name: _define_prototype(stage, name, k, float(heights[name]), kinds[name]) for k, name in enumerate(names)}
    root = build_quadtree({n: sets[n] for n in names}, x0, z0, size, max_instances, min_size)
    stats = {"tiles": 0, "leaf_tiles": 0, "instancers": 0, "max_depth": 0}
    if names:
        _emit_tile(_TileLayer(stage, path, provenance, sets, tints, bounds, stats), root, "/World/Vegetation")
    stage.GetRootLayer().Save()
    return stats


def _define_prototype(stage, name: str, k: int, h: float, kind: str) -> float:
    """The species' class prim with a placeholder cone; returns the radius
    around an instance's origin that holds the plant (m)."""
    from pxr import Gf, Kind, Usd, UsdGeom, Vt

    cls = UsdGeom.Xform.Define(stage, prototype_prim(name))
    Usd.ModelAPI(cls).SetKind(Kind.Tokens.component)
    cls.GetPrim().SetCustomDataByKey("worldbake:asset", {"layer": "plants.usda", "prim": plant_asset_prim(name)})
    cone = UsdGeom.Cone.Define(stage, prototype_prim(name) + "/Placeholder")
    radius = (0.45 if kind == "grass" else 0.3) * h
    cone.CreateHeightAttr(h)
    cone.CreateRadiusAttr(radius)
    cone.CreateAxisAttr(UsdGeom.Tokens.y)
    cone.CreatePurposeAttr(UsdGeom.Tokens.proxy)
    cone.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*colour(name, k))]))
    cone.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-radius, -h / 2, -radius), Gf.Vec3f(radius, h / 2, radius)]))
    UsdGeom.XformCommonAPI(cone).SetTranslate(Gf.Vec3d(0.0, h / 2, 0.0))
    # a plant of height h and width at most h, at any orientation, lies within 1.25 h of its origin
    return 1.25 * h


@dataclass(frozen=True)
class _TileLayer:
    """What every tile of the quadtree is written with."""
    stage: object  # the layer's Usd.Stage
    path: Path
    provenance: dict
    sets: dict
    tints: dict | None
    bounds: dict  # per species: the radius holding a plant (m)
    stats: dict  # counts, updated as tiles are written


def _emit_tile(layer: _TileLayer, tile: Tile, parent: str) -> np.ndarray | None:
    """The tile's Xform (a leaf's instancers in a payload file); returns its extent, None when empty."""
    from pxr import Gf, Kind, Usd, UsdGeom, Vt

    stats = layer.stats
    prim_path = f"{parent}/q{tile.path}"
    x = UsdGeom.Xform.Define(layer.stage, prim_path)
    Usd.ModelAPI(x).SetKind(Kind.Tokens.group)
    stats["tiles"] += 1
    stats["max_depth"] = max(stats["max_depth"], len(tile.path))
    ext = []
    if tile.children:
        for child in tile.children:
            e = _emit_tile(layer, child, prim_path)
            if e is not None:
                ext.append(e)
    else:
        stats["leaf_tiles"] += 1
        ext = _write_leaf_tile(layer, tile, x)
    if not ext:
        return None
    e = np.stack([np.min([a[0] for a in ext], axis=0), np.max([a[1] for a in ext], axis=0)])
    UsdGeom.ModelAPI(x).SetExtentsHint(Vt.Vec3fArray([Gf.Vec3f(*map(float, e[0])), Gf.Vec3f(*map(float, e[1]))]))
    x.GetPrim().SetCustomDataByKey("worldbake:bounds_xz_m", Vt.DoubleArray(
        [tile.x0, tile.z0, tile.x0 + tile.size, tile.z0 + tile.size]))
    return e


def _write_leaf_tile(layer: _TileLayer, tile: Tile, x) -> list:
    """The leaf's instancers in a file of their own, loaded as a payload; their extents."""
    from pipeline import usdio

    tile_file = f"{TILES_DIR}/q{tile.path}.usdc"
    tstage, _ = usdio.create_stage(layer.path.parent / tile_file, layer.provenance, root="/Tile", kind="group")
    ext = []
    for name, ii in tile.index.items():
        tint = layer.tints[name][ii] if layer.tints is not None and name in layer.tints else None
        ext.append(_write_instancer(tstage, name, layer.sets[name], ii, tint, layer.bounds[name]))
        layer.stats["instancers"] += 1
    tstage.GetRootLayer().Save()
    x.GetPrim().GetPayloads().AddPayload(f"./{tile_file}")
    return ext


def _write_instancer(tstage, name: str, inst: Instances, ii: np.ndarray, tint: np.ndarray | None,
                     bound: float) -> np.ndarray:
    """/Tile/<name>: a PointInstancer of the instances ii; returns its extent."""
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, Vt

    ipath = f"/Tile/{name}"
    pi = UsdGeom.PointInstancer.Define(tstage, ipath)
    Usd.ModelAPI(pi).SetKind(Kind.Tokens.group)
    scope = UsdGeom.Scope.Define(tstage, f"{ipath}/Prototypes")
    Usd.ModelAPI(scope).SetKind(Kind.Tokens.group)
    proto = UsdGeom.Xform.Define(tstage, f"{ipath}/Prototypes/{name}")
    proto.GetPrim().GetInherits().AddInherit(prototype_prim(name))
    # every tile's prototype is the same instance of the species' class: USD shares one
    # prototype (one set of meshes) among all tiles instead of composing a copy per tile
    proto.GetPrim().SetInstanceable(True)
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    n = len(ii)
    pi.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(inst.positions[ii])))
    pi.CreateOrientationsAttr(Vt.QuathArray.FromNumpy(np.ascontiguousarray(inst.orientations[ii])))
    pi.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(inst.scales[ii])))
    pi.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.zeros(n, np.int32)))
    pi.CreateIdsAttr(Vt.Int64Array.FromNumpy(np.ascontiguousarray(inst.ids[ii])))
    pv = UsdGeom.PrimvarsAPI(pi)
    pv.CreatePrimvar("age", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(inst.age[ii])))
    pv.CreatePrimvar("random", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(inst.random[ii])))
    if tint is not None:
        pv.CreatePrimvar("tint", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(tint, np.float32)))
    e = _extent(inst, ii, bound)
    pi.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, e[0])), Gf.Vec3f(*map(float, e[1]))]))
    return e
