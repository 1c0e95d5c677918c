"""Host side of the noise and fault kernels.

`make_spec` turns physical parameters (metres) into a `TerrainSpec`: the
octave and fault tables in cell units, all random numbers drawn on the host
with numpy's counter-based Philox generator keyed by (seed, purpose), so a
spec is a pure function of its arguments. `bake` runs `kernels.cl` on the
OpenCL device; `reference.evaluate` runs the same maths in numpy.

Conventions:
- cells are pixel-is-area; the sample of world cell (col, row) sits at
  X = col + 0.5, Z = row + 0.5 cell units, i.e. x = X * cell_size_m metres;
- octave i has frequency f_i = lacunarity**i / wavelength_m (cycles per metre)
  and amplitude lacunarity**(-i * hurst), i.e. gain = lacunarity**-hurst;
- with `tileable`, f_i is rounded to a whole number of cycles over size_m and
  the lattice indices wrap with that period, so the map is periodic;
- octaves whose wavelength is shorter than two cells (above Nyquist) are
  dropped: they can only alias. The normalisation still sums over all
  requested octaves, so heights do not change scale with resolution.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

KERNELS = Path(__file__).with_name("kernels.cl")
MAX_OCTAVES = 16  # table slots per field; random draws do not depend on the octave count
NOISE_STD = 0.305  # measured standard deviation of one octave of gnoise() (2e6 random points)

# Philox key purposes: independent streams from one seed
_PURPOSE_OCTAVES = 1
_PURPOSE_FAULTS = 2


@dataclass(frozen=True)
class TerrainSpec:
    """Everything the kernel needs, in cell units, as float32/int32 tables."""

    ridged: bool
    warp: bool
    fault: bool
    n_main: int
    n_warp: int
    octf: np.ndarray  # (n, 4) float32: scale (lattice units per cell), offset x, offset z, amplitude
    octi: np.ndarray  # (n, 4) int32: period (0 = not periodic), seed hash (uint32 bits), float32 bits of 1/period, 0
    hs: np.float32  # height = hb + hs * value
    hb: np.float32
    ridge_offset: np.float32 = np.float32(1.0)
    ridge_gain: np.float32 = np.float32(2.0)
    warp_cells: np.float32 = np.float32(0.0)
    faults: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))  # (m, 4): see fault_table
    cell_size_m: float = 1.0
    info: dict = field(default_factory=dict)  # diagnostics (octaves used, ...)

    @property
    def options(self) -> tuple[str, ...]:
        tileable = bool(len(self.octi) and (self.octi[:, 0] > 0).any())
        return (f"-DRIDGED={int(self.ridged)}", f"-DWARP={int(self.warp)}", f"-DFAULT={int(self.fault)}",
                f"-DTILEABLE={int(tileable)}")


def _seed_key(seed: int, purpose: int) -> np.ndarray:
    return np.array([int(seed) % (1 << 64), purpose], dtype=np.uint64)


def _octave_draws(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Per table slot (3 fields x MAX_OCTAVES): a uint32 hash seed and a
    fractional lattice offset (x, z) that keeps the octaves' lattices from
    lining up (with lacunarity 2 they would share every lattice line)."""
    rng = np.random.Generator(np.random.Philox(key=_seed_key(seed, _PURPOSE_OCTAVES)))
    seeds = rng.integers(0, 1 << 32, size=3 * MAX_OCTAVES, dtype=np.uint64).astype(np.uint32)
    offsets = rng.random((3 * MAX_OCTAVES, 2))
    return seeds, offsets


def octave_rows(
    *, slot0: int, wavelength_m: float, octaves: int, lacunarity: float, hurst: float,
    cell_size_m: float, size_m: float, tileable: bool, seeds: np.ndarray, offsets: np.ndarray,
    weight: float = 1.0, rms: bool = False,
) -> tuple[list, list]:
    """Table rows of one fBm field. Amplitudes sum to `weight` over the
    requested octaves (before dropping those above Nyquist), so the field is
    bounded by +-weight; with `rms` they are scaled instead so that the
    field's standard deviation is about `weight`."""
    amps = np.array([lacunarity ** (-i * hurst) for i in range(octaves)])
    norm = np.sqrt(np.sum(amps**2)) * NOISE_STD if rms else amps.sum()
    amps = amps / norm * weight
    rowsf, rowsi = [], []
    for i in range(octaves):
        f = lacunarity**i / wavelength_m  # cycles per metre
        period = 0
        if tileable:
            period = max(1, int(round(size_m * f)))
            f = period / size_m
        if f * cell_size_m > 0.5:  # shorter than two cells: aliasing only
            break
        s = slot0 + i
        rowsf.append((f * cell_size_m, offsets[s, 0], offsets[s, 1], amps[i]))
        inv = np.float32(1.0 / period if period else 0.0).view(np.int32)
        rowsi.append((period, int(seeds[s]), int(inv), 0))
    return rowsf, rowsi


