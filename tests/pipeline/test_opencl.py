"""pipeline.opencl: CachedKernel must launch exactly what a plain kernel call
launches, whichever arguments change between launches; the AVX-512 path is
offered only where the device and the CPU allow it."""
from __future__ import annotations

import numpy as np

from pipeline import opencl
from pipeline.opencl import CachedKernel, get_cl, x86_avx512

SOURCE = """
__kernel void axpb(__global const float *x, __global float *y, const float a, const float b, const int n)
{
    int i = get_global_id(0);
    if (i < n) y[i] = a * x[i] + b;
}
"""


def test_cached_kernel_sets_every_changed_argument():
    import pyopencl as cl

    env = get_cl()
    prg = cl.Program(env.ctx, SOURCE).build()
    mf = cl.mem_flags
    n = 37
    xs = [np.arange(n, dtype=np.float32) * s for s in (1.0, -2.0)]
    bx = [cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x) for x in xs]
    by = [cl.Buffer(env.ctx, mf.READ_WRITE, 4 * n) for _ in range(2)]
    k = CachedKernel(prg, "axpb", max_sets=2)
    # buffers alternate (double buffering), scalars change some of the time; three
    # buffer sets with room for two also exercise the eviction
    launches = [(0, 0, 2.0, 1.0), (1, 1, 2.0, 1.0), (0, 0, 3.0, 1.0), (0, 1, 3.0, -5.0),
                (1, 0, 3.0, -5.0), (0, 0, 3.0, -5.0), (1, 1, 0.5, 0.25)]
    for ix, iy, a, b in launches:
        k(env.queue, (64,), None, bx[ix], by[iy], np.float32(a), np.float32(b), np.int32(n))
        out = np.empty(n, np.float32)
        cl.enqueue_copy(env.queue, out, by[iy])
        np.testing.assert_array_equal(out, np.float32(a) * xs[ix] + np.float32(b), err_msg=str((ix, iy, a, b)))
    assert len(k._sets) <= 2


def test_avx512_path_needs_pocl_on_a_cpu_with_avx512_and_can_be_turned_off(monkeypatch):
    import pyopencl as cl

    device = get_cl().device
    pocl_cpu = "portable computing language" in device.platform.name.lower() and bool(
        device.type & cl.device_type.CPU)
    monkeypatch.setattr(opencl, "_host_cpu_flags", lambda: {"avx2", "avx512f", "avx512vl", "avx512dq"})
    assert x86_avx512(device) == pocl_cpu
    monkeypatch.setattr(opencl, "_host_cpu_flags", lambda: {"avx2", "avx512f"})  # no VL, DQ
    assert not x86_avx512(device)
    monkeypatch.setattr(opencl, "_host_cpu_flags", lambda: {"avx2", "avx512f", "avx512vl", "avx512dq"})
    monkeypatch.setenv("WORLDBAKE_CL_AVX512", "0")
    assert not x86_avx512(device)
