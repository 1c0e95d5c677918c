"""The volume kernels on the OpenCL device `env` (a pipeline.opencl.CL, each
function's first argument), with the reference's signatures after it."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .samples import Grid3, Samples, SampleTable

KERNELS = Path(__file__).with_name("kernels.cl")


def _program(env):
    from pipeline.opencl import load_program

    return load_program(env, KERNELS)


def _buf(env, a: np.ndarray):
    import pyopencl as cl

    a = np.ascontiguousarray(a)
    if a.size == 0:
        a = np.zeros(4, a.dtype)
    return cl.Buffer(env.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)


def surface_samples(env, table: SampleTable, grid: Grid3, textures: np.ndarray, alpha_threshold: float,
                    local: int | None = 64) -> Samples:
    import pyopencl as cl

    from pipeline.opencl import global_size

    n = int(table.offset[-1]) if len(table.offset) else 0
    out = Samples(np.full(n, -1, np.int32), np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3)))
    if n == 0:
        return out
    _, th, tw, _ = textures.shape
    dev = [cl.Buffer(env.ctx, cl.mem_flags.WRITE_ONLY, a.nbytes) for a in (out.voxel, out.weight, out.rgb, out.normal)]
    k = cl.Kernel(_program(env), "surface_samples")
    nt = len(table.m)
    loc = None if local is None else (local,)
    k(env.queue, global_size((nt,), loc), loc, np.int32(nt), *(_buf(env, a) for a in (table.pos, table.nrm, table.uv,
      table.tint, table.tex, textures.astype(np.float32))), np.int32(tw), np.int32(th),
      np.float32(alpha_threshold), _buf(env, table.m), _buf(env, table.offset[:-1]), *map(np.float64, grid.origin),
      np.float64(grid.voxel), *map(np.int32, grid.shape), *dev)
    for a, b in zip((out.voxel, out.weight, out.rgb, out.normal), dev):
        cl.enqueue_copy(env.queue, a, b)
    env.queue.finish()
    return out


FIXED = float(2 ** 40)  # surface_sums' fixed point: 1e-12 m^2 a unit, up to 8e6 m^2 a voxel


def surface_sums(env, table: SampleTable, grid: Grid3, textures: np.ndarray, alpha_threshold: float,
                 local: int | None = 64):
    """The surface samples of `table` summed per voxel on the device
    (kernels.cl surface_sums): a samples.SurfaceSums."""
    import pyopencl as cl

    from pipeline.opencl import global_size

    from .samples import SurfaceSums

    nt = len(table.m)
    acc = np.zeros((7, grid.count), np.int64)
    if nt:
        _, th, tw, _ = textures.shape
        dev = cl.Buffer(env.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=acc)
        k = cl.Kernel(_program(env), "surface_sums")
        loc = None if local is None else (local,)
        k(env.queue, global_size((nt,), loc), loc, np.int32(nt), *(_buf(env, a) for a in (table.pos, table.nrm,
          table.uv, table.tint, table.tex, np.asarray(textures, np.float32))), np.int32(tw), np.int32(th),
          np.float32(alpha_threshold), _buf(env, table.m), *map(np.float64, grid.origin), np.float64(grid.voxel),
          *map(np.int32, grid.shape), np.float64(FIXED), dev)
        mapped, _ = cl.enqueue_map_buffer(env.queue, dev, cl.map_flags.READ, 0, acc.shape, acc.dtype)
        env.queue.finish()
        sums = mapped / FIXED  # (the host array itself where the runtime shares it)
        mapped.base.release()
    else:
        sums = acc / FIXED
    del acc
    return SurfaceSums(sums[0], sums[1:4].T, sums[4:7].T)  # views of the one float64 array


def composite(env, camera_record: np.ndarray, width: int, height: int, grid: np.ndarray, origin, voxel: float,
              step: float, local: tuple[int, int] | None = (8, 8)) -> tuple[np.ndarray, np.ndarray]:
    return composite_views(env, [camera_record], width, height, grid, origin, voxel, step, local)[0]


def composite_views(env, camera_records: list[np.ndarray], width: int, height: int, grid: np.ndarray, origin,
                    voxel: float, step: float, local: tuple[int, int] | None = (8, 8)) -> list[tuple[np.ndarray, np.ndarray]]:
    """composite from each camera, the grid sent to the device once."""
    import pyopencl as cl

    from pipeline.opencl import global_size
    from worldlib.volumes.dense import LEAF_PROJECTION

    nz, ny, nx = grid.shape[:3]
    dgrid = _buf(env, np.asarray(grid, np.float32))
    k = cl.Kernel(_program(env), "composite")
    out = []
    for record in camera_records:
        alpha, rgb = np.zeros((height, width), np.float32), np.zeros((height, width, 3), np.float32)
        da, dr = (cl.Buffer(env.ctx, cl.mem_flags.WRITE_ONLY, a.nbytes) for a in (alpha, rgb))
        k(env.queue, global_size((width, height), local), local, np.int32(width), np.int32(height),
          _buf(env, np.asarray(record, np.float32)), dgrid, np.float64(LEAF_PROJECTION), np.int32(nx), np.int32(ny),
          np.int32(nz), *map(np.float64, origin), np.float64(voxel), np.float64(step), da, dr)
        cl.enqueue_copy(env.queue, alpha, da)
        cl.enqueue_copy(env.queue, rgb, dr)
        out.append((alpha, rgb))
    env.queue.finish()
    return out
