"""Host-side OpenCL helpers every stage's device module shares: kernel
objects retrieved once per program, buffers from arrays and back.

(Device choice and program builds are pipeline.opencl's.)"""
from __future__ import annotations

import numpy as np

from .opencl import CL, global_size

_KERNELS: dict = {}  # (id(program), name) -> (program, kernel); the program is kept so its id stays unique


def kernel(program, name: str):
    """The kernel `name` of `program`, one object per process: retrieving a
    kernel again builds a new object (and pyopencl warns)."""
    import pyopencl as cl

    key = (id(program), name)
    if key not in _KERNELS:
        _KERNELS[key] = (program, cl.Kernel(program, name))
    return _KERNELS[key][1]


class Buffers:
    """Device buffers from arrays, and back, on the OpenCL device `env`."""

    def __init__(self, env: CL):
        import pyopencl as cl

        self.cl, self.env = cl, env

    def arr(self, a, write: bool = False, in_place: bool = False):
        """A buffer holding `a` (an empty array gets one element: OpenCL has
        no empty buffers). in_place (read-only): the device uses the array's
        memory (no copy on a CPU device); nobody may write it meanwhile."""
        mf = self.cl.mem_flags
        a = np.ascontiguousarray(a)
        if not a.nbytes:
            a = np.zeros(1, a.dtype)
        if in_place and not write:
            return self.cl.Buffer(self.env.ctx, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=a)
        flags = (mf.READ_WRITE if write else mf.READ_ONLY) | mf.COPY_HOST_PTR
        return self.cl.Buffer(self.env.ctx, flags, hostbuf=a)

    def empty(self, nbytes):
        return self.cl.Buffer(self.env.ctx, self.cl.mem_flags.READ_WRITE, max(int(nbytes), 4))

    def get(self, buf, shape, dtype):
        out = np.empty(shape, dtype)
        self.cl.enqueue_copy(self.env.queue, out, buf)
        return out

    def run(self, kernel, gsize, local, *args):
        kernel(self.env.queue, global_size(tuple(gsize), local), local, *args)
