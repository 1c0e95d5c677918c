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
3. Splat (splat.py, OpenCL kernel `splat` with a numpy reference): each
   instance takes the coarsest level of its species whose voxels, scaled
   by the instance, are at most source_voxel_ratio sector voxels; every
   occupied voxel of it is carried through the instance's transform and,
   as a cube of at most a sector voxel, shared among the sector voxels it
   overlaps; what it holds (extinction x volume, premultiplied albedo,
   surface, surface x normal) scales with the instance's area (scale^2),
   so the sector keeps the plants' projected area. Sums in 64-bit fixed
   point with integer atomics: the same for any work-group size.
4. Only the occupied voxels go on (worldlib.volumes.sparse: a forest on a
   slope fills a few percent of its box): the grid is clipped to them (whole mips
   kept), mips sum the occupied 2 x 2 x 2 blocks, and each level is an EXR
   in the column runs layout (per (x, z) column one run of voxels along y;
   density float32, the other channels half floats; pxr24), and
   sectors.usda: over each forest tile /World/Vegetation/q<path> a
   FarVolume prim (purpose proxy) with a `mip` variant set of
   UsdVol.Volume prims. With vdb (the default) each level is also an
   OpenVDB file q<path>.mip<k>.vdb (worldlib.volumes.vdb: the occupied
   voxels, same transform), which the Volume's OpenVDBAsset fields name, so
   that Blender, Houdini and Omniverse render the sectors; the levels of
   many sectors go to one run of the system Python (VDB_BATCH_VOXELS).
5. Error (column_errors) on error_sectors tiles: the sector's columns, from
   above and from the side, against the instances' own volumes at finer
   voxels: extinction kept, relative L1 per column, cover.

Only the instances change a sector; a world whose instances and plant
volumes are unchanged reuses them (the key hashes both).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import usdio
from worldlib.volumes import dense as volume, sparse as sparse_volume
from pipeline.contract import Artifact, Check, CheckContext, Input, Param, Params, RunContext, Stage
from pipeline.errors import InputError, StageError
from pipeline.limits import leading_key

from . import reference, splat

MAX_DEPOSITS = 4_000_000  # bounds the error reference's index and weight buffers per batch
# The finest level is pxr24, the smallest of the compressions that keep albedo exact: it rounds density to 24-bit
# floats (relative 1.5e-5 a voxel; the half channels stay lossless), and the density is rounded so before the mips
# are made from it (what is stored is what they average). The mips are zip, lossless, so they keep the stored finest
# level's mean coverage.
COMPRESSION = ("pxr24", "zip")
VDB_BATCH_VOXELS = 8_000_000  # occupied voxels held for one run of the OpenVDB writer (about 300 MB of arrays)


class ForestVolumesParams(Params):
    voxel_m: float = Param(8.0, units="m", description="voxel edge of the sector volumes (made coarser by powers of 2 "
                           "where a sector would pass max_voxels; 8 m: a 1 km tile is 128 voxels across, a tree 2 "
                           "to 3 voxels tall)", gt=0.05, le=1000.0)
    mip_levels: int = Param(3, units="levels", description="levels per sector, each with voxels twice the edge", ge=1,
                            le=6)
    max_voxels: int = Param(4_000_000, units="voxels", description="largest finest grid of one sector", ge=1000,
                            le=200_000_000)
    source_voxel_ratio: float = Param(4.0, units="sector voxels", description="largest source voxel of a splat, "
                                      "scaled by its instance, in sector voxels: each instance splats the coarsest "
                                      "level of its species whose voxels, scaled, are at most this. 4: a spruce is "
                                      "one cube of at most a sector voxel (the closer cover from above); 1.25: 8 "
                                      "voxels (the closer canopy height and view from the side, nearly twice the "
                                      "bytes)",
                                      ge=0.25, le=8.0)
    use_opencl: bool = Param(True, description="splat with the OpenCL kernel (false: its numpy reference, small "
                             "forests only)")
    error_sectors: int = Param(8, units="sectors", description="sectors (spread evenly over the tiles) whose "
                               "columns are measured against their instances (column_errors; 0: none)", ge=0,
                               le=100_000)
    forest_min_height_m: float = Param(1.0, units="m", description="species whose volume is lower than this (grass, "
                                       "flowers) are left out of the sectors", ge=0.0, le=200.0)
    vdb: bool = Param(True, description="also write each sector level as OpenVDB (q<path>.mip<k>.vdb, grids density "
                      "and albedo, the OpenVDBAsset fields of the UsdVol.Volume that Blender, Houdini and Omniverse "
                      "render); needs Debian's python3-openvdb (worldlib/volumes/vdb.py): without it the bake is "
                      "refused before any stage runs, never baked without the .vdb files")


