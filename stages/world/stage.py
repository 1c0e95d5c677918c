"""The world assembly: writes the layers that make `world.usda`.

For now it reads the latest terrain height and writes
- terrain.usdc: /World/Terrain (kind component) with the ground in tiles,
  /World/Terrain/Ground/Tile_x<i>_y<j>, each a UsdGeom.Mesh (subdivisionScheme
  none, vertex normals, primvars:st, extent) whose `lod` variants each load a
  payload of terrain/tile_x<i>_y<j>.usdc (terrain_tiles.py), bound to a
  UsdPreviewSurface material that reads albedo.exr;
- albedo.exr: the ground colour from altitude and slope, tiled and mip-mapped;
- world.usda: /World (kind assembly) composing terrain.usdc and, as later
  stages come, their layers, all by relative paths. The engine publishes it
  as build/worlds/<name>/world.usda.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import usdio
from worldlib import images
from pipeline.contract import (Artifact, Check, CheckContext, GridInfo, Input, Param, Params, ReportPicture, RunContext,
                               Stage)
from pipeline.limits import leading_key
from worldlib.ground import SPLAT_CHANNELS
from worldlib.plant_asset import plant_asset_prim
from worldlib.terrain import GROUND_SOURCES

from pipeline.tiles import GridArray
from worldlib.terrain.mesh import bilinear, lattice_coordinates, lattice_heights, terrain_mesh_by_window

from .dcc_layer import write_dcc_layer
from .impostor_layer import IMPOSTOR_INPUT, bind_impostors
from .report_view import world_picture
from .terrain_tiles import water_points, write_terrain_tiles
from .volume_layer import SECTOR_VOLUMES

# Upstream USD layers composed into the world, strongest first; absent when
# their stage is disabled or not needed.
LAYER_INPUTS = (
    Input("water", one_of=("hydrology.water",), optional=True, description="rivers and lakes"),
    Input("vegetation", one_of=("vegetation.instances",), optional=True,
          description="PointInstancers per species and quadtree tile, with placeholder prototypes"),
    SECTOR_VOLUMES,
)
# The plant assets that replace the vegetation placeholders.
ASSET_INPUTS = (
    Input("placed", one_of=("vegetation.placed",), optional=True, description="which species were placed, where their prototypes are"),
    Input("plants", one_of=("plants.assets",), optional=True, description="the plant assets (plants.usda)"),
    IMPOSTOR_INPUT,
)


class WorldParams(Params):
    mesh_max_vertices: int = Param(1025, ge=2, le=8193, units="vertices",
                                   description="largest number of terrain mesh vertices along the longer side (the shorter side keeps "
                                   "the same spacing); the height grid is resampled down to it")
    terrain_tile_quads: int = Param(256, ge=2, le=8192, units="quads",
                                    description="most mesh quads per side of a terrain tile: the mesh is written as tiles, "
                                    "each a USD payload with full, half and quarter LODs (stages/world/terrain_tiles.py)")
    texture_size: int = Param(1024, ge=16, le=16384, units="texels",
                              description="ground colour texture size per side")
    snow_line_m: float = Param(2200.0, ge=-11000.0, le=9000.0, units="m", description="altitude above which the ground is snow")
    tree_line_m: float = Param(1600.0, ge=-11000.0, le=9000.0, units="m", description="altitude above which grass gives way to bare ground")
    rock_slope_deg: float = Param(35.0, ge=0.0, le=90.0, units="deg", description="slope above which the ground is bare rock")
    roughness: float = Param(0.9, ge=0.0, le=1.0, description="UsdPreviewSurface roughness of the ground")
    ground_texel_m: float = Param(
        1.0, ge=0.05, le=1000.0, units="m", description="texel size of the ground albedo's UDIM tiles when the "
        "vegetation stage's splat weights are baked: the whole world at this size, MIP-mapped, so the texel is this "
        "fine wherever the camera is near")
    ground_tile_texels: int = Param(2048, ge=16, le=8192, units="texels", description="texels per side of each UDIM tile")
    ground_detail: bool = Param(True, description="write the ground's detail layer (a tiling albedo and normal "
                                "texture per ground type, blended by the splat weights; worldlib.ground_detail) and "
                                "bake the blend over a near square (needs the vegetation stage's splat weights)")
    ground_detail_texels: int = Param(512, ge=16, le=4096, units="texels", description="texels per side of each "
                                      "ground type's detail texture (it tiles over 2-4 m: worldlib.ground_detail)")
    ground_near_m: float = Param(64.0, ge=0.0, le=4096.0, units="m", description="side of the square near the world's "
                                 "centre (moved by ground_near_east_m, ground_near_south_m) whose detail blend is "
                                 "baked for plain UsdPreviewSurface (rounded to whole mesh quads); 0: none")
    ground_near_texels: int = Param(2048, ge=16, le=8192, units="texels",
                                    description="most texels per side of the near square's baked albedo and normal "
                                    "(its texel is ground_texel_m / 32 or, capped by this, larger)")
    ground_near_east_m: float = Param(0.0, ge=-1e6, le=1e6, units="m", description="the near square's centre, east "
                                      "of the world's centre")
    ground_near_south_m: float = Param(0.0, ge=-1e6, le=1e6, units="m", description="the near square's centre, "
                                       "south of the world's centre")


# Ground colours (linear RGB): reasoned from typical albedo of the materials.
GRASS = np.array([0.10, 0.16, 0.05])
DRY = np.array([0.22, 0.20, 0.12])
ROCK = np.array([0.18, 0.17, 0.16])
SNOW = np.array([0.80, 0.82, 0.85])


def ground_colour(height, size: int, params: WorldParams) -> np.ndarray:
    """Ground albedo (size x size x 3) from altitude and slope, smooth blends
    between grass, dry ground, rock and snow; height: the terrain grid read
    by window (pipeline.tiles.GridFile or GridArray)."""
    rows, cols = height.shape
    hv = lattice_heights(heights_of(height), (rows, cols), np.linspace(0, rows - 1, size),
                         np.linspace(0, cols - 1, size), BAND_ROWS)
    step = height.cell_size_m * (max(rows, cols) - 1) / max(size - 1, 1)
    gz, gx = np.gradient(hv, step)
    slope = np.degrees(np.arctan(np.hypot(gx, gz)))

    def ramp(v, edge, width):
        return np.clip((v - edge) / width + 0.5, 0.0, 1.0)[..., None]

    dry = ramp(hv, params.tree_line_m, 200.0)
    colour = GRASS * (1 - dry) + DRY * dry
    rock = ramp(slope, params.rock_slope_deg, 10.0)
    colour = colour * (1 - rock) + ROCK * rock
    snow = ramp(hv, params.snow_line_m, 150.0) * (1 - ramp(slope, 50.0, 10.0))
    colour = colour * (1 - snow) + SNOW * snow
    return colour.astype(np.float32)


def heights_of(terrain):
    """read(row0, col0, rows, cols) of the terrain's height channel."""
    channel = terrain.channels[0]
    return lambda r0, c0, rows, cols: terrain.read(r0, c0, rows, cols, channel=channel)


