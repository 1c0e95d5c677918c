"""The `lod` selection a DCC renders with: a DCC tool (Blender, Houdini
Solaris, Omniverse) draws the `lod` variant each prim selects and cannot
switch by distance, so the plant assets' own selection (LOD0 everywhere)
puts the finest mesh of every one of the world's trees into one render.

dcc.usdc, beside the world stage's root layer and its strongest sublayer,
selects per vegetation tile and species the `lod` variant that the
impostors stage's switch distances (worldbake:lod_switch_m variant_m: each
representation's measured error projected to error_px on its screen) give
for the tile's nearest point to an eye (the world's centre at the median
tile height). Farther, where a plant spans less than CROWN_PX pixels of that
screen, a tile's instancer is deactivated and its plants are drawn as
crowns: one mesh per species (/World/Vegetation/Crowns), a three-sided
pyramid per plant around its bounding sphere's centre, of the area its
silhouette covers, in its mean albedo (both from its view atlas), thinned
with distance (1 in k plants kept, k = (distance / crown distance)^2, each
k times the area: the same cover). A renderer holds each instance as an object with its
transform and a BVH instance (about a kilobyte in Cycles), a crown as three
triangles. Where a plant spans less than MIN_PX pixels it is left out
(grass at a few hundred metres: the ground's splat albedo carries its
colour). Local opinions of the root layer stack: they beat the
prototypes' inherited class and its asset's selection (LOD0). The tiles'
prototypes stay instanceable: tiles with the same selection share one USD
prototype.

The terrain's tiles (terrain_tiles.py) get their `lod` the same way: per
tile the coarsest LOD whose largest height error, from the tile's nearest
point to the eye, spans at most TERRAIN_ERROR_PX pixels of the plants'
switch screen. Tiles at different LODs meet without cracks (a coarse LOD
keeps its border at full resolution).

A renderer that switches by distance itself mutes dcc.usdc
(Usd.Stage.MuteLayer; usdview's layer stack) and gets every asset's LOD0.
For a shot away from the centre, or LOD0 everywhere in a DCC:

    python -m stages.world.dcc_layer WORLD.usda OUT.usda --eye X Y Z   # metres, y up
    python -m stages.world.dcc_layer WORLD.usda OUT.usda --lod LOD0

writes OUT.usda, a root layer over WORLD.usda with its own selections.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from worldlib.render.usd_asset import DCC_SELECTION_LAYER

LAYER = DCC_SELECTION_LAYER  # the name our own renderer mutes
CROWNS = "/World/Vegetation/Crowns"
CROWN = "crowns"  # the selection that draws a tile's plants as crowns
RING = math.sqrt(4.0 * math.pi / (3.0 * math.sqrt(3.0)))  # a crown pyramid's base circle, in sphere radii
CROWN_PX = 4.0  # a plant narrower than this on the switch distances' screen is drawn as a crown
MIN_PX = 1.0  # a plant narrower than this is left out
# a terrain tile's LOD: the coarsest whose largest height error (worst vertex) spans at most this many pixels of
# the switch screen; 8 puts the default world's far ring of tiles (2-3 km from the centre) at quarter LOD
# (at most 16 m off: 5-7 px there), which brings Blender's import and render of it under 2 GB
TERRAIN_ERROR_PX = 8.0


def terrain_tiles(stage) -> list[tuple[str, np.ndarray, dict[str, float]]]:
    """(prim path, bounds x0 z0 x1 z1 y0 y1, LOD -> its largest height error
    in metres) of every terrain tile (terrain_tiles.py) of a stage (the
    terrain layer's or a world's, its payloads need not be loaded)."""
    from .terrain_tiles import TILE_KEY, tile_prims

    out = []
    for prim in tile_prims(stage):
        info = prim.GetCustomDataByKey(TILE_KEY)
        bounds = np.asarray(list(info["bounds_xz_m"]) + list(info["height_m"]), np.float64)
        out.append((str(prim.GetPath()), bounds, {k: float(v) for k, v in info["lod_error_m"].items()}))
    return out


def terrain_selection(tiles, eye: np.ndarray, px_per_rad: float) -> dict[str, str]:
    """Tile path -> its `lod`: the coarsest LOD whose largest height error,
    seen from the tile's nearest point to the eye, spans at most
    TERRAIN_ERROR_PX pixels on the plants' switch screen (px_per_rad); the
    full LOD where the eye is in or over the tile."""
    out = {}
    for path, bounds, errors in tiles:
        d = tile_distance(bounds, eye)
        fits = [(e, lod) for lod, e in errors.items() if e * px_per_rad <= TERRAIN_ERROR_PX * d]
        out[path] = max(fits)[1] if fits else min((e, lod) for lod, e in errors.items())[1]
    return out


def _author_terrain(layer, chosen: dict[str, str]) -> None:
    from pxr import Sdf

    for path, lod in chosen.items():
        Sdf.CreatePrimInLayer(layer, Sdf.Path(path)).variantSelections["lod"] = lod


def leaf_tiles(vegetation_layer: Path) -> list[tuple[str, np.ndarray, list[str]]]:
    """(prim path, bounds x0 z0 x1 z1 with y0 y1 when known, species
    instancer names) of every leaf tile of the vegetation layer, read from
    the layer and its tile files (Sdf only: nothing is composed)."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(vegetation_layer))
    out = []

    def walk(spec):
        payloads = list(spec.payloadList.prependedItems) + list(spec.payloadList.explicitItems)
        if payloads:
            data = spec.customData.get("worldbake", {})
            b = list(data.get("bounds_xz_m", [])) if hasattr(data, "get") else []
            hint = spec.attributes.get("extentsHint")
            if hint is not None and hint.default is not None and len(b) == 4:
                b += [float(hint.default[0][1]), float(hint.default[1][1])]
            names = []
            tile = Sdf.Layer.FindOrOpen(str(Path(layer.realPath).parent / payloads[0].assetPath))
            if tile is not None:
                root = tile.GetPrimAtPath(payloads[0].primPath or tile.defaultPrim and "/" + tile.defaultPrim)
                names = [c.name for c in root.nameChildren] if root else []
            out.append((str(spec.path), np.asarray(b, np.float64), names))
        for child in spec.nameChildren:
            walk(child)

    veg = layer.GetPrimAtPath("/World/Vegetation")
    if veg is not None:
        walk(veg)
    return out


