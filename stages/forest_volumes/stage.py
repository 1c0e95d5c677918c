"""The forest volumes stage: each vegetation quadtree tile that holds a
forest as one coarse voxel volume, the farthest LOD of the vegetation
(seed 002's conclusion: volumes pay off as whole forest sectors, as in
Volumetric Billboards, Decaudin and Neyret 2009).

1. Read the instances (vegetation's PointInstancers per leaf tile and
   species: positions, orientations, scales) and the species volumes (the
   volumes stage's EXR atlases, through volumes.usda).
2. Per tile with instances of a species at least forest_min_height_m tall:
   a grid of cubic voxels of voxel_m over the instances' boxes (coarser by
   powers of 2 while it would pass max_voxels), padded to whole mips.
3. Splat: every occupied voxel of each species' level pooled to about the
   sector voxel (a tree is a few voxels) is carried through each
   instance's transform and added to the 8 sector voxels around it with
   trilinear weights; what it holds (extinction x volume, premultiplied
   albedo, surface, surface x normal) scales with the instance's area
   (scale^2), so the sector keeps the plants' projected area. np.bincount
   adds in instance order: deterministic.
4. The grid is clipped to its occupied voxels (whole mips kept), then mips,
   EXR atlases in half floats but for density (pipeline.volume; a far LOD
   needs no more than 3 digits, and it nearly halves the disk; density stays
   float32 so the stored mips keep the mean coverage) and sectors.usda: over each
   forest tile /World/Vegetation/q<path> a FarVolume prim (purpose proxy)
   with a `mip` variant set of UsdVol.Volume prims.

Only the instances change a sector; a world whose instances and plant
volumes are unchanged reuses them (the key hashes both).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import usdio, volume
from pipeline.contract import Artifact, Check, CheckContext, Input, Param, Params, RunContext, Stage
from pipeline.errors import InputError, StageError

MAX_DEPOSITS = 4_000_000  # bounds the splat's index and weight buffers per batch


class ForestVolumesParams(Params):
    voxel_m: float = Param(8.0, units="m", description="voxel edge of the sector volumes (made coarser by powers of 2 "
                           "where a sector would pass max_voxels; 8 m: a 1 km tile is 128 voxels across, a tree 2 "
                           "to 3 voxels tall)", gt=0.05, le=1000.0)
    mip_levels: int = Param(3, units="levels", description="levels per sector, each with voxels twice the edge", ge=1,
                            le=6)
    max_voxels: int = Param(4_000_000, units="voxels", description="largest finest grid of one sector", ge=1000,
                            le=200_000_000)
    forest_min_height_m: float = Param(1.0, units="m", description="species whose volume is lower than this (grass, "
                                       "flowers) are left out of the sectors", ge=0.0, le=200.0)


class SpeciesVolume:
    """A species' levels as the volumes stage listed them, each read from its
    atlas when first needed (a sector needs only coarse levels)."""

    def __init__(self, folder: Path, entries: list[dict]):
        self.folder, self.entries = folder, entries
        self._read: dict[int, volume.VolumeLevel] = {}

    @property
    def height_m(self) -> float:
        return self.entries[0]["bbox_max"][1] - self.entries[0]["bbox_min"][1]

    @property
    def corners(self) -> np.ndarray:
        lo, hi = self.entries[0]["bbox_min"], self.entries[0]["bbox_max"]
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    def level(self, k: int) -> volume.VolumeLevel:
        if k not in self._read:
            self._read[k] = volume.read_atlas(self.folder / self.entries[k]["file"])
        return self._read[k]

    def level_for(self, voxel_m: float) -> volume.VolumeLevel:
        """The source of a splat into voxels of voxel_m: the coarsest level
        at most that edge (else the finest), pooled further while its voxels
        stay at most the edge: a plant splats as a few voxels, each spread
        over the 8 sector voxels around its centre."""
        fine = [k for k, e in enumerate(self.entries) if e["voxel_m"] <= voxel_m]
        level = self.level(fine[-1] if fine else 0)
        while 2 * level.voxel_m <= voxel_m and max(level.density.shape) > 1:
            level = volume.downsample(volume.pad_even(level))
        return level


def read_species_volumes(layer: Path) -> dict[str, SpeciesVolume]:
    from pxr import Usd

    stage = Usd.Stage.Open(str(layer))
    out = {}
    for prim in stage.GetPseudoRoot().GetAllChildren():
        for sp in prim.GetChildren():
            data = sp.GetCustomDataByKey("worldbake:volume")
            if data:
                out[sp.GetName()] = SpeciesVolume(layer.parent, json.loads(data)["levels"])
    return out


@dataclass
class TileInstances:
    path: str  # the tile prim
    bounds_xz: tuple[float, ...]
    species: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]  # name -> positions, rotations (n,3,3), scales (n,)


def _rotations(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) from unit quaternions (n, 4) as (real, i, j, k)."""
    q = q.astype(np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


def read_tiles(layer: Path) -> list[TileInstances]:
    """Every leaf tile's instancers, in prim order."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(layer))
    tiles: dict[str, TileInstances] = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.PointInstancer):
            continue
        pi = UsdGeom.PointInstancer(prim)
        tile = prim.GetParent()
        key = str(tile.GetPath())
        if key not in tiles:
            tiles[key] = TileInstances(key, tuple(tile.GetCustomDataByKey("worldbake:bounds_xz_m") or ()), {})
        pos = np.asarray(pi.GetPositionsAttr().Get(), np.float64).reshape(-1, 3)
        # Vt.QuathArray holds (i, j, k, real) per quaternion
        q = np.asarray(pi.GetOrientationsAttr().Get(), np.float64).reshape(-1, 4)[:, [3, 0, 1, 2]]
        scales = np.asarray(pi.GetScalesAttr().Get(), np.float64).reshape(-1, 3)
        if not (np.isfinite(pos).all() and np.isfinite(q).all() and np.isfinite(scales).all()):
            raise InputError(f"{layer}: {prim.GetPath()} holds NaN or Inf")
        tiles[key].species[prim.GetName()] = (pos, _rotations(q), scales.mean(1))
    return list(tiles.values())


def sector_grid(boxes_lo: np.ndarray, boxes_hi: np.ndarray, voxel_m: float, mip_levels: int,
                max_voxels: int) -> tuple[np.ndarray, float, tuple[int, int, int]]:
    lo, hi = boxes_lo.min(0), boxes_hi.max(0)
    multiple = 2 ** (mip_levels - 1)
    voxel = voxel_m
    while True:
        n = np.maximum(np.ceil((hi - lo) / voxel - 1e-9).astype(int), 1)
        n = -(-n // multiple) * multiple
        if int(np.prod(n)) <= max_voxels:
            break
        voxel *= 2
    origin = 0.5 * (lo + hi) - 0.5 * n * voxel
    return origin, voxel, (int(n[0]), int(n[1]), int(n[2]))


def splat(sector: volume.VolumeLevel, source: volume.VolumeLevel, pos: np.ndarray, rot: np.ndarray,
          scale: np.ndarray, acc: np.ndarray) -> None:
    """Add the source level at each instance transform into acc (8, voxels):
    extinction, premultiplied albedo (3), surface, surface x normal (3)."""
    nx, ny, nz = sector.shape_xyz
    occupied = np.nonzero(source.density.ravel() > 0)[0]
    if len(occupied) == 0:
        return
    sz, sy_, sx = np.unravel_index(occupied, source.density.shape)
    centres = source.origin + (np.stack([sx, sy_, sz], 1) + 0.5) * source.voxel_m
    flat = lambda a: a.reshape(-1, *a.shape[3:])[occupied]  # noqa: E731
    dens, alb, surf, nrm = flat(source.density), flat(source.albedo), flat(source.surface), flat(source.normal)
    ratio = (source.voxel_m / sector.voxel_m) ** 3
    batch = max(1, MAX_DEPOSITS // (8 * len(occupied)))
    for b0 in range(0, len(pos), batch):
        P, R, S = pos[b0:b0 + batch], rot[b0:b0 + batch], scale[b0:b0 + batch]
        world = P[:, None, :] + S[:, None, None] * np.einsum("nij,vj->nvi", R, centres)
        u = (world - sector.origin) / sector.voxel_m - 0.5
        i0 = np.floor(u).astype(np.int64)
        f = u - i0
        k = (S ** 2)[:, None] * ratio  # what a voxel holds scales with the instance's area
        normal = np.einsum("nij,vj->nvi", R, nrm.astype(np.float64))
        values = np.empty((len(P), len(occupied), 8))
        values[..., 0] = k * dens[None]
        values[..., 1:4] = k[..., None] * alb[None]
        values[..., 4] = k * surf[None]
        values[..., 5:8] = (k * surf[None])[..., None] * normal
        indices, weighted = [], []
        for dk in (0, 1):
            for dj in (0, 1):
                for di in (0, 1):
                    ii, jj, kk = i0[..., 0] + di, i0[..., 1] + dj, i0[..., 2] + dk
                    w = ((f[..., 0] if di else 1 - f[..., 0]) * (f[..., 1] if dj else 1 - f[..., 1])
                         * (f[..., 2] if dk else 1 - f[..., 2]))
                    ok = (ii >= 0) & (jj >= 0) & (kk >= 0) & (ii < nx) & (jj < ny) & (kk < nz)
                    indices.append(((kk * ny + jj) * nx + ii)[ok])
                    weighted.append(w[ok][:, None] * values[ok])
        idx, wv = np.concatenate(indices), np.concatenate(weighted)
        for c in range(8):
            acc[c] += np.bincount(idx, wv[:, c], acc.shape[1])


def bake_sector(tile: TileInstances, species: dict[str, SpeciesVolume], params: ForestVolumesParams) -> tuple[
        volume.VolumeLevel, dict] | None:
    names = [n for n in tile.species if n in species]
    if not names:
        return None
    los, his = [], []
    for n in names:
        radius = float(np.linalg.norm(species[n].corners, axis=1).max())
        pos, _, s = tile.species[n]
        los.append(pos - (radius * s)[:, None])
        his.append(pos + (radius * s)[:, None])
    origin, voxel, shape = sector_grid(np.concatenate(los), np.concatenate(his), params.voxel_m, params.mip_levels,
                                       params.max_voxels)
    sector = volume.empty_level(shape, origin, voxel)
    acc = np.zeros((8, sector.density.size))
    counts = {}
    for n in names:
        pos, rot, s = tile.species[n]
        splat(sector, species[n].level_for(voxel), pos, rot, s, acc)
        counts[n] = int(len(pos))
    full = sector.density.shape
    grid = acc.reshape(8, *full)
    box = occupied_box(grid[0] > 0, 2 ** (params.mip_levels - 1))
    if box is None:
        return None
    grid = grid[(slice(None),) + box]
    nz, ny, nx = grid.shape[1:]
    sector = volume.empty_level((nx, ny, nz), origin + voxel * np.array([box[2].start, box[1].start, box[0].start]),
                                voxel)
    sector.density = grid[0].astype(np.float32)
    sector.albedo = np.moveaxis(grid[1:4], 0, -1).astype(np.float32)
    sector.surface = grid[4].astype(np.float32)
    # normals only where there is surface: a sector is mostly air (a forest on a slope fills ~1 % of its box)
    where = np.nonzero(grid[4].ravel() > 0)[0]
    normal = grid[5:8].reshape(3, -1)[:, where].T / grid[4].ravel()[where, None]
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(length > 1.0, normal / np.maximum(length, 1e-30), normal)
    sector.normal.reshape(-1, 3)[where] = normal
    return sector, {"instances": counts, "grid": [nx, ny, nz], "voxel_m": voxel,
                    "grid_before_clip": [full[2], full[1], full[0]]}


def occupied_box(occupied: np.ndarray, multiple: int) -> tuple[slice, slice, slice] | None:
    """Per axis of `occupied` (whose sides are multiples of `multiple`) the
    smallest range holding every True, grown to a multiple of `multiple`
    (towards the far side, else the near one); None when nothing is."""
    if not occupied.any():
        return None
    box = []
    for axis in range(3):
        rest = tuple(a for a in range(3) if a != axis)
        hit = np.nonzero(occupied.any(axis=rest))[0]
        lo, hi, n = int(hit[0]), int(hit[-1]) + 1, occupied.shape[axis]
        size = -(-(hi - lo) // multiple) * multiple
        lo = min(lo, n - size)
        box.append(slice(lo, lo + size))
    return tuple(box)


def run(ctx: RunContext, inputs: dict[str, Any], params: ForestVolumesParams) -> dict[str, Any]:
    from pxr import Gf, Kind, Usd, UsdGeom, Vt

    t0 = time.perf_counter()
    species = read_species_volumes(inputs["volumes"])
    forest = {n: v for n, v in species.items()
              if v.height_m >= params.forest_min_height_m}
    tiles = read_tiles(inputs["instances"])
    layer = ctx.path("forest_volumes.sectors")
    stage, _ = usdio.create_stage(layer, ctx.provenance)
    report: dict[str, Any] = {"forest_species": sorted(forest), "sectors": {}}
    for i, tile in enumerate(tiles):
        ctx.progress(i / max(len(tiles), 1), f"forest volumes: {tile.path}")
        t = time.perf_counter()
        baked = bake_sector(tile, forest, params)
        if baked is None:
            continue
        sector, info = baked
        chain = volume.mip_chain(sector, params.mip_levels)
        stem = tile.path.rsplit("/", 1)[-1]
        files = [f"{stem}.mip{k}.exr" for k in range(len(chain))]
        mean0 = chain[0].mean_density()
        info["levels"] = []
        for k, (lv, f) in enumerate(zip(chain, files)):
            lv.check_finite(f"forest volumes: {tile.path} mip {k}")
            drift = abs(lv.mean_density() - mean0) / mean0 if mean0 > 0 else 0.0
            if drift > 1e-6:
                raise StageError(f"forest volumes: {tile.path}: mip {k} changes the mean coverage by {drift:.2e}")
            # the atlas holds density as float32 and the 7 other channels as half floats: 18 B a voxel
            entry = {"mip": k, "grid": list(lv.shape_xyz), "voxel_m": lv.voxel_m, "bytes": lv.nbytes,
                     "bytes_stored": int(lv.density.size * 18), "mean_density": lv.mean_density(),
                     "mean_density_drift": drift}
            volume.write_atlas(ctx.out_dir / f, lv, k, {**ctx.provenance, "tile": tile.path}, {"volume_errors": entry},
                               half=True)
            info["levels"].append(entry)
        info["seconds"] = time.perf_counter() - t
        parts = tile.path.split("/")
        for j in range(2, len(parts) + 1):
            stage.OverridePrim("/".join(parts[:j]))
        far = UsdGeom.Xform.Define(stage, f"{tile.path}/FarVolume")
        Usd.ModelAPI(far).SetKind(Kind.Tokens.subcomponent)
        far.CreatePurposeAttr(UsdGeom.Tokens.proxy)
        volume.define_mip_volumes(stage, f"{tile.path}/FarVolume", chain, [f"./{f}" for f in files])
        far.GetPrim().SetCustomDataByKey("worldbake:volume", json.dumps(info, sort_keys=True))
        lo, hi = chain[0].origin, chain[0].bbox_max
        UsdGeom.ModelAPI(far).SetExtentsHint(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        report["sectors"][tile.path] = info
    stage.GetRootLayer().Save()
    errors = usdio.validate(layer)
    if errors:
        raise StageError("forest volumes: the layer fails USD validation: " + "; ".join(errors[:10]))
    report["seconds"] = time.perf_counter() - t0
    ctx.metrics.update(sectors=len(report["sectors"]), seconds=report["seconds"],
                       seconds_per_sector={k: v["seconds"] for k, v in report["sectors"].items()})
    return {"forest_volumes.sectors": layer, "forest_volumes.stats": report}


def check(params: ForestVolumesParams, ctx: CheckContext) -> Check:
    """Memory: one sector at a time, at most max_voxels: its 8 float64 sums,
    the level's 8 float32 channels and its mips, about 110 B a voxel, and
    the splat's batch buffers (about 40 B a deposit)."""
    return Check(memory_bytes=110.0 * params.max_voxels + 40.0 * MAX_DEPOSITS,
                 memory_how=f"max_voxels = {params.max_voxels:,} x 110 B + {MAX_DEPOSITS:,} deposits x 40 B")


STAGE = Stage(
    name="forest_volumes",
    version=1,
    description="each vegetation quadtree tile that holds a forest as a coarse mip-mapped voxel volume (the far LOD), "
    "splatted from the species volumes at every instance",
    inputs=(Input("volumes", one_of=("volumes.assets",), description="the species volumes (volumes.usda and its atlases)"),
            Input("instances", one_of=("vegetation.instances",), description="the PointInstancers per quadtree tile")),
    outputs=(Artifact("forest_volumes.sectors", kind="usd", file="sectors.usda", shape="any", beside=("*.mip*.exr",),
                      description="over each forest tile /World/Vegetation/q<path>: FarVolume (purpose proxy) with a "
                      "`mip` variant set of UsdVol.Volume prims; each level an EXR Z-slice atlas q<path>.mip<k>.exr "
                      "in half floats (density float32), clipped to the occupied voxels"),
             Artifact("forest_volumes.stats", kind="json", file="stats.json", shape="any",
                      description="per sector: instances per species, grid, voxel size, memory and mean coverage per "
                      "level, time")),
    params=ForestVolumesParams,
    run=run,
    check=check,
    source_dir=Path(__file__).parent,
)