def splat_of(splat):
    """read(row0, col0, rows, cols) of the splat weights, (rows, cols, types)
    in ground.SPLAT_ORDER."""
    from . import ground

    order = [list(splat.channels).index(c) for c in ground.SPLAT_ORDER]
    return lambda r0, c0, rows, cols: np.ascontiguousarray(
        np.asarray(splat.read(r0, c0, rows, cols), np.float32).reshape(rows, cols, -1)[..., order])


def terrain_mesh(terrain, max_vertices: int):
    """The terrain mesh (worldlib.terrain.mesh) of the terrain read by window."""
    return terrain_mesh_by_window(heights_of(terrain), terrain.shape, terrain.cell_size_m, terrain.origin_m,
                                  max_vertices, BAND_ROWS)


def write_terrain_layer(path: Path, mesh_data, texture: str, params: WorldParams, provenance: dict,
                        udim: tuple[str, int] | None = None, normal_texture: str | None = None,
                        detail: dict | None = None, water: np.ndarray | None = None) -> dict:
    """udim: (file pattern with <UDIM>, tiles per side): the albedo from UDIM
    tiles read through primvar st_udim = st * tiles; normal_texture: a
    tangent-space normal map (encoded 0..1) over the whole terrain; detail:
    the ground's detail layer (ground_near.author_detail_graph); water:
    points on the water surface (terrain_tiles.water_points), which the
    coarse LODs are carved under. The mesh is written in tiles with LODs,
    each a payload (terrain_tiles.py)."""
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade

    stage, world = usdio.create_stage(path, provenance)
    terrain = UsdGeom.Xform.Define(stage, "/World/Terrain")
    Usd.ModelAPI(terrain).SetKind(Kind.Tokens.component)

    nfaces = len(mesh_data.face_vertex_indices) // 3
    ext = mesh_data.extent

    UsdGeom.Scope.Define(stage, "/World/Terrain/Looks")
    material = UsdShade.Material.Define(stage, "/World/Terrain/Looks/Ground")
    surface = UsdShade.Shader.Define(stage, "/World/Terrain/Looks/Ground/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(params.roughness))
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    reader = UsdShade.Shader.Define(stage, "/World/Terrain/Looks/Ground/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    albedo_reader = reader
    if udim is not None:  # the meshes' primvar st_udim = st * tiles (terrain_tiles.py)
        albedo_reader = UsdShade.Shader.Define(stage, "/World/Terrain/Looks/Ground/StUdimReader")
        albedo_reader.CreateIdAttr("UsdPrimvarReader_float2")
        albedo_reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st_udim")
    albedo = UsdShade.Shader.Define(stage, "/World/Terrain/Looks/Ground/Albedo")
    albedo.CreateIdAttr("UsdUVTexture")
    albedo.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(udim[0] if udim is not None else texture)
    albedo.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")  # linear EXR data
    albedo.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    albedo.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    albedo.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(albedo_reader.ConnectableAPI(), "result")
    if normal_texture is not None:
        nmap = UsdShade.Shader.Define(stage, "/World/Terrain/Looks/Ground/Normal")
        nmap.CreateIdAttr("UsdUVTexture")
        nmap.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(normal_texture)
        nmap.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
        nmap.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        nmap.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        nmap.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2.0, 2.0, 2.0, 1.0))  # 0..1 -> -1..1
        nmap.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(-1.0, -1.0, -1.0, 0.0))
        nmap.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        nmap.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(nmap.ConnectableAPI(), "rgb")
    albedo.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(albedo.ConnectableAPI(), "rgb")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    near = near_material = None
    if detail is not None:
        from .ground_near import author_detail_graph, author_near_material

        author_detail_graph(stage, detail["files"])
        if detail.get("near") is not None:
            near = dict(detail["near"], roughness=params.roughness)
            near_material = author_near_material(stage, near)
    tiles = write_terrain_tiles(stage, path.parent, mesh_data, params.terrain_tile_quads, material,
                                None if udim is None else udim[1], detail is not None, near, near_material, provenance,
                                water)

    world.GetPrim()  # /World stays the defaultPrim of this layer too
    stage.GetRootLayer().Save()
    return {"mesh_vertices": int(len(mesh_data.points)), "mesh_triangles": nfaces,
            "mesh_lattice": list(mesh_data.lattice_shape),
            "height_min_m": float(ext[0][1]), "height_max_m": float(ext[1][1]), **tiles}