def species_ladders(layer: Path, prims: dict[str, str]) -> dict[str, dict]:
    """Per species: its `lod` variants with the distance each is used from,
    its bounding sphere and crown look, read from `layer` at prims[species]:
    the impostors layer at /Plants/<species> (a world being written does not
    compose yet: its relative paths resolve once it is in place), or a
    world's prototypes. Species without the impostors' switch distances
    are left out (their assets' selection stands)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(layer), Usd.Stage.LoadNone)
    out = {}
    for species, path in prims.items():
        prim = stage.GetPrimAtPath(path)
        switch = prim.GetCustomDataByKey("worldbake:lod_switch_m") if prim else None
        info = prim.GetCustomDataByKey("worldbake:impostor") if prim else None
        if not switch:
            continue
        s = json.loads(switch)
        variants = set(prim.GetVariantSets().GetVariantSet("lod").GetVariantNames())
        ladder = sorted(((d, v) for v, d in s["variant_m"].items() if v in variants))
        sphere = json.loads(info)["bounding_sphere"] if info else {"radius_m": 1.0, "centre_m": [0.0, 1.0, 0.0]}
        radius = float(sphere["radius_m"])
        screen = s["screen_px"] / (2.0 * math.tan(math.radians(0.5 * s["fov_deg"])))  # pixels per radian at centre
        out[species] = {"ladder": ladder, "cull_m": 2.0 * radius * screen / MIN_PX, "px_per_rad": screen,
                        "crown_m": 2.0 * radius * screen / CROWN_PX, "centre": list(sphere["centre_m"]),
                        "radius": radius, "look": crown_look(prim, json.loads(info) if info else {})}
    return out


def crown_look(prim, info: dict) -> tuple[list[float], float]:
    """(linear albedo, covered share) of the species seen whole: the mean
    colour of the covered texels of its view atlas's frames, and the share
    of its bounding sphere's disc their silhouettes cover (a frame is the
    sphere's square, 2r a side: its covered share x 4 / pi), over every
    frame. Not the slice sheet: a slab's tile holds a slab, so its cover is
    a fraction of the plant's that shrinks as the slabs thin."""
    import OpenImageIO as oiio

    from pipeline.exr import linear_from_srgb

    fallback = [0.05, 0.1, 0.04], 0.5
    rel = info.get("files", {}).get("atlas_png")
    frames, frame_px = info.get("frames"), info.get("frame_px")
    layer = next((s.layer for s in prim.GetPrimStack()
                  if "impostor" in s.GetInfo("customData").get("worldbake", {})), None)  # namespaced key
    if not rel or not frames or not frame_px or layer is None:
        return fallback
    px = np.asarray(oiio.ImageBuf(str(Path(layer.realPath).parent / rel)).get_pixels(oiio.FLOAT), np.float32)
    side = int(frames) * int(frame_px)  # the frames fill the atlas from its corner; the rest is empty
    if px.ndim != 3 or px.shape[2] < 4 or min(px.shape[:2]) < side:
        return fallback
    px = px[:side, :side]
    covered = px[..., 3] >= 0.5
    if not covered.any():
        return fallback
    colour = linear_from_srgb(px[..., :3][covered]).mean(0)
    return [round(float(c), 4) for c in colour], min(float(covered.mean()) * 4.0 / math.pi, 1.0)


