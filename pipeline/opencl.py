"""One OpenCL context and queue per process, a program cache, and
`CachedKernel` for kernels launched many times in a time loop.

The device is PoCL on the CPU by default (installed from PyPI with pyopencl);
`WORLDBAKE_CL_DEVICE` picks another: an index "P:D" (platform:device) or a
case-insensitive substring of "platform name / device name".
"""
from __future__ import annotations

import functools
import hashlib
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class OpenCLError(RuntimeError):
    pass


@dataclass(frozen=True)
class CL:
    ctx: "object"  # pyopencl.Context
    queue: "object"  # pyopencl.CommandQueue
    device: "object"  # pyopencl.Device

    @property
    def fingerprint(self) -> str:
        """Identifies everything about the device that may change numbers."""
        d = self.device
        return f"{d.platform.name} {d.platform.version} / {d.name} / driver {d.driver_version}"


def _pick_device():
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error as e:  # no ICD at all
        raise OpenCLError(f"no OpenCL platform found ({e}); install pyopencl with the PoCL wheel: pip install 'pyopencl[pocl]'") from e
    devices = [(pi, di, p, d) for pi, p in enumerate(platforms) for di, d in enumerate(p.get_devices())]
    if not devices:
        raise OpenCLError("OpenCL platforms found but no device")
    want = os.environ.get("WORLDBAKE_CL_DEVICE", "").strip()
    if want:
        if ":" in want and all(part.isdigit() for part in want.split(":", 1)):
            pi, di = (int(x) for x in want.split(":", 1))
            for cand in devices:
                if cand[0] == pi and cand[1] == di:
                    return cand[3]
        else:
            for cand in devices:
                if want.lower() in f"{cand[2].name} / {cand[3].name}".lower():
                    return cand[3]
        listing = "; ".join(f"{pi}:{di} {p.name} / {d.name}" for pi, di, p, d in devices)
        raise OpenCLError(f"WORLDBAKE_CL_DEVICE={want!r} matches no device; available: {listing}")
    for cand in devices:  # the default: PoCL, whose numbers we test against
        if "portable computing language" in cand[2].name.lower():
            return cand[3]
    return devices[0][3]


@functools.lru_cache(maxsize=1)
def get_cl() -> CL:
    """The process-wide context and in-order queue (each Dask worker builds its own)."""
    import pyopencl as cl

    device = _pick_device()
    ctx = cl.Context([device])
    queue = cl.CommandQueue(ctx, device)
    return CL(ctx, queue, device)


AVX512_FLAGS = ("avx512f", "avx512vl", "avx512dq")


def _host_cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:  # not Linux: no flags known, so no AVX-512 path
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def x86_avx512(device) -> bool:
    """Whether kernels may compile parts of themselves for AVX-512 with a clang
    target attribute: the device is PoCL on this host's CPU (it compiles with
    clang for the host) and the CPU has AVX-512 F, VL and DQ. PoCL 3.0's
    LLVM 14 does not know Zen 4 and targets it as Zen 3 (AVX2 only).
    WORLDBAKE_CL_AVX512=0 turns the path off."""
    import pyopencl as cl

    if os.environ.get("WORLDBAKE_CL_AVX512", "1").strip() == "0":
        return False
    if "portable computing language" not in device.platform.name.lower():
        return False
    if not device.type & cl.device_type.CPU:
        return False
    return all(f in _host_cpu_flags() for f in AVX512_FLAGS)


@functools.lru_cache(maxsize=64)
def _build(source_hash: str, source: str, options: tuple[str, ...]):
    import pyopencl as cl

    env = get_cl()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # PoCL prints build logs as warnings even on success
        try:
            return cl.Program(env.ctx, source).build(options=list(options))
        except cl.RuntimeError as e:
            raise OpenCLError(f"OpenCL build failed:\n{e}") from e


def load_program(path: Path | str, options: tuple[str, ...] = ()) -> "object":
    """Build the kernels in a .cl file once per process (and per options).

    `-cl-fp32-correctly-rounded-divide-sqrt` keeps divisions and square roots
    exact so kernels agree with their numpy references; fast-math options are
    never used because they change numbers between devices."""
    from .sources import CL_INCLUDE_DIR, cl_include_hash

    source = Path(path).read_text()
    # The shared headers' hash is an option too: an edited header must not
    # be served from this process's cache or PoCL's (keyed on source text
    # and options).
    opts = ("-cl-fp32-correctly-rounded-divide-sqrt", f"-I{CL_INCLUDE_DIR}",
            f"-DWORLDBAKE_INCLUDE_HASH=0x{cl_include_hash()[:12]}") + tuple(options)
    return _build(hashlib.sha256(source.encode()).hexdigest(), source, opts)


def global_size(shape: tuple[int, ...], local: tuple[int, ...] | None) -> tuple[int, ...]:
    """Round a global size up to a multiple of the local size; kernels guard
    against the padding with explicit bounds checks."""
    if local is None:
        return tuple(shape)
    return tuple(-(-s // l) * l for s, l in zip(shape, local))


def to_device(array: np.ndarray):
    import pyopencl.array as cla

    return cla.to_device(get_cl().queue, np.ascontiguousarray(array))


class CachedKernel:
    """A kernel launched many times with mostly the same arguments (a time loop).

    Each launch sets only the arguments that changed since the last launch with
    the same buffers: PoCL spends about 4 us of host time per clSetKernelArg,
    which over the 50-odd arguments of an erosion step is CPU taken from the
    kernels themselves on a 2-core machine. One kernel object is kept per set
    of buffer arguments (a double-buffered loop alternates between two), the
    most recent `max_sets` of them."""

    def __init__(self, program, name: str, max_sets: int = 8):
        self.program, self.name, self.max_sets = program, name, max_sets
        self._sets: dict[tuple, tuple[object, list]] = {}  # buffer ids -> (kernel, last arguments)

    def __call__(self, queue, global_size, local_size, *args):
        import pyopencl as cl

        key = tuple(id(a) for a in args if isinstance(a, cl.MemoryObject))
        entry = self._sets.pop(key, None)  # re-inserted below: the dict's order is recency
        if entry is None:
            entry = (cl.Kernel(self.program, self.name), [None] * len(args))
            if len(self._sets) >= self.max_sets:
                del self._sets[next(iter(self._sets))]
        self._sets[key] = entry
        kernel, last = entry
        for i, a in enumerate(args):
            b = last[i]
            # `last` keeps the buffers alive, so ids in the key are never reused while cached
            if b is None or not (a is b or (type(a) is type(b) and not isinstance(a, cl.MemoryObject) and a == b)):
                kernel.set_arg(i, a)
                last[i] = a
        return cl.enqueue_nd_range_kernel(queue, kernel, global_size, local_size)