GROUND_TILE_THREADS = 2  # UDIM tiles baked at once (each holds about 40 B a texel at its peak)
# rows of a grid read at once where the world stage reads whole rows (the normal map, the splat textures, the
# mesh's lattice): a whole number of the textures' file tiles (images.MIP_TILE); about 50 MB of float64 per
# channel at 8192 columns
BAND_ROWS = 256


# what the ground textures read of the params (the unit's key; the rest shapes the layers only)
GROUND_PARAMS = ("texture_size", "ground_texel_m", "ground_tile_texels", "mesh_max_vertices", "ground_detail",
                 "ground_detail_texels",
                 "ground_near_m", "ground_near_texels", "ground_near_east_m", "ground_near_south_m")


def write_ground_textures(ctx: RunContext, terrain, splat_grid, mesh, params: WorldParams, albedo_path: Path,
                          folder: Path, provenance: dict) -> tuple[tuple[str, int], str]:
    """The ground from the splat weights (ground.py): albedo.exr (the whole
    world at texture_size, for overviews), UDIM albedo tiles ground.<UDIM>.exr
    at ground_texel_m and normal.exr from the height, beside the terrain
    layer. terrain, splat_grid: grids read by window (GridFile, GridArray),
    never whole."""
    from pipeline.errors import InputError

    from . import ground
    from .ground_device import GroundAlbedo

    missing = [c for c in ground.SPLAT_ORDER if c not in splat_grid.channels]
    if missing:
        raise InputError(f"world: the splat weights lack channels {missing}")
    rows, cols = terrain.shape
    if tuple(splat_grid.shape) != (rows, cols):
        raise InputError(f"world: the splat weights are {tuple(splat_grid.shape)}, the terrain {(rows, cols)}")
    read_splat = splat_of(splat_grid)
    splat_shape = (rows, cols, len(ground.SPLAT_ORDER))
    dx = terrain.cell_size_m
    size_m = max(rows, cols) * dx
    tiles, texels = ground.udim_layout(size_m, params.ground_texel_m, params.ground_tile_texels)
    texel_m = size_m / (tiles * texels)
    n = params.texture_size
    overview = GroundAlbedo(ctx.cl, read_splat, splat_shape, ground.detail_tables(ctx.seed, size_m / n))
    images.write_mipmapped_texture(albedo_path, overview.tile(dx, terrain.origin_m, 1, n, 0, 0, size_m / n), provenance)
    del overview
    baker = GroundAlbedo(ctx.cl, read_splat, splat_shape, ground.detail_tables(ctx.seed, texel_m))

    def write_tile(udim: int, tile: np.ndarray) -> int:
        # zip level 1: the write is most of a tile's cost, and the lowest level writes fastest for little more disk
        images.write_mipmapped_texture(folder / f"ground.{udim}.exr", tile, provenance, compression="zip:1")
        return udim

    # the device bakes a tile in a fraction of its write (box mips, half floats, zip): writes overlap in threads,
    # whose compression releases the GIL; at most GROUND_TILE_THREADS tiles wait in memory
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=GROUND_TILE_THREADS) as pool:
        pending = []
        for i, (u, v) in enumerate((u, v) for v in range(tiles) for u in range(tiles)):
            if len(pending) >= GROUND_TILE_THREADS:
                pending.pop(0).result()
            pending.append(pool.submit(write_tile, 1001 + u + 10 * v,
                                       baker.tile(dx, terrain.origin_m, tiles, texels, u, v, texel_m)))
            ctx.progress(0.05 + 0.6 * (i + 1) / tiles ** 2, f"ground tile {1001 + u + 10 * v}")
        for p in pending:
            p.result()
    ctx.progress(0.66, "ground normal map")
    write_normal_map(folder / "normal.exr", heights_of(terrain), (rows, cols), dx, mesh, provenance)
    ctx.metrics.update(ground_udim_tiles=tiles * tiles, ground_texel_m=texel_m, ground_tile_texels=texels)
    if params.ground_detail:
        ctx.progress(0.72, "ground detail layer")
        ctx.metrics["ground_detail"] = write_ground_detail(ctx, terrain, read_splat, mesh, params, folder, provenance)
    return ("./ground.<UDIM>.exr", tiles), "./normal.exr"


