"""Run the vertex kernels of kernels.cl, or their numpy references.

Each function takes the OpenCL device `env` (pipeline.opencl.CL; None: the
numpy reference) and packed float32 records (layouts in reference.py) and
returns a (n_vertices, VERT) float32 array."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import reference as ref

KERNELS = Path(__file__).with_name("kernels.cl")
LOCAL = 64


def _kernel(env, name: str):
    from pipeline.clhost import kernel
    from pipeline.opencl import load_program

    return kernel(load_program(env, KERNELS), name)


def _run(env, kernel_name: str, n_items: int, out_rows: int, scalars: list, arrays: list[np.ndarray]) -> np.ndarray:
    import pyopencl as cl

    from pipeline.opencl import global_size

    out = np.zeros((out_rows, ref.VERT), np.float32)
    if n_items == 0 or out_rows == 0:
        return out
    mf = cl.mem_flags
    bufs = [cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a)) for a in arrays]
    dst = cl.Buffer(env.ctx, mf.WRITE_ONLY, out.nbytes)
    kernel = _kernel(env, kernel_name)
    kernel(env.queue, global_size((n_items,), (LOCAL,)), (LOCAL,), *scalars, *bufs, dst)
    cl.enqueue_copy(env.queue, out, dst)
    env.queue.finish()
    return out


def tube_rings(env, ring: np.ndarray, sides: np.ndarray) -> np.ndarray:
    sides = np.ascontiguousarray(sides, np.int32)
    offset = np.zeros(len(sides), np.int32)
    if len(sides):
        offset[1:] = np.cumsum(sides + 1)[:-1]
    if env is None:
        return ref.tube_rings(ring, sides, offset)
    n = int((sides + 1).sum())
    return _run(env, "tube_rings", len(ring), n, [np.int32(len(ring))],
                [np.asarray(ring, np.float32).reshape(-1), sides, offset])


def leaf_instances(env, leaf: np.ndarray, tmpl: np.ndarray) -> np.ndarray:
    if env is None:
        return ref.leaf_instances(leaf, tmpl)
    nl, nt = len(leaf), len(tmpl)
    return _run(env, "leaf_instances", nl * nt, nl * nt, [np.int32(nl), np.int32(nt)],
                [np.asarray(leaf, np.float32).reshape(-1), np.asarray(tmpl, np.float32).reshape(-1)])


def grass_blades(env, blade: np.ndarray, rows: np.ndarray, taper: float) -> np.ndarray:
    rows = np.ascontiguousarray(rows, np.float32)
    if env is None:
        return ref.grass_blades(blade, rows, taper)
    nb = len(blade)
    n = rows.shape[1] - 1
    return _run(env, "grass_blades", nb * (n + 1), nb * (2 * n + 1),
                [np.int32(nb), np.int32(n), np.float32(taper)],
                [np.asarray(blade, np.float32).reshape(-1), rows.reshape(-1)])
