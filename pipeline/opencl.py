"""One OpenCL context and queue per process, chosen by probing the installed
runtimes; a program cache; and `CachedKernel` for kernels launched many times
in a time loop.

The device is handed around, not looked up: the engine chooses it (get_cl)
and gives it to each stage that declares `uses_opencl` as `RunContext.cl`, a
`CL`; stages pass it down, and every function that runs a kernel takes it as
its first argument `env` (load_program refuses to build without one).

Which device a bake uses, in this order (the first candidate whose probe
passes wins; each candidate that fails is skipped with one line saying why):

1. `WORLDBAKE_CL_DEVICE`, when set: an index "P:D" (platform:device) or a
   case-insensitive substring of "platform name / device name"; every device
   it matches is a candidate, in platform order.
2. GPUs with double precision, in platform order (a bake's budgets and
   diagnostics are float64).
3. CPU runtimes: PoCL, then Intel's CPU runtime (`intel-opencl-rt`): where
   both work PoCL bakes faster (`python -m bench.devices` compares them side
   by side). PoCL 3.0's LLVM 14 cannot compile for the newest CPUs ("unknown
   target CPU 'generic'"); there its probe fails and Intel's runtime is used.
4. Any other device.

The probe builds and runs a tiny kernel with the options every kernel is built
with (float64, correctly rounded division and square root) and checks its
results exactly: a runtime that lists a device but cannot compile for it, or
computes wrong numbers, is never used.

Runtimes installed from PyPI into the project's environment are registered by
the project itself (`register_bundled_runtimes`), before the first platform
query of the process: Intel's wheel ships an `.icd` file naming a placeholder
path, so ours names the library that was actually installed.
"""
from __future__ import annotations

import atexit
import functools
import hashlib
import os
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DeviceError


class OpenCLError(DeviceError):
    """A kernel failed to build or the device choice failed (exit status 3)."""


@dataclass(frozen=True)
class CL:
    """An OpenCL device handle: the context, its in-order queue and the
    device. Code that runs kernels takes one as its first argument (`env`),
    as pyopencl's own functions take a context or queue; the engine chooses
    it (get_cl) and hands it to a stage as `RunContext.cl`.

    Pickled (a job sent to a worker process), it names its device; the
    receiving process opens a context of its own on that same device."""

    ctx: "object"  # pyopencl.Context
    queue: "object"  # pyopencl.CommandQueue
    device: "object"  # pyopencl.Device

    @property
    def fingerprint(self) -> str:
        """Identifies everything about the device that may change numbers."""
        return device_fingerprint(self.device)

    def __reduce__(self):
        import pyopencl as cl

        for pi, p in enumerate(cl.get_platforms()):
            try:
                devices = p.get_devices()
            except cl.Error:
                continue
            for di, d in enumerate(devices):
                if d == self.device:
                    return (_reopen, (f"{pi}:{di}", self.fingerprint))
        raise OpenCLError(f"cannot name the device {self.fingerprint} for another process")


def device_fingerprint(d) -> str:
    return f"{d.platform.name} {d.platform.version} / {d.name} / driver {d.driver_version}"


# --- runtimes from PyPI -------------------------------------------------------

# library file name -> the .icd file name it is registered under
BUNDLED_RUNTIMES = {"libintelocl.so": "worldbake-intel-cpu.icd"}
SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")


def _bundled_libraries() -> list[Path]:
    """Runtime libraries that pip installed into this environment (wheels such
    as intel-opencl-rt put them in <prefix>/lib)."""
    found = []
    for name in BUNDLED_RUNTIMES:
        for lib_dir in dict.fromkeys((Path(sys.prefix) / "lib", Path(sys.base_prefix) / "lib")):
            if (lib_dir / name).is_file():
                found.append((lib_dir / name).resolve())
                break
    return found


def _vendor_folder() -> Path:
    """Where our .icd files go: inside the environment when it is writable,
    else a folder of this user's in the temporary directory."""
    inside = Path(sys.prefix) / "etc" / "OpenCL" / "worldbake-vendors"
    try:
        inside.mkdir(parents=True, exist_ok=True)
        if os.access(inside, os.W_OK):
            return inside
    except OSError:
        pass
    import tempfile

    outside = Path(tempfile.gettempdir()) / f"worldbake-vendors-{os.getuid()}"
    outside.mkdir(parents=True, exist_ok=True)
    return outside


def _write_if_changed(path: Path, text: str) -> None:
    try:
        if path.read_text() == text:
            return
    except OSError:
        pass
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)  # atomic: a concurrent process reads the old or the new file, never half


