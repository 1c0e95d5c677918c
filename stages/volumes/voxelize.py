"""A plant asset into a voxel volume (worldlib.volumes.dense.VolumeLevel).

1. The grid: cubic voxels over the plant's box, `voxels` along its longest
   side, the other sides padded to whole mips (worldlib.volumes.dense.grid_for_box).
2. Surfaces (every triangle, foliage cards, blades and bark): point samples
   on a barycentric grid about voxel / samples_per_voxel apart, each with
   its share of the triangle's area; a sample where a card's texture alpha
   fails the test is no surface. On the device (kernels.cl surface_sums)
   the samples are summed where they fall, area, area x albedo, area x
   normal, in 64-bit fixed point with integer atomics (no sample leaves the
   device; the sums do not depend on the work-group size); the numpy
   reference writes every sample (kernels.cl surface_samples does the
   same) and reduces them in sample order (samples.SurfaceSums).
3. The woody solid (the watertight Wood mesh): its occupied share of each
   voxel, from columns along z (sub x sub per voxel): the crossings of each
   column with the mesh, sorted, give the inside intervals by winding
   number, whose lengths fill the voxels they cross.
4. The channels: foliage extinction = G x area / voxel volume (G = 1/2),
   wood extinction = occupancy x SOLID_OPTICAL_DEPTH / voxel edge;
   albedo premultiplied by each; normals the area-weighted mean.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worldlib.render import Scene
from worldlib.volumes.dense import LEAF_PROJECTION, SOLID_OPTICAL_DEPTH, VolumeLevel, grid_for_box

from .samples import Grid3, SurfaceSums, sample_table

MAX_SAMPLES_PER_CHUNK = 2_000_000  # bounds the sample buffers (60 B a sample)


def backend(env):
    """The volume kernels with the reference's signatures: on the OpenCL
    device `env` (pipeline.opencl.CL), or the numpy references (env None)."""
    if env is not None:
        import functools
        import types

        from . import device

        return types.SimpleNamespace(**{name: functools.partial(getattr(device, name), env)
                                        for name in ("surface_samples", "composite", "composite_views")})
    from . import reference

    return reference


@dataclass
class Voxelized:
    level: VolumeLevel
    samples: int
    wood_volume_m3: float  # occupied volume of the woody solid in the grid


def plant_grid(scene: Scene, voxels: int, mip_levels: int) -> Grid3:
    p = scene.positions.astype(np.float64)
    origin, voxel, shape = grid_for_box(p.min(0), p.max(0), voxels, 2 ** (mip_levels - 1))
    return Grid3(origin, voxel, shape)


def surface_sums(env, scene: Scene, triangles: np.ndarray, grid: Grid3, samples_per_voxel: float,
                 alpha_threshold: float) -> tuple[SurfaceSums, int]:
    """Voxel sums of the surface samples of `triangles`, and the sample
    count: on the OpenCL device `env`, or the numpy reference (env None)."""
    sums = SurfaceSums.zeros(grid.count)
    if len(triangles) == 0:
        return sums, 0
    table = sample_table(scene, triangles, grid.voxel / samples_per_voxel)
    if env is not None:  # summed on the device: no sample leaves it
        from .device import surface_sums as device_sums

        return device_sums(env, table, grid, scene.textures, alpha_threshold), int(table.offset[-1])
    be = backend(env)
    lo, total = 0, 0
    while lo < len(table.m):
        # as many triangles as keep the chunk under the sample budget (at least one)
        hi = int(np.searchsorted(table.offset, table.offset[lo] + MAX_SAMPLES_PER_CHUNK, side="right")) - 1
        hi = min(max(hi, lo + 1), len(table.m))
        chunk = table.take(lo, hi)
        sums.add(be.surface_samples(chunk, grid, scene.textures, alpha_threshold))
        total += int(chunk.offset[-1])
        lo = hi
    return sums, total


def _ragged(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For counts c_i: (owner i of each of the sum(c) items, its index 0..c_i-1)."""
    owner = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    return owner, np.arange(int(counts.sum())) - starts[owner]


