"""Benchmark of the heightmap kernels (not part of `make test`).

    python -m bench.heightmap            # 2048^2 and 4096^2
    python -m bench.heightmap --quick    # 512^2 and 1024^2

For each size it prints, in one run on the same device:
- our kernel time per generator (best of --repeat, after a warm-up launch that
  also builds the program), in M cells/s and ns per cell-octave;
- the numpy reference (reference.py), timed on a smaller grid and scaled per
  cell (said so in the output);
- pyfastnoiselite (FastNoiseLite, Perlin and OpenSimplex2, fractal FBm, the
  same octaves, lacunarity and gain, `gen_from_coords` with float32 numpy
  coordinates made before the clock starts);
- achieved bandwidth (bytes written / time) of our kernel against the
  roofline measured in the same run: a trivial fill kernel (4 B written per
  cell) and a copy kernel (4 B read + 4 B written per cell).
The fBm config is chosen so that all octaves are above the Nyquist cut-off
(cell = 1 m, first wavelength 2^(octaves-1) * 2 m).
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np


def best_of(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def cl_roofline(n_cells: int, repeat: int) -> dict[str, float]:
    """GB/s of a fill (write only) and a copy (read + write) kernel."""
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    import pyopencl as cl

    from pipeline.opencl import get_cl
    from stages.heightmap import noise
    from pipeline.opencl import load_program

    env = get_cl()
    prg = load_program(cl_env, noise.KERNELS, ("-DVW=1",))
    a = cl.Buffer(env.ctx, cl.mem_flags.READ_WRITE, n_cells * 4)
    b = cl.Buffer(env.ctx, cl.mem_flags.READ_WRITE, n_cells * 4)
    fill = cl.Kernel(prg, "fill")
    fill.set_args(a, np.int32(n_cells), np.float32(1.0))
    copy = cl.Kernel(prg, "copy")
    copy.set_args(a, b, np.int32(n_cells))

    def run_fill():
        cl.enqueue_nd_range_kernel(env.queue, fill, (n_cells,), None)
        env.queue.finish()

    def run_copy():
        cl.enqueue_nd_range_kernel(env.queue, copy, (n_cells,), None)
        env.queue.finish()

    run_fill(), run_copy()
    t_fill = best_of(run_fill, repeat)
    t_copy = best_of(run_copy, repeat)
    return {"fill_gbs": n_cells * 4 / t_fill / 1e9, "copy_gbs": n_cells * 8 / t_copy / 1e9,
            "fill_s": t_fill, "copy_s": t_copy}


def fastnoise_time(n: int, octaves: int, wavelength_cells: float, noise_type: str, repeat: int) -> float:
    import pyfastnoiselite.pyfastnoiselite as fnl

    f = fnl.FastNoiseLite(1234)
    f.noise_type = getattr(fnl.NoiseType, f"NoiseType_{noise_type}")
    f.fractal_type = fnl.FractalType.FractalType_FBm
    f.fractal_octaves = octaves
    f.fractal_lacunarity = 2.0
    f.fractal_gain = 0.5
    f.frequency = 1.0 / wavelength_cells
    z, x = np.mgrid[0:n, 0:n].astype(np.float32)
    coords = np.ascontiguousarray(np.stack([x.ravel() + 0.5, z.ravel() + 0.5]))
    del x, z
    f.gen_from_coords(coords[:, :1024])  # warm-up
    return best_of(lambda: f.gen_from_coords(coords), repeat)


def main(argv=None) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="512^2 and 1024^2 instead of 2048^2 and 4096^2")
    ap.add_argument("--octaves", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--ref-size", type=int, default=256, help="grid side for timing the numpy reference")
    args = ap.parse_args(argv)

    from pipeline.opencl import get_cl
    from stages.heightmap import noise, reference

    sizes = (512, 1024) if args.quick else (2048, 4096)
    octaves = args.octaves
    wavelength = 2.0 ** (octaves - 1) * 2.0  # in cells: the last octave is exactly two cells
    env = get_cl()
    print(f"device: {env.fingerprint}")
    print(f"host:   {platform.processor() or platform.machine()}, python {platform.python_version()}, numpy {np.__version__}")
    print(f"fbm: {octaves} octaves, lacunarity 2, gain 0.5 (hurst 1), first wavelength {wavelength:g} cells; "
          f"best of {args.repeat}\n")

    def spec_for(gen: str, n: int):
        extra = {}
        if gen == "warped":
            extra = dict(warp_strength_m=20.0, warp_wavelength_m=wavelength, warp_octaves=3, warp_basis="fbm")
        if gen == "fault":
            extra = dict(fault_count=256, fault_softness_m=8.0, fault_noise_fraction=0.0)
        s = noise.make_spec(seed=1, generator=gen, size_m=float(n), resolution=n, wavelength_m=wavelength, octaves=octaves,
                            lacunarity=2.0, hurst=1.0, relief_m=1000.0, base_m=0.0, **extra)
        return s

    gens = {"fbm": "fbm", "ridged": "ridged", "warped": "warped fbm + 2x3 warp octaves", "fault": "fault, 256 lines, no noise"}
    for n in sizes:
        cells = n * n
        print(f"=== {n}x{n} = {cells / 1e6:.1f} M cells ===")
        roof = cl_roofline(cells, args.repeat)
        results = {}
        for gen in gens:
            s = spec_for(gen, n)
            assert gen == "fault" or s.n_main == octaves, s.info
            noise.bake(cl_env, s, (0, 0, 64, 64))  # build + warm-up
            times = [noise.bake(cl_env, s, (0, 0, n, n))[1] for _ in range(args.repeat)]
            results[gen] = min(times)
        # numpy reference, timed on a smaller grid and scaled per cell
        m = min(args.ref_size, n)
        ref_t = {}
        for gen in ("fbm", "fault"):
            s = spec_for(gen, n)
            ref_t[gen] = best_of(lambda: reference.evaluate(s, (0, 0, m, m)), 1) * cells / (m * m)
        fnl_perlin = fastnoise_time(n, octaves, wavelength, "Perlin", max(1, args.repeat - 1))
        fnl_os2 = fastnoise_time(n, octaves, wavelength, "OpenSimplex2", max(1, args.repeat - 1))

        print(f"{'generator':40s} {'seconds':>9s} {'Mcell/s':>9s} {'GB/s out':>9s}")
        for gen, label in gens.items():
            t = results[gen]
            print(f"{'ours ' + label:40s} {t:9.4f} {cells / t / 1e6:9.1f} {cells * 4 / t / 1e9:9.3f}")
        for label, t in [("numpy reference fbm (scaled from %d^2)" % m, ref_t["fbm"]),
                         ("numpy reference fault (scaled from %d^2)" % m, ref_t["fault"]),
                         ("pyfastnoiselite Perlin FBm", fnl_perlin),
                         ("pyfastnoiselite OpenSimplex2 FBm", fnl_os2)]:
            print(f"{label:40s} {t:9.4f} {cells / t / 1e6:9.1f}")
        print(f"{'roofline: fill kernel (4 B/cell)':40s} {roof['fill_s']:9.4f} {cells / roof['fill_s'] / 1e6:9.1f} {roof['fill_gbs']:9.3f}")
        print(f"{'roofline: copy kernel (8 B/cell)':40s} {roof['copy_s']:9.4f} {cells / roof['copy_s'] / 1e6:9.1f} {roof['copy_gbs']:9.3f}")
        t = results["fbm"]
        print(f"fbm: {t / cells / octaves * 1e9:.2f} ns per cell-octave; "
              f"speed-up vs numpy reference x{ref_t['fbm'] / t:.1f}, "
              f"vs FastNoiseLite Perlin x{fnl_perlin / t:.2f}, vs OpenSimplex2 x{fnl_os2 / t:.2f}; "
              f"bandwidth {cells * 4 / t / 1e9:.3f} GB/s = {100 * cells * 4 / t / 1e9 / roof['fill_gbs']:.1f} % of the fill roofline "
              "(compute bound)\n")


if __name__ == "__main__":
    main()