def register_bundled_runtimes() -> Path | None:
    """Point the ICD loader at the runtimes installed in this environment,
    keeping every vendor the system or the user registered. Must run before
    the first platform query of the process (the loader reads its vendor list
    once); `get_cl()` and `probe_all()` call it. Returns the vendor folder, or
    None when this environment holds no runtime library of its own."""
    libraries = _bundled_libraries()
    if not libraries:
        return None
    if os.environ.get("WORLDBAKE_OCL_VENDORS_SET") == "1":  # already done in this process or a parent
        return Path(os.environ["OCL_ICD_VENDORS"])
    folder = _vendor_folder()
    wanted: dict[str, str] = {}
    # the loader reads one folder: carry over what it would otherwise have read
    previous = os.environ.get("OCL_ICD_VENDORS")
    sources = [Path(previous)] if previous else [SYSTEM_VENDORS]
    for src in sources:
        if src.is_dir():
            for icd in sorted(src.glob("*.icd")):
                try:
                    wanted[f"system-{icd.name}"] = icd.read_text()
                except OSError:
                    continue
        elif src.is_file():  # ocl-icd also accepts a single library path
            wanted["system-user.icd"] = f"{src}\n"
    for lib in libraries:
        wanted[BUNDLED_RUNTIMES[lib.name]] = f"{lib}\n"
    for name, text in wanted.items():
        _write_if_changed(folder / name, text)
    for stale in folder.glob("*.icd"):
        if stale.name not in wanted:
            try:
                stale.unlink()
            except OSError:
                pass
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    os.environ["WORLDBAKE_OCL_VENDORS_SET"] = "1"
    return folder


# --- probing ------------------------------------------------------------------

PROBE_SOURCE = r"""
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
__kernel void worldbake_probe(__global const float *x, __global float *q, __global double *s, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float v = sqrt(x[i]) / 3.0f;
    q[i] = v;
    s[i] = (double)v * (double)x[i] + 1.0;
}
"""
BUILD_OPTIONS = ("-cl-fp32-correctly-rounded-divide-sqrt",)


@dataclass
class Candidate:
    """One device as the choice sees it."""
    index: str  # "P:D"
    platform: str
    name: str
    kind: str  # "GPU", "CPU", "other"
    fingerprint: str
    device: object = field(repr=False, default=None)
    reason: str = ""  # why it stands where it does in the order
    ok: bool | None = None  # None: not probed
    error: str = ""
    probe_ms: float = 0.0

    @property
    def label(self) -> str:
        return f"{self.index} {self.platform} / {self.name}"

    def as_dict(self) -> dict:
        return {"index": self.index, "platform": self.platform, "device": self.name, "type": self.kind,
                "fingerprint": self.fingerprint, "order_reason": self.reason,
                "probe": None if self.ok is None else ("ok" if self.ok else "failed"), "error": self.error,
                "probe_ms": round(self.probe_ms, 1)}


def _kind(device) -> str:
    import pyopencl as cl

    if device.type & cl.device_type.GPU:
        return "GPU"
    if device.type & cl.device_type.CPU:
        return "CPU"
    return "other"


def list_devices() -> list[Candidate]:
    """Every device of every platform the ICD loader finds, in platform order."""
    register_bundled_runtimes()
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error as e:  # no ICD at all
        raise OpenCLError(f"no OpenCL platform found ({e}); reinstall the project (make setup) so that "
                          "its CPU runtimes (pocl, intel-opencl-rt) are installed") from e
    out = []
    for pi, p in enumerate(platforms):
        try:
            devices = p.get_devices()
        except cl.Error:  # a platform with no usable device
            continue
        for di, d in enumerate(devices):
            out.append(Candidate(f"{pi}:{di}", p.name.strip(), d.name.strip(), _kind(d), device_fingerprint(d), d))
    return out


CPU_RUNTIME_ORDER = ("portable computing language", "intel(r) opencl")  # the faster first (bench/devices.py)


def order_candidates(devices: list[Candidate], want: str = "") -> list[Candidate]:
    """The documented order (module docstring). With `want` set, only the
    devices it names; an OpenCLError when it names none."""
    if want:
        if ":" in want and all(part.strip().isdigit() for part in want.split(":", 1)):
            picked = [c for c in devices if c.index == ":".join(p.strip() for p in want.split(":", 1))]
        else:
            picked = [c for c in devices if want.lower() in f"{c.platform} / {c.name}".lower()]
        if not picked:
            listing = "; ".join(c.label for c in devices) or "none"
            raise OpenCLError(f"WORLDBAKE_CL_DEVICE={want!r} matches no device; available: {listing}")
        for c in picked:
            c.reason = "named by WORLDBAKE_CL_DEVICE"
        return picked

    def rank(c: Candidate) -> tuple[int, int]:
        if c.kind == "GPU":
            c.reason = "GPU"
            return (0, 0)
        if c.kind == "CPU":
            for i, runtime in enumerate(CPU_RUNTIME_ORDER):
                if c.platform.lower().startswith(runtime):
                    c.reason = f"CPU runtime, preference {i + 1} of {len(CPU_RUNTIME_ORDER)}"
                    return (1, i)
            c.reason = "other CPU runtime"
            return (1, len(CPU_RUNTIME_ORDER))
        c.reason = "other device"
        return (2, 0)

    return sorted(devices, key=rank)  # stable: platform order within a rank