def write_normal_map(path: Path, read_height, shape: tuple[int, int], dx: float, mesh, provenance: dict) -> None:
    """ground.normal_map of the whole grid against the mesh surface at every
    cell centre (bilinear within the lattice; the mesh is piecewise linear),
    written band by band of rows (each read with a row around it for the
    gradient): the bytes of the whole map, never whole in memory."""
    from . import ground

    rows, cols = shape
    nr, nc = mesh.lattice_shape
    lattice = mesh.points[:, 1].reshape(nr, nc).astype(np.float64)
    ri = np.interp(np.arange(rows), lattice_coordinates(rows, nr), np.arange(nr))
    ci = np.interp(np.arange(cols), lattice_coordinates(cols, nc), np.arange(nc))
    with images.MipmappedWriter(path, rows, cols, 3, provenance) as out:
        for r0 in range(0, rows, BAND_ROWS):
            r1 = min(rows, r0 + BAND_ROWS)
            a, b = max(0, r0 - 1), min(rows, r1 + 1)
            h = np.asarray(read_height(a, 0, b - a, cols), np.float64)
            normals = ground.normal_map(h, bilinear(lattice, ri[a:b], ci), dx)
            out.write_rows(normals[r0 - a:r1 - a])


def write_ground_detail(ctx: RunContext, terrain, read_splat, mesh, params: WorldParams, folder: Path,
                        provenance: dict) -> dict:
    """The detail textures, the splat textures and the near square's bake
    (ground_near); what write_terrain_layer's `detail` takes."""
    import time

    from worldlib import ground_detail

    from .ground_near import write_detail_files, write_near

    t0 = time.perf_counter()
    textures = ground_detail.detail_textures(ctx.seed, params.ground_detail_texels)
    files = write_detail_files(folder, textures, read_splat, terrain.shape, provenance, BAND_ROWS)
    detail = {"files": files, "near": None}
    if params.ground_near_m > 0:
        layer = ground_detail.DetailLayer.from_textures(textures)
        t1 = time.perf_counter()
        read_height = heights_of(terrain)
        detail["near"] = write_near(folder, layer, read_splat, lambda *w: np.asarray(read_height(*w), np.float64),
                                    terrain.shape, terrain.cell_size_m, terrain.origin_m, mesh,
                                    params.ground_near_m, (params.ground_near_east_m, params.ground_near_south_m),
                                    params.ground_near_texels, params.ground_texel_m / 32)
        ctx.metrics["ground_near_bake_s"] = round(time.perf_counter() - t1, 2)
        files += [detail["near"]["albedo"], detail["near"]["normal"]]
    ctx.metrics["ground_detail_s"] = round(time.perf_counter() - t0, 2)
    return detail


