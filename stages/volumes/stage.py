"""The volumes stage: every placed species' plant asset as a mip-mapped voxel
volume (seed 002's volume method, one grid instead of six; Volumetric
Billboards' 128^3 colour volume), measured against its mesh.

1. Read each placed species' asset as the plants stage wrote it
   (worldlib.render.usd_asset: meshes, card and bark textures through the
   materials), at LOD `lod`.
2. Voxelize it (voxelize.py, OpenCL kernel surface_samples with a numpy
   reference): coverage density, premultiplied albedo, mean normal and its
   length, from the alpha-tested card texels and the bark; the woody solid
   by its occupied share of each voxel.
3. Mips (worldlib.volumes.dense): 2x2x2 averages that keep the mean coverage.
4. Error (error.py): each level composited front to back (OpenCL kernel
   composite) against the mesh rendered by worldlib/render from held-out
   views: alpha IoU, PSNR of premultiplied colour; the woody solid's
   occupied volume against manifold3d's volume of the Wood mesh.
5. Write each level as an EXR Z-slice atlas (worldlib.volumes.dense.write_atlas,
   layout and errors in the header), with vdb (the default) also as an
   OpenVDB file (worldlib.volumes.vdb, every level of a species in one run
   of the system Python), and volumes.usda: /Volumes/<species> with a `mip`
   variant set whose variants hold a UsdVol.Volume (OpenVDBAsset fields
   density and albedo naming the .vdb).

Only placed species are voxelized; an unchanged plant asset gives the same
key (its content is the key's input), so it is never voxelized again.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import usdio
from worldlib.volumes import dense as volume
from pipeline.contract import Artifact, Check, CheckContext, Input, Param, ParamError, Params, RunContext, Stage
from pipeline.errors import StageError
from pipeline.limits import leading_key
from worldlib.render.usd_asset import load_asset

from . import error
from .voxelize import backend, voxelize

VOLUMES_ROOT = "/Volumes"


class VolumesParams(Params):
    voxels: int = Param(128, units="voxels", description="voxels along the longest side of each plant's box (cubic "
                        "voxels; 32, 64, 128 are the usual choices)", ge=8, le=256)
    mip_levels: int = Param(5, units="levels", description="levels written, each with voxels twice the edge of the one "
                            "before (the finest's sides are padded to a multiple of 2^(levels-1))", ge=1, le=8)
    lod: int = Param(0, units="level", description="the plant asset's LOD that is voxelized", ge=0, le=7)
    samples_per_voxel: float = Param(1.5, units="samples", description="surface samples per voxel edge on every "
                                     "triangle (point sampling of the card textures' alpha; 1.5 is as close to the mesh "
                                     "as 2 or 3, with half the samples of 2)",
                                     ge=1.0, le=16.0)
    solid_columns: int = Param(4, units="columns", description="columns per voxel side that measure the woody solid's "
                               "occupancy", ge=1, le=16)
    error_view_pixels: int = Param(96, units="pixels", description="size of the held-out error views (0: no error "
                                   "views)", ge=0, le=1024)
    error_views: int = Param(2, units="views", description="held-out views the error is measured from, of "
                             "error.HELD_OUT_VIEWS (the bake's default measures two; bench.volumes all four)",
                             ge=1, le=4)
    error_view_samples: int = Param(2, units="samples", description="n x n samples a pixel of the mesh renders the "
                                    "volume is compared with (1 point-samples thin needles, so a conifer's reference "
                                    "loses coverage)", ge=1, le=4)
    use_opencl: bool = Param(True, description="voxelize and composite with the OpenCL kernels (false: the numpy "
                             "reference, small meshes only)")
    vdb: bool = Param(True, description="also write each level as OpenVDB (<species>.mip<k>.vdb, grids density and "
                      "albedo, the OpenVDBAsset fields of the UsdVol.Volume that Blender, Houdini and Omniverse "
                      "render); needs Debian's python3-openvdb (worldlib/volumes/vdb.py): without it the bake is "
                      "refused before any stage runs, never baked without the .vdb files")


def _manifold_volume(scene, wood: np.ndarray) -> float | None:
    """manifold3d's volume of the Wood triangles, welded by position."""
    import manifold3d as m3d

    if len(wood) == 0:
        return None
    corners = scene.positions[scene.triangles[wood]].reshape(-1, 3)
    points, inverse = np.unique(corners, axis=0, return_inverse=True)
    solid = m3d.Manifold(m3d.Mesh(vert_properties=np.ascontiguousarray(points, np.float32),
                                  tri_verts=np.ascontiguousarray(inverse.reshape(-1, 3), np.uint32)))
    if solid.status() != m3d.Error.NoError:
        return None
    return float(solid.volume())