def tile_distance(bounds: np.ndarray, eye: np.ndarray) -> float:
    """Nearest distance from eye (x, y, z) to the tile's box (its xz
    rectangle, and y range when known; else the eye's height counts 0)."""
    x0, z0, x1, z1 = bounds[:4]
    dx = max(x0 - eye[0], 0.0, eye[0] - x1)
    dz = max(z0 - eye[2], 0.0, eye[2] - z1)
    dy = max(bounds[4] - eye[1], 0.0, eye[1] - bounds[5]) if len(bounds) == 6 else 0.0
    return float(math.sqrt(dx * dx + dy * dy + dz * dz))


def choose(ladder: list[tuple[float, str]], cull_m: float, distance: float, crown_m: float = math.inf) -> str | None:
    """The variant used at this distance, CROWN, or None: left out."""
    if distance > cull_m:
        return None
    if distance > crown_m:
        return CROWN
    pick = ladder[0][1]
    for d, v in ladder:
        if distance >= d:
            pick = v
    return pick


def selections(tiles, ladders: dict[str, dict], eye: np.ndarray) -> dict[str, str | None]:
    """instancer path -> its variant (None: deactivated)."""
    out = {}
    for path, bounds, names in tiles:
        if len(bounds) < 4:
            continue
        d = tile_distance(bounds, eye)
        for species in names:
            if species in ladders:
                lad = ladders[species]
                out[f"{path}/{species}"] = choose(lad["ladder"], lad["cull_m"], d, lad.get("crown_m", math.inf))
    return out


def _author(layer, prefix: str, chosen: dict[str, str | None]) -> None:
    """The overs under prefix (a prim path, a variant's included)."""
    from pxr import Sdf

    for inst, variant in chosen.items():
        rel = Sdf.Path(inst).MakeRelativePath(Sdf.Path("/World"))
        target = Sdf.Path(prefix).AppendPath(rel)
        spec = Sdf.CreatePrimInLayer(layer, target)
        if variant is None or variant == CROWN:
            spec.active = False
            continue
        species = Sdf.Path(inst).name
        proto = Sdf.CreatePrimInLayer(layer, target.AppendChild("Prototypes").AppendChild(species))
        proto.variantSelections["lod"] = variant


def crown_points(tiles, chosen: dict[str, str | None], ladders: dict[str, dict], vegetation_layer: Path,
                 eye: np.ndarray) -> dict:
    """species -> (centres (n, 3), radii (n,)) of the plants drawn as crowns."""
    from pxr import Sdf

    parts: dict[str, list] = {}
    distances = {f"{path}/{s}": tile_distance(bounds, eye) for path, bounds, names in tiles for s in names}
    veg = Sdf.Layer.FindOrOpen(str(vegetation_layer))  # held: its specs live as long as it does
    base = Path(veg.realPath).parent
    for inst, variant in chosen.items():
        if variant != CROWN:
            continue
        tile_path, species = inst.rsplit("/", 1)
        spec = veg.GetPrimAtPath(tile_path)
        payload = (list(spec.payloadList.prependedItems) + list(spec.payloadList.explicitItems))[0]
        tile = Sdf.Layer.FindOrOpen(str(base / payload.assetPath))
        root = payload.primPath if not payload.primPath.isEmpty else Sdf.Path("/" + tile.defaultPrim)
        prim = tile.GetPrimAtPath(root.AppendChild(species))
        attrs = prim.attributes
        pos = np.asarray(attrs["positions"].default, np.float64)
        scale = np.asarray(attrs["scales"].default, np.float64) if "scales" in attrs else np.ones_like(pos)
        lad = ladders[species]
        # thinned with distance: 1 in k plants kept (by the instance's own random number), k times the area,
        # so a far tile's forest keeps its cover with fewer, larger crowns
        k = max(1.0, (distances[inst] / lad["crown_m"]) ** 2)
        rnd = np.asarray(attrs["primvars:random"].default, np.float64) if "primvars:random" in attrs else \
            (np.arange(len(pos)) * 0.6180339887) % 1.0
        keep = rnd < 1.0 / k
        centre = pos[keep] + np.asarray(lad["centre"]) * scale[keep]  # the crown's offset, scaled (turns about y ignored)
        radius = lad["radius"] * np.sqrt(lad["look"][1] * k) * scale[keep].max(1)  # the area the plant covers, k times
        parts.setdefault(species, []).append((centre, radius))
    return {s: (np.concatenate([c for c, _ in v]), np.concatenate([r for _, r in v])) for s, v in parts.items()}