def bind_plant_assets(root_path: Path, placed: dict, plants_layer: Path, ctx: RunContext) -> dict[str, str]:
    """In the root layer (stronger than the vegetation layer it composes),
    reference each placed species' plant asset on its prototype class prim
    and switch its placeholder off; every instancer's prototype inherits that
    class, so the asset shows in every tile. Species without an asset keep
    their placeholder."""
    from pxr import Sdf

    assets = Sdf.Layer.FindOrOpen(str(plants_layer))
    layer = Sdf.Layer.FindOrOpen(str(root_path))
    bound = {}
    for species, proto_path in placed.get("prototypes", {}).items():
        asset_prim = Sdf.Path(plant_asset_prim(species))
        if not assets.GetPrimAtPath(asset_prim):
            continue
        spec = Sdf.CreatePrimInLayer(layer, Sdf.Path(proto_path))
        spec.referenceList.Prepend(Sdf.Reference(ctx.asset_path(plants_layer), asset_prim))
        placeholder = Sdf.CreatePrimInLayer(layer, Sdf.Path(proto_path).AppendChild("Placeholder"))
        placeholder.active = False
        bound[species] = str(asset_prim)
    layer.Save()
    return bound


def run(ctx: RunContext, inputs: dict, params: WorldParams) -> dict:
    """The whole run: its grids read by window from memory, the tiled run's
    code (run_tiled), so both write the same bytes."""
    grids = {role: GridArray(inputs[role]) for role in ("terrain", "splat") if role in inputs}
    return run_tiled(ctx, {**inputs, **grids}, params)