def _probe(device) -> None:
    """Build and run the probe kernel on `device`; raise with the reason it is
    unusable. Replaced in tests to simulate runtimes that fail."""
    import pyopencl as cl

    if not device.double_fp_config:
        raise OpenCLError("no double precision (cl_khr_fp64), which the budgets need")
    ctx = cl.Context([device])
    queue = cl.CommandQueue(ctx, device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prg = cl.Program(ctx, PROBE_SOURCE).build(options=list(BUILD_OPTIONS))
    n = 61
    x = (np.arange(n, dtype=np.float32) * np.float32(0.7312) + np.float32(0.25)).astype(np.float32)
    mf = cl.mem_flags
    bx = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    bq = cl.Buffer(ctx, mf.WRITE_ONLY, 4 * n)
    bs = cl.Buffer(ctx, mf.WRITE_ONLY, 8 * n)
    prg.worldbake_probe(queue, (64,), None, bx, bq, bs, np.int32(n))
    q = np.empty(n, np.float32)
    s = np.empty(n, np.float64)
    cl.enqueue_copy(queue, q, bq)
    cl.enqueue_copy(queue, s, bs)
    queue.finish()
    want_q = np.sqrt(x) / np.float32(3.0)
    want_s = want_q.astype(np.float64) * x.astype(np.float64) + 1.0
    if not (np.array_equal(q, want_q) and np.array_equal(s, want_s)):
        bad = int(np.count_nonzero((q != want_q) | (s != want_s)))
        raise OpenCLError(f"the probe kernel computed {bad} of {n} values wrong (correctly rounded float32 "
                          "division and square root, float64 products)")


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    for line in text.splitlines():  # a build log: the line that names the cause
        if "error" in line.lower() and line.strip() != "":
            return line.strip()[:300]
    return (text.splitlines()[0] if text else type(error).__name__)[:300]


def probe_all(want: str | None = None, *, stop_at_first: bool = True, log=None) -> tuple[list[Candidate], Candidate | None]:
    """Probe candidates in the documented order. Returns every candidate (the
    ones after the winner unprobed when `stop_at_first`) and the winner."""
    import time

    if want is None:
        want = os.environ.get("WORLDBAKE_CL_DEVICE", "").strip()
    candidates = order_candidates(list_devices(), want)
    chosen = None
    for c in candidates:
        if chosen is not None and stop_at_first:
            break
        t0 = time.perf_counter()
        try:
            _probe(c.device)
            c.ok = True
        except Exception as e:  # any failure makes the candidate unusable; the reason is reported
            c.ok, c.error = False, _first_line(e)
            if log is not None:
                print(f"worldbake: OpenCL device {c.label} skipped: {c.error}", file=log, flush=True)
        c.probe_ms = 1e3 * (time.perf_counter() - t0)
        if c.ok and chosen is None:
            chosen = c
    return candidates, chosen


def no_device_message(candidates: list[Candidate], want: str) -> str:
    tried = "\n".join(f"  {c.label}: {c.error}" for c in candidates) or "  (no OpenCL device found)"
    named = f" named by WORLDBAKE_CL_DEVICE={want!r}" if want else ""
    return (f"no usable OpenCL device{named}; tried:\n{tried}\n"
            "Run `worldbake devices` to see every device and its probe; pick one with WORLDBAKE_CL_DEVICE=P:D "
            "or part of its name, or reinstall the environment (make setup) to get the CPU runtimes "
            "(pocl, intel-opencl-rt).")


@functools.lru_cache(maxsize=1)
def _default_cl() -> CL:
    import pyopencl as cl

    want = os.environ.get("WORLDBAKE_CL_DEVICE", "").strip()
    candidates, chosen = probe_all(want, log=sys.stderr)
    if chosen is None:
        raise OpenCLError(no_device_message(candidates, want))
    ctx = cl.Context([chosen.device])
    env = CL(ctx, cl.CommandQueue(ctx, chosen.device), chosen.device)
    _made.append(env)
    return env


_current: list[CL] = []  # a device pushed by use_device(), innermost last
_made: list[CL] = []  # every context this process made, released at exit


def release_all() -> None:
    """Drop every context, queue and program this process made, waiting for
    queued work first. Runs at exit (atexit), while the runtimes are still
    whole: Intel's CPU runtime aborts in its own teardown ("malloc_consolidate():
    unaligned fastbin chunk detected") when a Dask worker that also loaded
    pymeshlab exits with OpenCL objects still alive."""
    import gc

    for env in _made:
        try:
            env.queue.finish()
        except Exception:  # teardown: nothing left to report to
            pass
    _made.clear()
    _current.clear()
    _default_cl.cache_clear()
    _context_for.cache_clear()
    _build.cache_clear()
    gc.collect()


atexit.register(release_all)


def get_cl() -> CL:
    """The engine's choice of device: the process-wide one (each Dask worker
    makes its own), or the one `use_device` set. The engine hands it to the
    stages that declare `uses_opencl` (RunContext.cl); library and stage
    code never calls this but takes the handle as an argument."""
    if _current:
        return _current[-1]
    return _default_cl()


@functools.lru_cache(maxsize=None)
def _context_for(fingerprint_and_index: str, device) -> CL:
    import pyopencl as cl

    ctx = cl.Context([device])
    env = CL(ctx, cl.CommandQueue(ctx, device), device)
    _made.append(env)
    return env


def context_for(device) -> CL:
    """A context and queue on `device` (a pyopencl.Device), one per device
    and process: what a test of every device passes to the code it tests."""
    return _context_for(device_fingerprint(device) + str(device.int_ptr), device)


def _reopen(index: str, fingerprint: str) -> CL:
    """The other side of pickling a CL: this process's context on the device
    at platform:device `index`, which must be the one `fingerprint` names."""
    for c in list_devices():
        if c.index == index and c.fingerprint == fingerprint:
            return context_for(c.device)
    raise OpenCLError(f"no device {index} ({fingerprint}) in this process; "
                      f"found: {'; '.join(c.label for c in list_devices()) or 'none'}")


class use_device:
    """Make another device the engine's choice (get_cl) for a while: a bake
    in a test of every device.

        with use_device(candidate.device):
            ...  # get_cl() returns a context on that device
    """

    def __init__(self, device):
        self.env = context_for(device)

    def __enter__(self) -> CL:
        _current.append(self.env)
        return self.env

    def __exit__(self, *exc) -> None:
        _current.pop()


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


@functools.lru_cache(maxsize=128)
def _build(env: CL, source_hash: str, source: str, options: tuple[str, ...]):
    import pyopencl as cl

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # PoCL prints build logs as warnings even on success
        try:
            return cl.Program(env.ctx, source).build(options=list(options))
        except cl.RuntimeError as e:
            raise OpenCLError(f"OpenCL build failed on {env.fingerprint}:\n{e}\n"
                              "Another device may work: see `worldbake devices` and WORLDBAKE_CL_DEVICE.") from e


def require(env, what: str) -> CL:
    """`env` when it is a device handle; else an OpenCLError naming `what`
    needs one (code that also has a numpy path takes None for that path, so
    a missing device must fail where only the device will do)."""
    if not isinstance(env, CL):
        raise OpenCLError(f"{what}: no OpenCL device handed in (got {env!r}); a stage gets one as ctx.cl "
                          "when it declares uses_opencl")
    return env


def load_program(env: CL, path: Path | str, options: tuple[str, ...] = ()) -> "object":
    """Build the kernels in a .cl file for the device `env` once per process
    (and per options).

    `-cl-fp32-correctly-rounded-divide-sqrt` keeps divisions and square roots
    exact so kernels agree with their numpy references; fast-math options are
    never used because they change numbers between devices."""
    from .sources import CL_INCLUDE_DIR, cl_include_hash

    require(env, Path(path).name)
    source = Path(path).read_text()
    # The shared headers' hash is an option too: an edited header must not
    # be served from this process's cache or PoCL's (keyed on source text
    # and options).
    opts = BUILD_OPTIONS + (f"-I{CL_INCLUDE_DIR}", f"-DWORLDBAKE_INCLUDE_HASH=0x{cl_include_hash()[:12]}") + tuple(options)
    return _build(env, hashlib.sha256(source.encode()).hexdigest(), source, opts)


def global_size(shape: tuple[int, ...], local: tuple[int, ...] | None) -> tuple[int, ...]:
    """Round a global size up to a multiple of the local size; kernels guard
    against the padding with explicit bounds checks."""
    if local is None:
        return tuple(shape)
    return tuple(-(-s // l) * l for s, l in zip(shape, local))


def to_device(env: CL, array: np.ndarray):
    import pyopencl.array as cla

    return cla.to_device(env.queue, np.ascontiguousarray(array))


class CachedKernel:
    """A kernel launched many times with mostly the same arguments (a time loop).

    Each launch sets only the arguments that changed since the last launch with
    the same buffers: PoCL spends host time on every clSetKernelArg, which
    over the 50-odd arguments of an erosion step is CPU taken from the
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