def crown_mesh(centre: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, face counts, indices): per crown a three-sided pyramid
    (4 points, 3 triangles) around its sphere, seen from above and from the
    side with the area of the sphere's disc, pi r^2: its base triangle, on a
    circle of RING r, has 3 sqrt(3) / 4 RING^2 r^2 = pi r^2, its side about
    half its width (sqrt(3) RING r) times its height (2.4 r). Not points:
    Blender 5.0 imports a UsdGeom.Points without its material."""
    n = len(centre)
    a = np.radians([90.0, 210.0, 330.0])
    ring = np.stack([np.cos(a), np.full(3, -0.8), np.sin(a)], 1) * np.array([RING, 1.0, RING])
    unit = np.concatenate([ring, [[0.0, 1.6, 0.0]]]).astype(np.float64)
    pts = (centre[:, None, :] + radius[:, None, None] * unit[None]).reshape(-1, 3).astype(np.float32)
    faces = np.array([[0, 3, 1], [1, 3, 2], [2, 3, 0]], np.int32)  # outward, counter-clockwise from outside
    idx = (np.arange(n, dtype=np.int32)[:, None, None] * 4 + faces[None]).reshape(-1)
    return pts, np.full(3 * n, 3, np.int32), idx


def _author_crowns(layer, crowns: dict, ladders: dict[str, dict], where: str = CROWNS) -> None:
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    stage = Usd.Stage.Open(layer)
    group = UsdGeom.Scope.Define(stage, where)
    for species, (centre, radius) in sorted(crowns.items()):
        pts, counts, idx = crown_mesh(centre, radius)
        mesh = UsdGeom.Mesh.Define(stage, f"{where}/{species}")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(idx))
        lo, hi = pts.min(0), pts.max(0)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        colour = ladders[species]["look"][0]
        mesh.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*colour)]))
        mat = UsdShade.Material.Define(stage, f"{where}/{species}Look")
        surf = UsdShade.Shader.Define(stage, f"{where}/{species}Look/Surface")
        surf.CreateIdAttr("UsdPreviewSurface")
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
        surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.9)
        mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    group.GetPrim().SetCustomDataByKey("worldbake:crowns", "plants drawn as three-sided pyramids where they span less than "
                                       f"{CROWN_PX:g} px (stages/world/dcc_layer.py)")


def summary(chosen: dict[str, str | None]) -> dict:
    counts: dict[str, int] = {}
    for v in chosen.values():
        counts[v or "off"] = counts.get(v or "off", 0) + 1
    return dict(sorted(counts.items()))


def default_eye(tiles) -> np.ndarray:
    """The tiles' centre, at their median lowest height (ground level)."""
    b = np.array([t[1][:4] for t in tiles if len(t[1]) >= 4])
    y = [t[1][4] for t in tiles if len(t[1]) == 6]
    return np.array([0.5 * (b[:, 0].min() + b[:, 2].max()), float(np.median(y)) if y else 0.0,
                     0.5 * (b[:, 1].min() + b[:, 3].max())])


def write_dcc_layer(root_path: Path, vegetation_layer: Path, impostors_layer: Path, species: list[str],
                    provenance: dict, terrain_layer: Path | None = None) -> dict:
    """dcc.usdc beside the root layer, made its strongest sublayer; returns
    the eye and the tiles per variant, and with terrain_layer the terrain
    tiles per LOD (empty, and nothing written, without vegetation tiles or
    switch distances)."""
    from pxr import Sdf

    from pipeline import usdio

    from worldlib.plant_asset import plant_asset_prim

    tiles = leaf_tiles(vegetation_layer)
    ladders = species_ladders(impostors_layer, {s: plant_asset_prim(s) for s in species})
    if not tiles or not ladders:
        return {}
    eye = default_eye(tiles)
    chosen = selections(tiles, ladders, eye)
    path = root_path.with_name(LAYER)
    layer = Sdf.Layer.CreateNew(str(path))
    usdio.set_provenance(layer, provenance)
    _author(layer, "/World", chosen)
    crowns = crown_points(tiles, chosen, ladders, vegetation_layer, eye)
    if crowns:
        _author_crowns(layer, crowns, ladders)
    ground = {}
    if terrain_layer is not None:
        from pxr import Usd

        ground = terrain_selection(terrain_tiles(Usd.Stage.Open(str(terrain_layer), Usd.Stage.LoadNone)), eye,
                                   next(iter(ladders.values()))["px_per_rad"])
        _author_terrain(layer, ground)
    layer.Save()
    root = Sdf.Layer.FindOrOpen(str(root_path))
    root.subLayerPaths.insert(0, "./" + LAYER)
    root.Save()
    return {"eye_m": [round(float(v), 2) for v in eye], "tiles": summary(chosen),
            "crowns": {s: int(len(r)) for s, (_, r) in crowns.items()}, "terrain_tiles": summary(ground)}