def run_tiled(ctx: RunContext, inputs: dict, params: WorldParams) -> dict:
    """The world from its grids read by window (a tiled bake's GridFile
    handles): the ground textures band by band and tile by tile, the mesh's
    lattice band by band; no grid is ever whole."""
    terrain = inputs["terrain"]
    rows, cols = terrain.shape
    if rows < 2 or cols < 2:
        from pipeline.errors import InputError

        raise InputError(f"world: the terrain grid is {rows}x{cols}; a terrain mesh needs at least 2x2 cells")

    ctx.progress(0.0, "ground colour texture")
    albedo_path = ctx.path("world.albedo")
    terrain_path = ctx.path("world.terrain")
    splat_grid = inputs.get("splat")
    udim = normal_file = mesh = None
    if splat_grid is None:
        images.write_texture(albedo_path, ground_colour(terrain, params.texture_size, params), ctx.provenance)
    else:
        # the ground textures (most of this stage's time and bytes) are a unit (pipeline.units): a world
        # re-made for its plants, impostors or volumes links them from the run that baked them
        unit = ctx.unit("ground", {"height": terrain.content_hash(), "splat": splat_grid.content_hash(),
                                   "seed": ctx.seed, "params": {k: getattr(params, k) for k in GROUND_PARAMS}})
        saved = unit.restore(terrain_path.parent)
        if saved is not None:
            udim, normal_file = (saved["udim"][0], saved["udim"][1]), saved["normal"]
            ctx.metrics.update(saved["metrics"], ground_reused=True)
        else:
            metrics_before = set(ctx.metrics)
            mesh = terrain_mesh(terrain, params.mesh_max_vertices)
            udim, normal_file = write_ground_textures(ctx, terrain, splat_grid, mesh, params, albedo_path,
                                                      terrain_path.parent, unit.provenance)
            folder = terrain_path.parent
            files = [albedo_path.name, normal_file.removeprefix("./")] + sorted(
                p.name for p in folder.glob("ground.*.exr")) + ctx.metrics.get("ground_detail", {}).get("files", [])
            unit.save(folder, files, {"udim": list(udim), "normal": normal_file,
                                      "metrics": {k: v for k, v in ctx.metrics.items()
                                                  if k not in metrics_before and not k.endswith("_s")}})
            ctx.metrics["ground_reused"] = False

    ctx.progress(0.8, "terrain mesh")
    if mesh is None:
        mesh = terrain_mesh(terrain, params.mesh_max_vertices)
    water = water_points(inputs["water"]) if "water" in inputs else None
    ctx.metrics.update(write_terrain_layer(terrain_path, mesh, "./" + albedo_path.name, params, ctx.provenance,
                                           udim, normal_file, ctx.metrics.get("ground_detail"), water))

    ctx.progress(0.9, "world layer")
    root_path = ctx.path("world.root")
    layers = [ctx.asset_path(inputs[inp.role]) for inp in LAYER_INPUTS if inp.role in inputs]
    layers.append("./" + terrain_path.name)
    usdio.write_root_layer(root_path, ctx.provenance, layers)
    ctx.metrics["layers"] = layers
    if "placed" in inputs and "plants" in inputs:
        ctx.metrics["plant_assets"] = bind_plant_assets(root_path, inputs["placed"], inputs["plants"], ctx)
        if "impostors" in inputs:
            ctx.metrics["impostors"] = bind_impostors(root_path, ctx.metrics["plant_assets"], inputs["placed"],
                                                      inputs["impostors"], ctx)
            # what a DCC, which cannot switch LODs by distance, renders (dcc_layer.py)
            ctx.metrics["dcc"] = write_dcc_layer(root_path, inputs["vegetation"], inputs["impostors"],
                                                 ctx.metrics["impostors"], ctx.provenance,
                                                 terrain_path) if "vegetation" in inputs else {}
    return {"world.root": root_path, "world.terrain": terrain_path, "world.albedo": albedo_path}


MAX_GROUND_TEXELS = 1e10  # texels of the albedo overview and the UDIM tiles (the default world: 7e7)


def ground_layout(params: WorldParams, terrain: GridInfo | None) -> tuple[int, int]:
    """(UDIM tiles per side, texels per tile side) the run will bake: the
    configured tile size, or more texels per tile where the UDIM row limit
    caps the columns (a fine ground_texel_m on a large world)."""
    from . import ground

    if terrain is None:
        return 1, params.ground_tile_texels
    size_m = max(terrain.shape) * terrain.cell_size_m
    return ground.udim_layout(size_m, params.ground_texel_m, params.ground_tile_texels)


