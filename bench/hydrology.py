"""Benchmark of the hydrology kernels against pysheds (not part of `make test`).

    python -m bench.hydrology            # 1024^2 and 4096^2
    python -m bench.hydrology --quick    # 512^2 and 1024^2

DEMs: stages.heightmap.stage.heights(HeightmapParams(resolution=n), seed) at
the default world's size (8192 m). "eroded" DEMs come from the erosion stage
when it is importable with a usable entry point; otherwise the line says so.

For each DEM it times, best of --repeat (after a warm-up on a small grid that
builds our programs and numba-compiles pysheds), host arrays in and out:
- fill: ours = dev.fill (Priority-Flood by relaxation on the device, no
  epsilon) vs pysheds sGrid.fill_depressions;
- flowdir: D8 on the same filled DEM (ours on the epsilon-filled surface,
  which pysheds gets too, so the outputs are comparable);
- accumulation: D8 accumulation of our directions (ours exact in integers)
  vs pysheds sGrid.accumulation of the same directions;
and checks equality: fill bit-exact, flowdir agreement fraction, accumulation
equal. Needs `pip install pysheds affine`; pysheds 0.5 calls np.in1d, shimmed.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def best_of(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def dem(n: int, seed: int = 20261123) -> np.ndarray:
    from stages.heightmap.stage import HeightmapParams, heights

    h, _ = heights(HeightmapParams(resolution=n), seed)
    return h


def eroded(n: int):
    try:
        from stages.erosion import STAGE  # noqa: F401
    except Exception as e:  # the erosion stage is not there yet
        return None, f"erosion stage not importable ({type(e).__name__}: {e})"
    return None, "erosion stage has no bench entry point yet"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sizes", type=int, nargs="*")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    sizes = args.sizes or ([512, 1024] if args.quick else [1024, 4096])

    np.in1d = getattr(np, "in1d", np.isin)
    from affine import Affine
    from pysheds.sgrid import sGrid
    from pysheds.sview import Raster, ViewFinder

    from pipeline.opencl import get_cl
    from stages.hydrology import device as dev
    from stages.hydrology import reference as ref

    print(f"device: {get_cl().fingerprint}")
    dirmap = np.array([64, 128, 1, 2, 4, 8, 16, 32])

    def ps_grid(h, dx):
        vf = ViewFinder(affine=Affine(dx, 0, 0, 0, -dx, 0), shape=h.shape, nodata=np.nan)
        return sGrid(viewfinder=vf), vf

    # warm-up: build programs, numba-compile pysheds
    w = dem(64)
    k = ref.cell_kinds(w)
    g, vf = ps_grid(w, 8.0)
    R = dev.fill(w, k, True)
    c = dev.d8(R, k, 8.0)
    dev.accumulate(c)
    g.accumulation(g.flowdir(g.fill_depressions(Raster(w.astype(np.float64), viewfinder=vf))))

    rows = []
    for n in sizes:
        cases = [("raw", dem(n))]
        e, why = eroded(n)
        if e is None:
            print(f"{n}^2 eroded: not run: {why}")
        else:
            cases.append(("eroded", e))
        for label, h in cases:
            h = ref.canonical(h)
            dx = 8192.0 / n
            kind = ref.cell_kinds(h)
            g, vf = ps_grid(h, dx)
            cells = h.size
            r = args.repeat if n <= 1024 else 1
            t_ours_fill, F = best_of(lambda: dev.fill(h, kind, False), r)
            t_ps_fill, PF = best_of(lambda: g.fill_depressions(Raster(h.astype(np.float64), viewfinder=vf)), r)
            fill_equal = bool(np.array_equal(F, np.asarray(PF).astype(np.float32)))
            R = dev.fill(h, kind, True)
            R64 = Raster(R.astype(np.float64), viewfinder=vf)
            t_ours_fd, code = best_of(lambda: dev.d8(R, kind, dx), r)
            t_ps_fd, pfd = best_of(lambda: g.flowdir(R64), r)
            inter = kind == ref.INTERIOR
            agree = float((np.asarray(pfd)[inter] == dirmap[code[inter]]).mean())
            ours_dirs = np.where(code >= 0, dirmap[np.clip(code, 0, 7)], 0).astype(np.int64)
            fd_r = Raster(ours_dirs, viewfinder=ViewFinder(affine=vf.affine, shape=h.shape, nodata=0))
            t_ours_acc, A = best_of(lambda: dev.accumulate(code), r)
            t_ps_acc, PA = best_of(lambda: g.accumulation(fd_r), r)
            PA = np.asarray(PA)
            acc_equal = bool(np.array_equal(PA[inter], A[inter].astype(np.float64)))
            for op, to, tp, check in (("fill", t_ours_fill, t_ps_fill, f"bit-exact={fill_equal}"),
                                      ("flowdir", t_ours_fd, t_ps_fd, f"agree={agree:.6f}"),
                                      ("accumulation", t_ours_acc, t_ps_acc, f"equal={acc_equal}")):
                rows.append((f"{n}^2 {label}", op, cells / to / 1e6, cells / tp / 1e6, tp / to, check))
            print(f"{n}^2 {label}: done", flush=True)

    print()
    print(f"{'DEM':14s} {'operation':13s} {'ours Mcell/s':>13s} {'pysheds Mcell/s':>16s} {'ratio':>7s}  check")
    for dem_name, op, o, p, ratio, check in rows:
        print(f"{dem_name:14s} {op:13s} {o:13.1f} {p:16.2f} {ratio:7.2f}  {check}")


if __name__ == "__main__":
    main()