def vegetation_source(veg):
    """The layer that defines the vegetation's tiles (dcc.usdc only overs them), or None."""
    from pxr import Sdf

    for spec in veg.GetPrimStack() if veg else []:
        q = spec.layer.GetPrimAtPath("/World/Vegetation/q")
        if q and q.specifier == Sdf.SpecifierDef:
            return spec.layer
    return None


def write_shot_layer(world_usda: Path, out: Path, eye: np.ndarray | None = None, lod: str | None = None) -> dict:
    """OUT: a root layer over world_usda selecting for a camera at eye (the
    terrain tiles' LODs too), or `lod` on every tile (the plants that
    dcc.usdc leaves out put back) and the terrain at its full LOD."""
    from pxr import Sdf, Usd, UsdGeom

    stage = Usd.Stage.Open(str(world_usda), Usd.Stage.LoadNone)
    veg = stage.GetPrimAtPath("/World/Vegetation")
    protos = {p.GetName(): str(p.GetPath()) for p in veg.GetChild("Prototypes").GetAllChildren()} if veg else {}
    source = vegetation_source(veg)
    if source is None:
        raise SystemExit(f"{world_usda}: no vegetation tiles to select for")
    tiles = leaf_tiles(Path(source.realPath))
    ladders = species_ladders(world_usda, protos)
    if lod is not None:  # the species whose prototype has that variant (a placeholder has none)
        has = {s for s, path in protos.items() if lod in stage.GetPrimAtPath(path).GetVariantSets()
               .GetVariantSet("lod").GetVariantNames()}
        chosen = {f"{path}/{s}": lod for path, _, names in tiles for s in names if s in has}
    else:
        chosen = selections(tiles, ladders, np.asarray(eye, np.float64))
    layer = Sdf.Layer.CreateNew(str(out))
    layer.subLayerPaths.append(str(Path(world_usda).resolve()))
    layer.defaultPrim = "World"
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, UsdGeom.Tokens.y)
    layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
    for inst, variant in chosen.items():
        if variant is not None:  # the world's dcc.usdc may have left it out
            Sdf.CreatePrimInLayer(layer, Sdf.Path(inst)).active = True
    _author(layer, "/World", chosen)
    ground = terrain_tiles(stage)
    if lod is not None or not ladders:  # every terrain tile at its full LOD
        ground = {path: "full" for path, _, _ in ground}
    else:
        ground = terrain_selection(ground, np.asarray(eye, np.float64), next(iter(ladders.values()))["px_per_rad"])
    _author_terrain(layer, ground)
    Sdf.CreatePrimInLayer(layer, CROWNS).active = False  # the world's crowns, for its own eye
    crowns = crown_points(tiles, chosen, ladders, Path(source.realPath), np.asarray(eye, np.float64)) if eye is not None else {}
    if crowns:
        _author_crowns(layer, crowns, ladders, CROWNS + "ForShot")
    layer.Save()
    return {"eye_m": None if eye is None else [float(v) for v in eye], "tiles": summary(chosen),
            "crowns": {s: int(len(r)) for s, (_, r) in crowns.items()}, "terrain_tiles": summary(ground)}


def main(argv=None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description="a root layer over a world selecting each tile's LOD for one camera")
    ap.add_argument("world")
    ap.add_argument("out")
    ap.add_argument("--eye", type=float, nargs=3, metavar=("X", "Y", "Z"), help="the camera (m, y up)")
    ap.add_argument("--lod", help="this variant on every tile instead (LOD0: full detail)")
    a = ap.parse_args(argv)
    if (a.eye is None) == (a.lod is None):
        ap.error("give --eye or --lod")
    print(json.dumps(write_shot_layer(Path(a.world), Path(a.out), None if a.eye is None else np.asarray(a.eye), a.lod)))


if __name__ == "__main__":
    main()