def load_species(name: str, usdc: Path, params: VolumesParams):
    """The asset level that is voxelized (LOD `lod`, else LOD0)."""
    levels = load_asset(usdc, levels=[params.lod]) or load_asset(usdc, levels=[0])
    asset = levels[0]
    if asset.scene.n_triangles == 0:
        raise StageError(f"volumes: the asset of {name} has no triangles")
    return asset


RUN_TIMES = ("seconds_load", "seconds_voxelize", "seconds_error", "seconds")  # of volume_species' report


def volume_species(env, name: str, asset, params: VolumesParams, out_dir: Path,
                   provenance: dict, t_load: float = 0.0) -> tuple[dict, list[volume.VolumeLevel]]:
    """One species: its levels written beside the layer; returns its report
    and levels (the report's RUN_TIMES are the run's, which run() keeps out
    of stats.json). `env`: the OpenCL device (the stage's ctx.cl)."""
    t0 = time.perf_counter() - t_load
    t = time.perf_counter()
    kernels_env = env if params.use_opencl else None  # None: the numpy references
    vox = voxelize(kernels_env, asset.scene, asset.parts, params.voxels, params.mip_levels, params.samples_per_voxel,
                   solid_sub=params.solid_columns)
    t_vox = time.perf_counter() - t
    chain = volume.mip_chain(vox.level, params.mip_levels)
    for k, lv in enumerate(chain):
        lv.check_finite(f"volumes: {name} mip {k}")
    mean0 = chain[0].mean_density()
    report: dict[str, Any] = {"seconds_load": t_load, "seconds_voxelize": t_vox, "samples": vox.samples,
                              "triangles": asset.scene.n_triangles, "grid": list(chain[0].shape_xyz),
                              "voxel_m": chain[0].voxel_m, "levels": []}
    wood = np.nonzero(asset.parts == "Wood")[0]
    solid = _manifold_volume(asset.scene, wood)
    report["wood"] = {"occupied_m3": vox.wood_volume_m3, "manifold_m3": solid,
                      "relative_error": (vox.wood_volume_m3 - solid) / solid if solid else None}
    t = time.perf_counter()
    meshes, cams = [], []
    if params.error_view_pixels:
        lo, hi = asset.scene.positions.min(0), asset.scene.positions.max(0)
        cams = error.view_cameras(lo, hi, error.HELD_OUT_VIEWS[:params.error_views])
        # rendered once per view, compared with every mip level
        meshes = error.mesh_views(env, asset.scene, cams, params.error_view_pixels, params.error_view_samples)
    be = backend(kernels_env)
    for k, lv in enumerate(chain):
        mean = lv.mean_density()
        entry: dict[str, Any] = {"mip": k, "grid": list(lv.shape_xyz), "voxel_m": lv.voxel_m, "bytes": lv.nbytes,
                                 "bbox_min": [float(v) for v in lv.origin], "bbox_max": [float(v) for v in lv.bbox_max],
                                 "bytes_rgba8": int(lv.density.size * 4), "mean_density": mean,
                                 "mean_density_drift": abs(mean - mean0) / mean0 if mean0 > 0 else 0.0,
                                 "max_normal_length": float(np.linalg.norm(lv.normal, axis=-1).max())}
        if meshes:
            errs = error.level_errors(meshes, error.level_views(lv, cams, params.error_view_pixels, be))
            entry.update({k2: v for k2, v in errs.items() if k2 != "views"})
            entry["views"] = errs["views"]
        file = f"{name}.mip{k}.exr"
        entry["file"] = file
        if params.vdb:
            entry["vdb"] = f"{name}.mip{k}.vdb"
        volume.write_atlas(out_dir / file, lv, k, {**provenance, "species": name},
                           {"volume_errors": {k2: v for k2, v in entry.items() if k2 not in ("file", "views")}})
        report["levels"].append(entry)
    if params.vdb:  # every level in one run of the system Python
        from worldlib.volumes.vdb import write_vdbs

        write_vdbs([(out_dir / e["vdb"], lv) for e, lv in zip(report["levels"], chain)])
    report["seconds_error"] = time.perf_counter() - t
    report["seconds"] = time.perf_counter() - t0
    return report, chain