class SpeciesVolume:
    """A species' levels as the volumes stage listed them, each read from its
    atlas when first needed (a sector needs only coarse levels)."""

    def __init__(self, folder: Path, entries: list[dict]):
        self.folder, self.entries = folder, entries
        self._read: dict[int, volume.VolumeLevel] = {}
        self._pooled: dict[tuple[int, int], volume.VolumeLevel] = {}

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
        stay at most the edge: a plant splats as a few voxels, each shared
        among the sector voxels it overlaps."""
        fine = [k for k, e in enumerate(self.entries) if e["voxel_m"] <= voxel_m]
        k = fine[-1] if fine else 0
        level, pooled = self.level(k), 0
        while 2 * level.voxel_m <= voxel_m and max(level.density.shape) > 1:
            pooled += 1
            if (k, pooled) not in self._pooled:
                self._pooled[k, pooled] = volume.downsample(volume.pad_even(level))
            level = self._pooled[k, pooled]
        return level

    def levels_for(self, voxel_m: float, scales: np.ndarray) -> list[tuple[volume.VolumeLevel, np.ndarray]]:
        """Instances by their source level: instance i (scale s_i) splats
        level_for(voxel_m / s_i), whose voxels, scaled, are at most a sector
        voxel (a 20 m spruce is several voxels, a 3 m one a single voxel).
        Returns (level, indices of its instances), finest level first."""
        # level_for(t) changes only where t passes a level's voxel edge, e_k x 2^p (file level k pooled p times)
        edges = np.unique([e["voxel_m"] * 2.0 ** p for e in self.entries for p in range(16)])
        target = voxel_m / np.asarray(scales, np.float64)
        chosen = np.maximum(np.searchsorted(edges, target * (1 + 1e-9), side="right") - 1, 0)
        groups: dict[int, tuple[volume.VolumeLevel, list]] = {}
        for j in np.unique(chosen):
            level = self.level_for(float(edges[j]) * (1 + 1e-9))
            groups.setdefault(id(level), (level, []))[1].append(np.flatnonzero(chosen == j))
        return sorted(((lv, np.sort(np.concatenate(w))) for lv, w in groups.values()), key=lambda g: g[0].voxel_m)


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


def bake_sector(env, tile: TileInstances, species: dict[str, SpeciesVolume], params: ForestVolumesParams) -> tuple[
        sparse_volume.SparseLevel, dict] | None:
    """One tile's sector, splatted on the OpenCL device `env` (the stage's
    ctx.cl) or, with use_opencl false, by the numpy reference."""
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
    counts = {}
    if params.use_opencl:
        device = splat.DeviceSplat(env, shape, origin, voxel)
    else:
        nx, ny, nz = shape
        sums = np.zeros((splat.CHANNELS, nx * ny * nz), np.int64)
    for n in names:
        pos, rot, s = tile.species[n]
        for source, which in species[n].levels_for(voxel * params.source_voxel_ratio, s):
            if params.use_opencl:
                device.add(source, pos[which], rot[which], s[which])
            else:
                reference.splat(shape, origin, voxel, source, pos[which], rot[which], s[which], sums)
        counts[n] = int(len(pos))
    if params.use_opencl:
        sums = device.result()
    full = (shape[2], shape[1], shape[0])
    # only the occupied voxels go on: a forest on a slope fills a few % of its box
    occupied = np.flatnonzero((sums[0] > 0) | (sums[4] > 0))
    if len(occupied) == 0:
        return None
    coords = np.unravel_index(occupied, full)
    box = occupied_range([(int(c.min()), int(c.max()) + 1) for c in coords], full, 2 ** (params.mip_levels - 1))
    nz, ny, nx = (b.stop - b.start for b in box)
    index = ((coords[0] - box[0].start) * ny + coords[1] - box[1].start) * nx + coords[2] - box[2].start
    values = sums[:, occupied] / splat.FIXED
    level = sparse_volume.SparseLevel(
        index, values[0].astype(np.float32), values[1:4].T.astype(np.float32),
        sparse_volume.normals_from_sums(values[5:8].T, values[4]), values[4].astype(np.float32), (nx, ny, nz),
        origin + voxel * np.array([box[2].start, box[1].start, box[0].start]), voxel)
    return level, {"instances": counts, "grid": [nx, ny, nz], "voxel_m": voxel,
                   "grid_before_clip": [full[2], full[1], full[0]]}


ERROR_KEYS = ("extinction_relative", "column_relative_l1", "column_relative_l1_32m", "cover_mae", "cover_bias",
              "side_column_relative_l1", "side_column_relative_l1_32m", "side_cover_mae", "side_cover_bias")


def _projected_deposits(src: volume.VolumeLevel, pos, rot, scale, origin, axes: tuple[int, int], cell_m: float,
                        fine: np.ndarray) -> float:
    """Add each instance's source voxels (extinction x volume x scale^2) to
    the cell of `fine` (rows along axes[1], columns along axes[0], cell_m
    wide) under its carried centre; returns the total held."""
    occ = np.flatnonzero(src.density.ravel() > 0)
    sz, sy, sx = np.unravel_index(occ, src.density.shape)
    centres = src.origin + (np.stack([sx, sy, sz], 1) + 0.5) * src.voxel_m
    held = src.density.ravel()[occ].astype(np.float64) * src.voxel_m ** 3
    ax = list(axes)
    batch, total = max(1, MAX_DEPOSITS // max(len(occ), 1)), 0.0
    for b0 in range(0, len(pos), batch):
        P, R, S = pos[b0:b0 + batch], rot[b0:b0 + batch], scale[b0:b0 + batch]
        world = P[:, None, ax] + S[:, None, None] * np.einsum("nij,vj->nvi", R[:, ax], centres)
        cell = np.floor((world - origin[ax]) / cell_m).astype(np.int64)
        w = (S ** 2)[:, None] * held[None]
        total += float(w.sum())
        ok = (cell >= 0).all(-1) & (cell[..., 0] < fine.shape[1]) & (cell[..., 1] < fine.shape[0])
        fine += np.bincount((cell[..., 1] * fine.shape[1] + cell[..., 0])[ok], w[ok], fine.size).reshape(fine.shape)
    return total


def _projection_errors(sector: np.ndarray, fine: np.ndarray, total: float, h: float) -> dict:
    """Figures of column_errors for one projection: sector (rows, cols) sums
    of extinction x volume, fine the reference on cells half as wide."""
    nr, nc = sector.shape
    instances = fine.reshape(nr, 2, nc, 2).sum(axis=(1, 3))

    def blocks(a: np.ndarray, k: int) -> np.ndarray:
        a = np.pad(a, ((0, -nr % k), (0, -nc % k)))
        return a.reshape(a.shape[0] // k, k, a.shape[1] // k, k).sum(axis=(1, 3))

    k32 = max(1, int(round(32.0 / h)))
    cover_s = 1 - np.exp(-sector / h ** 2)
    cover_r = (1 - np.exp(-fine / (h / 2) ** 2)).reshape(nr, 2, nc, 2).mean(axis=(1, 3))
    seen = (sector > 0) | (instances > 0)
    ref_sum = max(float(instances.sum()), 1e-300)
    return {"extinction_relative": float(sector.sum() / max(total, 1e-300) - 1.0),
            "column_relative_l1": float(np.abs(sector - instances).sum() / ref_sum),
            "column_relative_l1_32m": float(np.abs(blocks(sector, k32) - blocks(instances, k32)).sum() / ref_sum),
            "cover_mae": float(np.abs(cover_s - cover_r)[seen].mean()) if seen.any() else 0.0,
            "cover_bias": float((cover_s - cover_r)[seen].mean()) if seen.any() else 0.0,
            "cover_sector": float(cover_s[seen].mean()) if seen.any() else 0.0,
            "cover_reference": float(cover_r[seen].mean()) if seen.any() else 0.0}


def column_errors(level: sparse_volume.SparseLevel, tile: TileInstances, species: dict[str, SpeciesVolume]) -> dict:
    """The sector's finest level against its instances, column by column,
    from straight above (columns along y) and from the side (along x: how
    the height of the canopy is kept). Reference: every instance's species
    volume at voxels that, scaled, are at most half the sector's
    (SpeciesVolume.levels_for), each voxel's extinction x volume (scale^2,
    as the splat) put in the column of its transformed centre, on columns
    half the sector's voxel wide. Sector: density x voxel^3 summed over each
    of its columns. Figures (from above; side_* from the side):

        extinction_relative     total sector / total reference - 1 (what
                                the splat keeps; clipping loses nothing)
        column_relative_l1      sum |sector - reference| / sum reference
                                per sector column (voxel_m wide)
        column_relative_l1_32m  the same on columns 32 m wide (blocks of
                                sector columns): the error beyond the
                                splat's one-voxel blur
        cover_mae, cover_bias   mean |a_s - a_r| and mean a_s - a_r over
                                the columns either covers, a = 1 -
                                exp(-optical depth) the cover seen along
                                the column; a_r the mean of the reference's
                                fine columns (a sector voxel averages its
                                clumps, so it covers more)."""
    nx, ny, nz = level.shape_xyz
    h = level.voxel_m
    z, rest = np.divmod(level.index, nx * ny)
    y, x = np.divmod(rest, nx)
    held = level.density.astype(np.float64) * h ** 3
    out = {}
    for prefix, axes, (rows, cols), (nr, nc) in (("", (0, 2), (z, x), (nz, nx)), ("side_", (2, 1), (y, z), (ny, nz))):
        sector = np.bincount(rows * nc + cols, held, nr * nc).reshape(nr, nc)
        fine = np.zeros((2 * nr, 2 * nc))
        total = 0.0
        for name, (pos, rot, scale) in tile.species.items():
            if name in species:
                for src, which in species[name].levels_for(h / 2, scale):
                    total += _projected_deposits(src, pos[which], rot[which], scale[which], level.origin, axes, h / 2,
                                                 fine)
        out.update({prefix + k: v for k, v in _projection_errors(sector, fine, total, h).items()})
    return out


def occupied_range(ranges: list[tuple[int, int]], shape: tuple[int, ...], multiple: int) -> tuple[slice, ...]:
    """Per axis the occupied range lo..hi grown to a multiple of `multiple`
    voxels (towards the far side, else the near one) inside the axis's
    `shape` (itself a multiple)."""
    box = []
    for (lo, hi), n in zip(ranges, shape):
        size = -(-(hi - lo) // multiple) * multiple
        lo = min(lo, n - size)
        box.append(slice(lo, lo + size))
    return tuple(box)


def occupied_box(occupied: np.ndarray, multiple: int) -> tuple[slice, slice, slice] | None:
    """Per axis of `occupied` (whose sides are multiples of `multiple`) the
    smallest range holding every True, grown to a multiple of `multiple`
    (towards the far side, else the near one); None when nothing is."""
    if not occupied.any():
        return None
    coords = np.nonzero(occupied)
    return occupied_range([(int(c.min()), int(c.max()) + 1) for c in coords], occupied.shape, multiple)


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
    # run time is a run record (metrics), never content: the layer and stats.json are the same every bake
    seconds_per_sector: dict[str, float] = {}
    phases = {"read": time.perf_counter() - t0, "splat": 0.0, "mips": 0.0, "error": 0.0, "write": 0.0, "usd": 0.0,
              "vdb": 0.0}
    pending_vdb: list = []  # (file, level) not yet written: a batch goes to one run of the system Python
    # the error is measured on error_sectors tiles spread evenly over the list (deterministic)
    measured = set(np.linspace(0, len(tiles) - 1, min(params.error_sectors, len(tiles))).round().astype(int).tolist()
                   if tiles and params.error_sectors else [])
    for i, tile in enumerate(tiles):
        ctx.progress(i / max(len(tiles), 1), f"forest volumes: {tile.path}")
        t = time.perf_counter()
        baked = bake_sector(ctx.cl, tile, forest, params)
        phases["splat"] += time.perf_counter() - t
        if baked is None:
            continue
        sector, info = baked
        t_mips = time.perf_counter()
        sector.density = sparse_volume.round_to_pxr24(sector.density)
        chain = sparse_volume.mip_chain(sector, params.mip_levels)
        phases["mips"] += time.perf_counter() - t_mips
        if i in measured:
            t_err = time.perf_counter()
            info["error"] = column_errors(sector, tile, forest)
            phases["error"] += time.perf_counter() - t_err
        stem = tile.path.rsplit("/", 1)[-1]
        files = [f"{stem}.mip{k}.exr" for k in range(len(chain))]
        mean0 = chain[0].mean_density()
        info["levels"] = []
        t_write = time.perf_counter()
        for k, (lv, f) in enumerate(zip(chain, files)):
            lv.check_finite(f"forest volumes: {tile.path} mip {k}")
            drift = abs(lv.mean_density() - mean0) / mean0 if mean0 > 0 else 0.0
            if drift > 1e-6:
                raise StageError(f"forest volumes: {tile.path}: mip {k} changes the mean coverage by {drift:.2e}")
            entry = {"mip": k, "grid": list(lv.shape_xyz), "voxel_m": lv.voxel_m, "bytes": lv.nbytes,
                     "occupied_voxels": int(len(lv.index)), "mean_density": lv.mean_density(),
                     "mean_density_drift": drift}
            sparse_volume.write_runs(ctx.out_dir / f, lv, k, {**ctx.provenance, "tile": tile.path},
                                     {"volume_errors": entry}, compression=COMPRESSION[min(k, 1)])
            entry["bytes_file"] = (ctx.out_dir / f).stat().st_size
            info["levels"].append(entry)
        phases["write"] += time.perf_counter() - t_write
        vdb_files = [f"{stem}.mip{k}.vdb" for k in range(len(chain))] if params.vdb else None
        if vdb_files:
            pending_vdb += [(ctx.out_dir / f, lv) for f, lv in zip(vdb_files, chain)]
            if sum(len(lv.index) for _, lv in pending_vdb) > VDB_BATCH_VOXELS:
                phases["vdb"] += _write_vdbs(pending_vdb)
        seconds_per_sector[tile.path] = time.perf_counter() - t
        t_usd = time.perf_counter()
        parts = tile.path.split("/")
        for j in range(2, len(parts) + 1):
            stage.OverridePrim("/".join(parts[:j]))
        far = UsdGeom.Xform.Define(stage, f"{tile.path}/FarVolume")
        Usd.ModelAPI(far).SetKind(Kind.Tokens.subcomponent)
        far.CreatePurposeAttr(UsdGeom.Tokens.proxy)
        volume.define_mip_volumes(stage, f"{tile.path}/FarVolume", chain, [f"./{f}" for f in files],
                                  vdb_files=[f"./{f}" for f in vdb_files] if vdb_files else None)
        far.GetPrim().SetCustomDataByKey("worldbake:volume", json.dumps(info, sort_keys=True))
        lo, hi = chain[0].origin, chain[0].bbox_max
        UsdGeom.ModelAPI(far).SetExtentsHint(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        report["sectors"][tile.path] = info
        phases["usd"] += time.perf_counter() - t_usd
    phases["vdb"] += _write_vdbs(pending_vdb)
    t_usd = time.perf_counter()
    stage.GetRootLayer().Save()
    errors = usdio.validate(layer)
    if errors:
        raise StageError("forest volumes: the layer fails USD validation: " + "; ".join(errors[:10]))
    phases["usd"] += time.perf_counter() - t_usd
    report["bytes_files"] = sum(e["bytes_file"] for v in report["sectors"].values() for e in v["levels"])
    errs = [v["error"] for v in report["sectors"].values() if "error" in v]
    if errs:
        report["error"] = {"sectors": len(errs), **{f"{k}_max": max(abs(e[k]) for e in errs) for k in ERROR_KEYS}}
    ctx.metrics.update(sectors=len(report["sectors"]), seconds=time.perf_counter() - t0, phases_seconds=phases,
                       bytes_files=report["bytes_files"], error=report.get("error"),
                       seconds_per_sector=seconds_per_sector)
    return {"forest_volumes.sectors": layer, "forest_volumes.stats": report}


def _write_vdbs(pending: list) -> float:
    """Write the pending (file, level) pairs as .vdb and empty the list;
    returns the seconds it took."""
    from worldlib.volumes.vdb import write_vdbs

    t = time.perf_counter()
    write_vdbs(pending)
    pending.clear()
    return time.perf_counter() - t


MAX_SECTOR_VOXELS = 4e9  # a sector's levels plus the measured sectors' (the defaults: about 4e7)


def check(params: ForestVolumesParams, ctx: CheckContext) -> Check:
    """Memory: one sector at a time, at most max_voxels: its 8 int64 sums
    (64 B a voxel), the occupied voxels' channels and mips (under 20 B a
    voxel of the box), and the error reference's batch buffers (about 40 B
    a deposit). Work, in voxels (the number of sectors is the vegetation
    quadtree's, not a param): one sector's levels, at most max_voxels and
    its mips, plus the error_sectors sectors' columns measured against their
    instances (each up to max_voxels), at most MAX_SECTOR_VOXELS."""
    if params.vdb:
        from worldlib.volumes.vdb import require_writer

        require_writer("sectors without .vdb files: no DCC renders them")
    levels = 8 / 7 * (1 - 8.0 ** -params.mip_levels)  # a sector's levels, each 1/8 of the one before
    work = params.max_voxels * (levels + params.error_sectors)
    return Check(memory_bytes=90.0 * params.max_voxels + 40.0 * MAX_DEPOSITS,
                 memory_how=f"max_voxels = {params.max_voxels:,} x 90 B + {MAX_DEPOSITS:,} deposits x 40 B",
                 work=work, work_unit="voxels", work_limit=MAX_SECTOR_VOXELS,
                 work_how=f"max_voxels = {params.max_voxels:,} x ({levels:.3g} for a sector's {params.mip_levels} "
                 f"mip_levels + {params.error_sectors} error_sectors measured)",
                 work_key=leading_key(params, grows=("max_voxels", "error_sectors", "mip_levels")))


STAGE = Stage(
    name="forest_volumes",
    version=1,
    description="each vegetation quadtree tile that holds a forest as a coarse mip-mapped voxel volume (the far LOD), "
    "splatted from the species volumes at every instance",
    inputs=(Input("volumes", one_of=("volumes.assets",), description="the species volumes (volumes.usda and its atlases)"),
            Input("instances", one_of=("vegetation.instances",), description="the PointInstancers per quadtree tile")),
    outputs=(Artifact("forest_volumes.sectors", kind="usd", file="sectors.usda", shape="any",
                      beside=("*.mip*.exr", "*.mip*.vdb"),
                      description="over each forest tile /World/Vegetation/q<path>: FarVolume (purpose proxy) with a "
                      "`mip` variant set of UsdVol.Volume prims; each level q<path>.mip<k>.exr holds the occupied "
                      "voxels as column runs (worldlib.volumes.sparse: part voxels, half floats but density float32; "
                      "part columns, run.y0/length/offset per (x, z)); with vdb = true also q<path>.mip<k>.vdb "
                      "(worldlib.volumes.vdb), the Volume's OpenVDBAsset fields"),
             Artifact("forest_volumes.stats", kind="json", file="stats.json", shape="any",
                      description="per sector: instances per species, grid, voxel size, memory, occupied voxels, "
                      "file size and mean coverage per level, time, and on error_sectors sectors the column errors "
                      "against the instances (column_errors); the phases' seconds")),
    params=ForestVolumesParams,
    run=run,
    check=check,
    source_dir=Path(__file__).parent,
    uses_opencl=True,
)
