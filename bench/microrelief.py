"""The erosion's microrelief (stages/erosion/microrelief.py): run time
against error for its one quality knob, the classes of disturbance sizes
per octave (not part of `make test`).

    python -m bench.microrelief                 # 1 m cells under an 8 m geology, 1, 2, 4 classes per octave
    python -m bench.microrelief --size 512 --seeds 2

Error: a periodic field's periodogram (its seeds pooled) against the
analytic steady state S(k) = C (exp(-k^2 s0^2) - exp(-k^2 s1^2)), as the
worst ratio per ring of wavelengths 32 .. 3 m, and the 2-to-16-cell grid
anisotropy (1 isotropic; the stat the hydrology reports). Time: one
--size^2 window with its halo, seconds per million cells, best of two.
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np


def main(argv=None) -> None:
    from stages.erosion import microrelief
    from worldlib.terrain.stats import grid_anisotropy

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--classes", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--rms", type=float, default=0.1)
    ap.add_argument("--size-m", type=float, default=1.5)
    a = ap.parse_args(argv)
    n, s0, s1 = a.size, max(a.size_m, 1.0), 4.0
    k1 = 2 * np.pi * np.fft.fftfreq(n, 1.0)
    k = np.hypot(*np.meshgrid(k1, k1, indexing="ij"))
    c = a.rms ** 2 / (1 / (4 * math.pi * s0 ** 2) - 1 / (4 * math.pi * s1 ** 2))
    want = c * (np.exp(-k ** 2 * s0 ** 2) - np.exp(-k ** 2 * s1 ** 2))
    edges = 2 * np.pi / np.array([32.0, 16.0, 12.0, 8.0, 6.0, 4.0, 3.0])
    rings = [(k >= lo) & (k < hi) for lo, hi in zip(edges, edges[1:])]
    print(f"{n}^2 cells of 1 m under an 8 m geology, RMS {a.rms} m, s0 {s0} m, s1 {s1} m, {a.seeds} seeds")
    print("classes/octave classes  s/Mcell  worst ring ratio (32..3 m)  ratio 32..6 m  anisotropy  RMS")
    default = microrelief.CLASSES_PER_OCTAVE
    try:
        for per in a.classes:
            microrelief.CLASSES_PER_OCTAVE = per
            fields, best = [], math.inf
            for seed in range(a.seeds):
                mr = microrelief.MicroRelief.of(seed, (n, n), 1.0, 8.0, a.rms, a.size_m, periodic=True)
                for _ in range(2 if seed == 0 else 1):
                    t = time.perf_counter()
                    f = mr.field((0, 0, n, n))
                    best = min(best, time.perf_counter() - t)
                fields.append(f)
            power = sum(np.abs(np.fft.fft2(f)) ** 2 / n ** 2 for f in fields) / len(fields)
            ratios = [power[r].mean() / want[r].mean() for r in rings]
            worst = max(ratios, key=lambda x: abs(math.log(x)))
            worst_wide = max(ratios[:-1], key=lambda x: abs(math.log(x)))
            aniso = np.mean([grid_anisotropy(f) for f in fields])
            rms = np.mean([f.std() for f in fields])
            print(f"{per:14d} {len(mr.sizes_m):7d} {best / (n * n / 1e6):8.3f} {worst:27.3f} {worst_wide:14.3f} "
                  f"{aniso:11.3f} {rms:.4f}")
    finally:
        microrelief.CLASSES_PER_OCTAVE = default


if __name__ == "__main__":
    main()