def solid_occupancy(tri_pos: np.ndarray, grid: Grid3, sub: int = 2) -> np.ndarray:
    """(nz, ny, nx) share of each voxel inside the closed mesh tri_pos (m, 3, 3),
    from sub x sub columns along z per voxel (module docstring, step 3)."""
    nx, ny, nz = grid.shape
    out = np.zeros(grid.count)
    if len(tri_pos) == 0:
        return out.reshape(nz, ny, nx)
    o, h = grid.origin, grid.voxel
    hs = h / sub
    # column centres sit a little off the regular grid: a column through a mesh vertex or edge would count twice
    jitter = 0.5 + 1e-4 * np.sqrt(2.0)
    p = tri_pos.astype(np.float64)
    X, Y = (p[:, :, 0] - o[0]) / hs - jitter, (p[:, :, 1] - o[1]) / hs - jitter
    ix0 = np.maximum(np.ceil(X.min(1)), 0).astype(np.int64)
    ix1 = np.minimum(np.floor(X.max(1)), nx * sub - 1).astype(np.int64)
    iy0 = np.maximum(np.ceil(Y.min(1)), 0).astype(np.int64)
    iy1 = np.minimum(np.floor(Y.max(1)), ny * sub - 1).astype(np.int64)
    wx, wy = np.maximum(ix1 - ix0 + 1, 0), np.maximum(iy1 - iy0 + 1, 0)
    tri, local = _ragged(wx * wy)
    cx, cy = ix0[tri] + local % wx[tri], iy0[tri] + local // wx[tri]
    px, py = (cx + jitter) * hs, (cy + jitter) * hs  # relative to the origin
    q = p[tri] - o
    x0, y0, z0 = q[:, 0, 0], q[:, 0, 1], q[:, 0, 2]
    x1, y1, z1 = q[:, 1, 0], q[:, 1, 1], q[:, 1, 2]
    x2, y2, z2 = q[:, 2, 0], q[:, 2, 1], q[:, 2, 2]
    d = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
    ok = d != 0
    ds = np.where(ok, d, 1.0)
    l0 = ((y1 - y2) * (px - x2) + (x2 - x1) * (py - y2)) / ds
    l1 = ((y2 - y0) * (px - x2) + (x0 - x2) * (py - y2)) / ds
    l2 = 1.0 - l0 - l1
    inside = ok & (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
    z = (l0 * z0 + l1 * z1 + l2 * z2)[inside]
    # a +z ray enters where the face looks down (outward normal z < 0): winding +1
    normal_z = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
    step = -np.sign(normal_z[inside])
    col = (cy * (nx * sub) + cx)[inside]
    order = np.lexsort((z, col))
    z, step, col = z[order], step[order], col[order]
    winding = np.cumsum(step)
    first = np.r_[True, col[1:] != col[:-1]]
    base = np.maximum.accumulate(np.where(first, np.arange(len(col)), 0))
    winding = winding - (np.cumsum(step) - step)[base]  # the winding within each column
    seg = (col[:-1] == col[1:]) & (winding[:-1] != 0)
    a = np.clip(z[:-1][seg] / h, 0, nz)
    b = np.clip(z[1:][seg] / h, 0, nz)
    c = col[:-1][seg]
    k0 = np.floor(a).astype(np.int64)
    k1 = np.minimum(np.ceil(b).astype(np.int64), nz)
    n = np.maximum(k1 - k0, 0)
    owner, j = _ragged(n)
    k = k0[owner] + j
    overlap = np.minimum(b[owner], k + 1) - np.maximum(a[owner], k)
    vx, vy = (c[owner] % (nx * sub)) // sub, (c[owner] // (nx * sub)) // sub
    out += np.bincount((k * ny + vy) * nx + vx, np.maximum(overlap, 0.0), grid.count)
    return np.minimum(out / (sub * sub), 1.0).reshape(nz, ny, nx)


def voxelize(env, scene: Scene, parts: np.ndarray, voxels: int, mip_levels: int, samples_per_voxel: float = 3.0,
             alpha_threshold: float = 0.5, solid_sub: int = 2) -> Voxelized:
    """The finest level of a plant's volume (module docstring), sampled on
    the OpenCL device `env` or with the numpy reference (env None)."""
    grid = plant_grid(scene, voxels, mip_levels)
    wood = np.nonzero(parts == "Wood")[0]
    foliage = np.nonzero(parts != "Wood")[0]
    fol, n_fol = surface_sums(env, scene, foliage, grid, samples_per_voxel, alpha_threshold)
    bark, n_bark = surface_sums(env, scene, wood, grid, samples_per_voxel, alpha_threshold)
    nx, ny, nz = grid.shape
    h = grid.voxel
    vol = h ** 3
    occ = solid_occupancy(scene.positions[scene.triangles[wood]], grid, solid_sub).ravel()
    area = fol.area + bark.area
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = np.where(area[:, None] > 0, (fol.normal + bark.normal) / area[:, None], 0.0)
        mean_bark = bark.rgb.sum(0) / bark.area.sum() if bark.area.sum() > 0 else np.zeros(3)
        bark_colour = np.where(bark.area[:, None] > 0, bark.rgb / bark.area[:, None], mean_bark[None, :])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.where(length > 1.0, normal / np.maximum(length, 1e-30), normal)
    wood_sigma = occ * SOLID_OPTICAL_DEPTH / h
    density = LEAF_PROJECTION * fol.area / vol + wood_sigma
    albedo = LEAF_PROJECTION * fol.rgb / vol + wood_sigma[:, None] * bark_colour
    shape = (nz, ny, nx)
    level = VolumeLevel(density.reshape(shape).astype(np.float32), albedo.reshape(*shape, 3).astype(np.float32),
                        normal.reshape(*shape, 3).astype(np.float32), (area / vol).reshape(shape).astype(np.float32),
                        grid.origin.copy(), h)
    return Voxelized(level, n_fol + n_bark, float(occ.sum() * vol))