def write_layer(path: Path, provenance: dict, species: dict[str, list[volume.VolumeLevel]], reports: dict,
                vdb: bool = False) -> None:
    """volumes.usda: /Volumes (kind group), /Volumes/<species> (kind
    component) with a `mip` variant set, each variant a UsdVol.Volume."""
    from pxr import Kind, Usd, UsdGeom

    stage, root = usdio.create_stage(path, provenance, root=VOLUMES_ROOT, kind="group")
    for name, chain in species.items():
        prim = UsdGeom.Xform.Define(stage, f"{VOLUMES_ROOT}/{name}")
        Usd.ModelAPI(prim).SetKind(Kind.Tokens.component)
        volume.define_mip_volumes(stage, f"{VOLUMES_ROOT}/{name}", chain, [f"./{name}.mip{k}.exr" for k in range(len(chain))],
                                  vdb_files=[f"./{name}.mip{k}.vdb" for k in range(len(chain))] if vdb else None)
        lo, hi = chain[0].origin, chain[0].bbox_max
        from pxr import Gf, Vt

        UsdGeom.ModelAPI(prim).SetExtentsHint(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        summary = {"levels": [{k: e[k] for k in e if k != "views"} for e in reports[name]["levels"]],
                   "wood": reports[name]["wood"]}
        prim.GetPrim().SetCustomDataByKey("worldbake:volume", json.dumps(summary, sort_keys=True))
    stage.GetRootLayer().Save()


def run(ctx: RunContext, inputs: dict[str, Any], params: VolumesParams) -> dict[str, Any]:
    plants_layer: Path = inputs["plants"]
    placed = inputs.get("placed")
    folder = plants_layer.parent
    names = [n for n in (placed["placed"] if placed is not None else []) if (folder / f"{n}.usdc").is_file()]
    reports, chains = {}, {}
    runs: dict[str, dict] = {}  # per species its seconds and whether it was reused: metrics, never stats.json
    for i, name in enumerate(names):
        ctx.progress(i / max(len(names), 1), f"volumes: {name}")
        t0 = time.perf_counter()
        asset = load_species(name, folder / f"{name}.usdc", params)
        # a species is a unit (pipeline.units): an asset that did not change is not voxelized again when
        # another species' did
        unit = ctx.unit(name, {"asset": asset.scene.digest(), "parts": "\n".join(map(str, asset.parts)),
                               "params": {k: v for k, v in params.model_dump(mode="json").items() if k != "enabled"}})
        saved = unit.restore(ctx.out_dir)
        if saved is not None:
            reports[name] = saved
            runs[name] = {**unit.record.get("seconds", {}), "reused": True}  # the seconds of the run that made it
            chains[name] = [volume.read_atlas(ctx.out_dir / e["file"]) for e in saved["levels"]]
            continue
        reports[name], chains[name] = volume_species(ctx.cl, name, asset, params, ctx.out_dir, unit.provenance,
                                                     time.perf_counter() - t0)
        seconds = {k: reports[name].pop(k) for k in RUN_TIMES}
        unit.save(ctx.out_dir, [f for e in reports[name]["levels"] for f in (e["file"], e.get("vdb")) if f],
                  json.loads(json.dumps(reports[name])), record={"seconds": seconds})
        runs[name] = {**seconds, "reused": False}
        drift = max(e["mean_density_drift"] for e in reports[name]["levels"])
        if drift > 1e-6:
            raise StageError(f"volumes: {name}: the mips change the mean coverage by {drift:.2e} (relative)")
    layer = ctx.path("volumes.assets")
    write_layer(layer, ctx.provenance, chains, reports, params.vdb)
    errors = usdio.validate(layer)
    if errors:
        raise StageError("volumes: the layer fails USD validation: " + "; ".join(errors[:10]))
    ctx.metrics.update(species={n: {**{k: v for k, v in r.items() if k != "levels"}, **runs[n]}
                                for n, r in reports.items()}, voxelized=names)
    ctx.progress(1.0, "volumes: done")
    return {"volumes.assets": layer, "volumes.stats": {"species": reports, "voxelized": names,
                                                       "not_voxelized": [n for n in (placed or {}).get("placed", [])
                                                                         if n not in names]}}


MAX_VOXEL_SAMPLES = 4e9  # per species (the defaults: about 4e7)


def check(params: VolumesParams, ctx: CheckContext) -> Check:
    """The finest grid must halve exactly down the mips; memory: per species
    the finest level's 8 float32 channels, its mips (1/7 more) and the float64
    voxel sums (10 a voxel), about voxels^3 x 150 B at most. Work, in
    voxel-samples per species (a species at a time): the woody solid's
    columns (solid_columns^2 a voxel side, each through the grid), the error
    views' rays marched through every level (under twice the finest's voxels)
    and the mesh's reference samples, at most MAX_VOXEL_SAMPLES."""
    step = 2 ** (params.mip_levels - 1)
    if params.voxels % step:
        raise ParamError("voxels", f"{params.voxels} voxels cannot halve {params.mip_levels - 1} times; use a multiple "
                         f"of {step} or fewer mip_levels")
    if params.vdb:
        from worldlib.volumes.vdb import require_writer

        require_writer("a world without .vdb volumes: no DCC renders them")
    n = params.voxels ** 3
    solid = n * params.solid_columns ** 2
    views = params.error_views * params.error_view_pixels ** 2 if params.error_view_pixels else 0
    march = views * 2 * params.voxels  # every level's views march its voxels: under twice the finest's
    reference = views * params.error_view_samples ** 2
    return Check(memory_bytes=150.0 * n + 4e8, memory_how=f"{params.voxels}^3 voxels x 150 B + 400 MB of surface samples",
                 work=solid + march + reference, work_unit="voxel-samples per species", work_limit=MAX_VOXEL_SAMPLES,
                 work_how=f"{params.voxels}^3 voxels x {params.solid_columns}^2 solid_columns + {params.error_views} "
                 f"error_views x {params.error_view_pixels}^2 pixels x (2 x {params.voxels} voxels marched + "
                 f"{params.error_view_samples}^2 error_view_samples)",
                 work_key=leading_key(params, grows=("voxels", "solid_columns", "error_views", "error_view_pixels",
                                                     "error_view_samples")))


STAGE = Stage(
    name="volumes",
    version=1,
    description="per placed species a mip-mapped voxel volume (density, premultiplied albedo, mean normal) as EXR "
    "Z-slice atlases and UsdVol.Volume prims, with its error against the mesh from held-out views",
    inputs=(Input("plants", one_of=("plants.assets",), description="the plant assets (plants.usda and the species "
                  "layers and textures beside it)"),
            Input("placed", one_of=("vegetation.placed",), optional=True,
                  description="the species the vegetation map placed: only those are voxelized")),
    outputs=(Artifact("volumes.assets", kind="usd", file="volumes.usda", shape="any", beside=("*.mip*.exr", "*.mip*.vdb"),
                      description="/Volumes (kind group): per species a `mip` variant set of UsdVol.Volume prims, "
                      "each level an EXR Z-slice atlas <species>.mip<k>.exr (channels albedo.RGB premultiplied by "
                      "density, density 1/m, normal.xyz, surface m^2/m^3; layout and errors in the header) and, "
                      "with vdb = true, <species>.mip<k>.vdb (worldlib.volumes.vdb: the same voxels, albedo not "
                      "premultiplied) that the Volume's OpenVDBAsset fields name"),
             Artifact("volumes.stats", kind="json", file="stats.json", shape="any",
                      description="per species: grid, per mip level memory, mean coverage, alpha IoU and "
                      "PSNR against the mesh from held-out views; the woody solid's volume against manifold3d's "
                      "(timings and reuse are metrics)")),
    params=VolumesParams,
    run=run,
    check=check,
    source_dir=Path(__file__).parent,
    uses_opencl=True,
)