def check(params: WorldParams, ctx: CheckContext) -> Check:
    """Memory: the albedo computed at texture resolution (ground_colour
    holds about 20 float64 values a texel at its peak, with the RGB blends,
    and maketx copies the result: 256 B a texel), the terrain mesh (points,
    normals, uvs, indices: about 80 B a vertex) and the UDIM tiles baked at
    once at their real size (ground.udim_layout). Work: the texels of the
    overview and of every UDIM tile, at most MAX_GROUND_TEXELS."""
    texels = params.texture_size ** 2
    vertices = params.mesh_max_vertices ** 2
    terrain = ctx.inputs.get("terrain")
    if terrain is not None:
        vertices = min(terrain.shape[0], params.mesh_max_vertices) * min(terrain.shape[1], params.mesh_max_vertices)
    tiles, tile_texels = (0, 0) if terrain is not None and "splat" not in ctx.inputs else ground_layout(params, terrain)
    # UDIM tiles baked at once: weights and detail per ground type (float32) and the RGB result, about 64 B a texel
    tile_bytes = min(GROUND_TILE_THREADS, tiles ** 2) * 64 * tile_texels ** 2
    ground_texels = (tiles * tile_texels) ** 2
    overview = f"world.texture_size = {params.texture_size}: {texels:,} texels x 256 B"
    udim = (f"{min(GROUND_TILE_THREADS, tiles ** 2)} ground tiles of {tile_texels}^2 texels x 64 B "
            f"(world.ground_texel_m = {params.ground_texel_m:g}: {tiles} x {tiles} UDIM tiles)")
    parts = [overview, f"{vertices:,} vertices x 80 B", udim]
    if tile_bytes > 256 * texels:  # the larger size first: a memory refusal names the file that set it
        parts = [udim, f"{vertices:,} vertices x 80 B", overview]
    # the detail layer: 12 textures with their MIP levels (float32 RGB, and float64 while made), and a
    # chunk of 128 near rows in the blend (about 600 B a texel)
    detail_bytes = 0
    if params.ground_detail and tiles:
        detail_bytes = 12 * 24 * 2 * params.ground_detail_texels ** 2 + 600 * 128 * params.ground_near_texels
        parts.append(f"ground detail {12 * 24 * 2 * params.ground_detail_texels ** 2 // 2 ** 20} MiB + near rows "
                     f"{600 * 128 * params.ground_near_texels // 2 ** 20} MiB")
    return Check(memory_bytes=256 * texels + 80 * vertices + tile_bytes + detail_bytes, memory_how=" + ".join(parts),
                 work=texels + ground_texels, work_unit="texels", work_limit=MAX_GROUND_TEXELS,
                 work_key=leading_key(params, grows=("texture_size",), shrinks=("ground_texel_m",)),
                 work_how=f"{texels:,} overview texels + {tiles} x {tiles} UDIM tiles of {tile_texels}^2 texels")


STAGE = Stage(
    name="world",
    version=1,
    description="Assemble world.usda: the terrain mesh and material, and every upstream USD layer.",
    inputs=(Input("terrain", one_of=GROUND_SOURCES, description="the ground: the final terrain with the river beds carved", channels=("height",),
                  units="m"),
            Input("splat", one_of=("vegetation.splat",), optional=True,
                  description="ground splat weights: the ground material's one definition of rock, scree, grass, "
                  "dry grass, mud and snow", channels=SPLAT_CHANNELS, units="1"),) + LAYER_INPUTS + ASSET_INPUTS,
    outputs=(
        Artifact("world.root", kind="usd", file="world.usda", shape="any", publish=True, beside=("dcc.usdc",),
                 description="the root layer composing every layer of the world; beside it dcc.usdc, its strongest "
                 "sublayer: the per-tile `lod` selection a DCC renders with (dcc_layer.py)"),
        Artifact("world.terrain", kind="usd", file="terrain.usdc", shape="any", beside=("terrain/*.usdc",),
                 description="the terrain mesh and its material; beside it terrain/tile_x<i>_y<j>.usdc, one payload "
                 "per terrain tile holding its LOD meshes (terrain_tiles.py)"),
        Artifact("world.albedo", kind="texture", file="albedo.exr", shape="any", units="linear RGB",
                 beside=("ground.*.exr", "normal.exr", "splat_*.exr", "near_*.png", "detail/*.png"),
                 description="ground colour texture (an overview), tiled and mip-mapped; beside it the UDIM albedo "
                 "tiles ground.<UDIM>.exr from the splat weights and the normal map from the final height; the "
                 "detail layer (detail/*.png, splat_*.exr, near_*.png: stages/world/ground_near.py)"),
    ),
    params=WorldParams,
    run=run,
    run_tiled=run_tiled,
    check=check,
    report=(ReportPicture("view", world_picture),),
    source_dir=Path(__file__).parent,
    shared_params=("mesh_max_vertices",),
    uses_opencl=True,  # the ground albedo tiles (ground.cl)
    uses_seed=True,  # the ground's detail noise (ground.detail_tables)
)