def fault_table(
    seed: int, count: int, size_m: float, cell_size_m: float, softness_m: float, delta_min_ratio: float, weight: float,
) -> np.ndarray:
    """Fault lines: a random point in the world square and a random direction
    (Philox on the host). Step heights decrease linearly (seed 003, GPG):
    delta_i = dmax - (dmax - dmin) i / n with dmax = 1, dmin = delta_min_ratio;
    scaled so that `weight` is three standard deviations of the sum.
    Row i = (nx / w, nz / w, d / w - 1/2, weight_i), w = softness in cells, so
    the kernel's smoothstep argument is t = row0 * X + row1 * Z - row2."""
    if count == 0:
        return np.zeros((0, 4), np.float32)
    rng = np.random.Generator(np.random.Philox(key=_seed_key(seed, _PURPOSE_FAULTS)))
    theta = rng.random(count) * 2.0 * np.pi
    px, pz = rng.random(count) * size_m, rng.random(count) * size_m
    nx, nz = np.cos(theta), np.sin(theta)
    d_m = nx * px + nz * pz
    i = np.arange(count)
    delta = 1.0 - (1.0 - delta_min_ratio) * i / count
    w = delta / (3.0 * np.sqrt(np.sum(delta**2))) * weight
    soft = softness_m / cell_size_m
    return np.stack([nx / soft, nz / soft, d_m / cell_size_m / soft - 0.5, w], axis=1).astype(np.float32)


def make_spec(
    *, seed: int, generator: str, size_m: float, resolution: int, wavelength_m: float, octaves: int,
    lacunarity: float, hurst: float, relief_m: float, base_m: float, tileable: bool = False,
    warp_strength_m: float = 0.0, warp_wavelength_m: float = 1.0, warp_octaves: int = 4,
    warp_basis: str = "fbm", ridge_offset: float = 1.0, ridge_gain: float = 2.0,
    fault_count: int = 0, fault_softness_m: float = 1.0, fault_delta_min_ratio: float = 0.1,
    fault_noise_fraction: float = 0.0,
) -> TerrainSpec:
    """The kernel tables for one of the noise generators: fbm, ridged,
    warped or fault."""
    if generator not in ("fbm", "ridged", "warped", "fault"):
        raise ValueError(f"make_spec does not handle generator {generator!r}")
    if tileable and generator == "fault":
        raise ValueError("fault lines are not periodic: tileable is not possible with generator 'fault'")
    dx = size_m / resolution
    seeds, offsets = _octave_draws(seed)
    ridged = generator == "ridged" or (generator == "warped" and warp_basis == "ridged")
    warp = generator == "warped" and warp_strength_m > 0
    fault = generator == "fault"
    common = dict(lacunarity=lacunarity, hurst=hurst, cell_size_m=dx, size_m=size_m, tileable=tileable, seeds=seeds, offsets=offsets)
    main_weight = fault_noise_fraction if fault else 1.0
    f_main, i_main = [], []
    if main_weight > 0:
        f_main, i_main = octave_rows(slot0=0, wavelength_m=wavelength_m, octaves=octaves, weight=main_weight, **common)
    f_wx, i_wx, f_wz, i_wz = [], [], [], []
    if warp:
        f_wx, i_wx = octave_rows(slot0=MAX_OCTAVES, wavelength_m=warp_wavelength_m, octaves=warp_octaves, rms=True, **common)
        f_wz, i_wz = octave_rows(slot0=2 * MAX_OCTAVES, wavelength_m=warp_wavelength_m, octaves=warp_octaves, rms=True, **common)
        if not f_wx:
            warp = False
    if not warp:
        f_wx, i_wx, f_wz, i_wz = [], [], [], []
    octf = np.array(f_main + f_wx + f_wz, dtype=np.float64).reshape(-1, 4).astype(np.float32)
    octi = np.array(i_main + i_wx + i_wz, dtype=np.int64).reshape(-1, 4)
    octi = (octi & 0xFFFFFFFF).astype(np.uint32).view(np.int32)  # seed hash: uint32 bits in an int
    if ridged:  # sum of s_i * amp_i lies in [0, offset^2]; map it to [-1, 1]
        hs, hb = relief_m * 2.0 / ridge_offset**2, base_m - relief_m
    else:
        hs, hb = relief_m, base_m
    faults = np.zeros((0, 4), np.float32)
    if fault:
        faults = fault_table(seed, fault_count, size_m, dx, fault_softness_m, fault_delta_min_ratio, 1.0 - fault_noise_fraction)
    return TerrainSpec(
        ridged=ridged, warp=warp, fault=fault, n_main=len(f_main), n_warp=len(f_wx),
        octf=np.ascontiguousarray(octf), octi=np.ascontiguousarray(octi),
        hs=np.float32(hs), hb=np.float32(hb), ridge_offset=np.float32(ridge_offset), ridge_gain=np.float32(ridge_gain),
        warp_cells=np.float32(warp_strength_m / dx), faults=faults,
        cell_size_m=dx,
        info={"octaves_used": len(f_main), "warp_octaves_used": len(f_wx) if warp else 0},
    )


