"""The sector splat on the OpenCL device (kernels.cl `splat`; its numpy
reference is reference.py).

Every occupied voxel of a species' source level is carried through each
instance's transform (position, rotation, uniform scale S) and, as a cube
of edge S x its voxel (at most one sector voxel) centred there, shared
among the sector voxels it overlaps (1 or 2 per axis; the shares sum to 1,
so nothing is lost). What it adds: extinction x volume, premultiplied
albedo and surface scaled by S^2 (the instance's projected area), and the
surface x its normal turned by the rotation. Sums are 64-bit fixed point
(FIXED units per 1/m; integer additions in any order give the same sums,
hence no dependence on work-group size); a deposit rounds to 2^-40, about
1e-12, and a voxel holds up to 8e6.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from worldlib.volumes.dense import VolumeLevel

FIXED = float(2 ** 40)
CHANNELS = 8  # extinction, albedo (3), surface, surface x normal (3)
KERNELS = Path(__file__).with_name("kernels.cl")


def source_voxels(source: VolumeLevel) -> tuple[np.ndarray, np.ndarray]:
    """(v, 3) centres in the plant's frame and (v, 8) channels (density,
    albedo, surface, normal) of the source's occupied voxels."""
    occupied = np.flatnonzero(source.density.ravel() > 0)
    sz, sy, sx = np.unravel_index(occupied, source.density.shape)
    centres = source.origin + (np.stack([sx, sy, sz], 1) + 0.5) * source.voxel_m
    held = np.concatenate([source.density.reshape(-1, 1), source.albedo.reshape(-1, 3),
                           source.surface.reshape(-1, 1), source.normal.reshape(-1, 3)], axis=1)[occupied]
    return np.ascontiguousarray(centres, np.float64), np.ascontiguousarray(held, np.float64)


class DeviceSplat:
    """One sector's fixed-point sums on the OpenCL device `env` (a
    pipeline.opencl.CL): the accumulator is a host array the device writes
    in place (a CPU runtime shares it)."""

    def __init__(self, env, shape_xyz, origin, voxel: float, local: int | None = 64):
        import pyopencl as cl

        from pipeline.opencl import load_program

        program = load_program(env, KERNELS)
        self.env = env
        self.shape_xyz, self.origin, self.voxel, self.local = tuple(shape_xyz), np.asarray(origin, np.float64), voxel, local
        nx, ny, nz = self.shape_xyz
        self.acc = np.zeros((CHANNELS, nx * ny * nz), np.int64)
        self.dev = cl.Buffer(self.env.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=self.acc)
        self.kernel = cl.Kernel(program, "splat")

    def add(self, source: VolumeLevel, pos, rot, scale) -> None:
        import pyopencl as cl

        from pipeline.opencl import global_size

        centres, held = source_voxels(source)
        n, v = len(pos), len(centres)
        if n == 0 or v == 0:
            return
        mf = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        bufs = [cl.Buffer(self.env.ctx, mf, hostbuf=np.ascontiguousarray(a, np.float64))
                for a in (pos, np.asarray(rot).reshape(-1, 9), scale, centres, held)]
        nx, ny, nz = self.shape_xyz
        loc = None if self.local is None else (self.local,)
        self.kernel(self.env.queue, global_size((n * v,), loc), loc, np.int32(n), np.int32(v), *bufs,
                    *map(np.float64, self.origin), np.float64(self.voxel), np.float64(source.voxel_m),
                    np.float64((source.voxel_m / self.voxel) ** 3), np.int32(nx), np.int32(ny), np.int32(nz),
                    np.float64(FIXED), self.dev)

    def result(self) -> np.ndarray:
        """The (8, voxels) int64 sums, once the device is done."""
        import pyopencl as cl

        cl.enqueue_map_buffer(self.env.queue, self.dev, cl.map_flags.READ, 0, self.acc.shape, self.acc.dtype)[0].base.release()
        self.env.queue.finish()
        return self.acc