def vector_width(device) -> int:
    """Cells per work-item: the device's preferred float vector width (8 on
    AVX2/AVX-512 CPUs, 1 on most GPUs), as one of 1, 2, 4, 8. Capped at 8:
    PoCL 3.0 / LLVM 14 crashes building the 16-wide kernel ("Cannot emit
    physreg copy instruction")."""
    w = int(getattr(device, "preferred_vector_width_float", 1) or 1)
    return max(v for v in (1, 2, 4, 8) if v <= max(1, min(w, 8)))


def program(env, spec: TerrainSpec, vw: int):
    from pipeline.opencl import load_program

    return load_program(env, KERNELS, spec.options + (f"-DVW={vw}",))


def bake(
    env, spec: TerrainSpec, window: tuple[int, int, int, int], local_size: tuple[int, int] | None = None,
    progress: Callable[[float, str], None] | None = None, band_cells: int = 1 << 22, vw: int | None = None,
) -> tuple[np.ndarray, float]:
    """Evaluate the spec on the OpenCL device `env` (pipeline.opencl.CL) on
    the tile window = (col0, row0, cols, rows) of world cells (any integers;
    cells outside the world continue the same function). Returns the
    float32 (rows, cols) heights and the device time in seconds.

    A work-item computes `vw` consecutive cells of a row (default: the
    device's preferred vector width); `local_size` is in work-items. The tile
    is computed in row bands (one launch each, for progress). Each cell is
    computed and written on its own, so neither the bands, `vw` nor
    `local_size` change a single bit of the result. The device holds one
    band (band_cells cells, 16 MiB by default), copied back after each launch,
    so tiles of any size fit the device's allocation limit."""
    import pyopencl as cl

    from pipeline.opencl import global_size

    col0, row0, cols, rows = (int(v) for v in window)
    if cols <= 0 or rows <= 0:
        raise ValueError(f"empty window {window}")
    vw = vector_width(env.device) if vw is None else int(vw)
    kernel = cl.Kernel(program(env, spec, vw), "terrain")
    mf = cl.mem_flags

    def const(a, dtype):
        a = np.ascontiguousarray(a, dtype=dtype).ravel()
        a = a if a.size else np.zeros(4, dtype)
        return cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)

    d_octf, d_octi, d_fault = const(spec.octf, np.float32), const(spec.octi, np.int32), const(spec.faults, np.float32)
    band = max(1, band_cells // cols)
    if local_size is not None:
        band = -(-band // local_size[1]) * local_size[1]
    band = min(band, rows)
    d_out = cl.Buffer(env.ctx, mf.WRITE_ONLY, band * cols * 4)  # one band; reused
    i32, f32 = np.int32, np.float32
    kernel.set_args(
        d_out, i32(cols), i32(band), i32(col0), i32(row0), i32(spec.n_main), i32(spec.n_warp), d_octf, d_octi,
        f32(spec.hs), f32(spec.hb), f32(spec.ridge_offset), f32(spec.ridge_gain), f32(spec.warp_cells),
        i32(len(spec.faults)), d_fault,
    )
    items_x = -(-cols // vw)
    out = np.empty((rows, cols), np.float32)
    seconds = 0.0
    for r in range(0, rows, band):
        n = min(band, rows - r)
        kernel.set_arg(2, i32(n))  # rows in this band
        kernel.set_arg(4, i32(row0 + r))  # world row of the band's first row
        t0 = time.perf_counter()
        cl.enqueue_nd_range_kernel(env.queue, kernel, global_size((items_x, n), local_size), local_size)
        env.queue.finish()
        seconds += time.perf_counter() - t0
        cl.enqueue_copy(env.queue, out[r:r + n], d_out).wait()
        if progress is not None and rows > band:
            progress((r + n) / rows, f"rows {r + n}/{rows}")
    return out, seconds
