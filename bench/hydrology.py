"""Benchmark of the hydrology kernels against pysheds (not part of `make test`).

    python -m bench.hydrology            # 1024^2 and 4096^2
    python -m bench.hydrology --quick    # 512^2 and 1024^2
    python -m bench.hydrology --erode-max 4096   # erode 4096^2 too (slow)

DEMs: stages.heightmap.stage.heights(HeightmapParams(resolution=n), seed) at
the default world's size (8192 m) ("raw"), and the same DEM eroded by the
erosion stage's run (through a RunContext) with the default world's settings
("eroded"). Eroding 4096^2 takes about 40 minutes on 2 cores, so by default
DEMs above --erode-max (1024) are eroded at 1024^2 and resampled by cubic
spline ("eroded1024up"); the erosion time is printed, not in the table.

For each DEM it times, best of --repeat at every size (after a warm-up on a small grid that
builds our programs and numba-compiles pysheds), host arrays in and out:
- fill: ours = dev.fill (Priority-Flood by relaxation on the device, no
  epsilon) vs pysheds sGrid.fill_depressions;
- flowdir: D8 on the same filled DEM (ours on the epsilon-filled surface,
  which pysheds gets too, so the outputs are comparable);
- accumulation: D8 accumulation of our directions (ours exact in integers)
  vs pysheds sGrid.accumulation of the same directions;
and checks equality: fill bit-exact, flowdir agreement fraction, accumulation
equal. Breaching (no pysheds counterpart) is timed against our pure-Python
reference, with a bit-exactness check. Needs `pip install pysheds affine`; pysheds 0.5 calls np.in1d, shimmed.
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
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.heightmap.stage import HeightmapParams, heights

    h, _ = heights(cl_env, HeightmapParams(resolution=n), seed)
    return h


# the default world's erosion settings (configs/default.toml)
DEFAULT_EROSION = dict(boundary="open", thermal_years=300.0, storm_hours=0.35)
_ERODED: dict[int, np.ndarray] = {}


def erode(n: int) -> tuple[np.ndarray, float]:
    """The n^2 DEM eroded by the erosion stage (its run, through a RunContext,
    with the default world's settings); returns (height, seconds)."""
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    import tempfile
    from pathlib import Path

    from pipeline.contract import RunContext
    from pipeline.grid import Grid
    from stages.erosion import STAGE, ErosionParams

    if n not in _ERODED:
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            ctx = RunContext(cl=cl_env, stage=STAGE, key="bench", out_dir=Path(tmp), seed=0, provenance={}, project_root=Path(tmp))
            out = STAGE.run(ctx, {"height": Grid(dem(n).astype(np.float32), cell_size_m=8192.0 / n)},
                            ErosionParams(**DEFAULT_EROSION))
        _ERODED[n] = (np.asarray(out["erosion.height"].channel("height"), np.float32), time.perf_counter() - t0)
    return _ERODED[n]


def eroded(n: int, erode_max: int):
    """(height, label, note): eroded at n^2 when n <= erode_max, otherwise
    eroded at erode_max^2 and resampled (cubic spline) to n^2, a DEM with the
    eroded valleys at the finer cell size but not eroded at that size."""
    try:
        from stages.erosion import STAGE  # noqa: F401
    except Exception as e:  # the erosion stage is not there
        return None, None, f"erosion stage not importable ({type(e).__name__}: {e})"
    m = min(n, erode_max)
    h, secs = erode(m)
    if m == n:
        return h, "eroded", f"eroded at {m}^2 in {secs:.0f} s"
    from scipy import ndimage

    return (ndimage.zoom(h.astype(np.float64), n / m, order=3).astype(np.float32), f"eroded{m}up",
            f"eroded at {m}^2 in {secs:.0f} s, resampled to {n}^2 (cubic)")


def main() -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sizes", type=int, nargs="*")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--erode-max", type=int, default=1024,
                    help="largest size eroded by the erosion stage (4096^2 takes ~40 min on 2 cores); larger "
                    "DEMs are eroded at this size and resampled")
    ap.add_argument("--no-eroded", action="store_true")
    ap.add_argument("--breach-ref-max", type=int, default=1024,
                    help="largest size at which the pure-Python breaching reference is timed (4096^2: ~80 s)")
    args = ap.parse_args()
    sizes = args.sizes or ([512, 1024] if args.quick else [1024, 4096])

    np.in1d = getattr(np, "in1d", np.isin)
    from affine import Affine
    from pysheds.sgrid import sGrid
    from pysheds.sview import Raster, ViewFinder

    from pipeline.opencl import get_cl
    from worldlib.flow import device as dev
    from worldlib.flow import reference as ref

    print(f"device: {get_cl().fingerprint}")
    dirmap = np.array([64, 128, 1, 2, 4, 8, 16, 32])

    def ps_grid(h, dx):
        vf = ViewFinder(affine=Affine(dx, 0, 0, 0, -dx, 0), shape=h.shape, nodata=np.nan)
        return sGrid(viewfinder=vf), vf

    # warm-up: build programs, numba-compile pysheds
    w = dem(64)
    k = ref.cell_kinds(w)
    g, vf = ps_grid(w, 8.0)
    R = dev.fill(cl_env, w, k, True)
    c = dev.d8(cl_env, R, k, 8.0)
    dev.accumulate(cl_env, c)
    dev.breach(cl_env, w, k)
    g.accumulation(g.flowdir(g.fill_depressions(Raster(w.astype(np.float64), viewfinder=vf))))

    rows, breaches = [], []
    for n in sizes:
        cases = [("raw", dem(n))]
        if not args.no_eroded:
            e, label, why = eroded(n, args.erode_max)
            print(f"{n}^2 eroded: {why}", flush=True)
            if e is not None:
                cases.append((label, e))
        for label, h in cases:
            h = ref.canonical(h)
            dx = 8192.0 / n
            kind = ref.cell_kinds(h)
            g, vf = ps_grid(h, dx)
            cells = h.size
            r = args.repeat
            t_ours_fill, F = best_of(lambda: dev.fill(cl_env, h, kind, False), r)
            t_ps_fill, PF = best_of(lambda: g.fill_depressions(Raster(h.astype(np.float64), viewfinder=vf)), r)
            fill_equal = bool(np.array_equal(F, np.asarray(PF).astype(np.float32)))
            R = dev.fill(cl_env, h, kind, True)
            R64 = Raster(R.astype(np.float64), viewfinder=vf)
            t_ours_fd, code = best_of(lambda: dev.d8(cl_env, R, kind, dx), r)
            t_ps_fd, pfd = best_of(lambda: g.flowdir(R64), r)
            inter = kind == ref.INTERIOR
            agree = float((np.asarray(pfd)[inter] == dirmap[code[inter]]).mean())
            ours_dirs = np.where(code >= 0, dirmap[np.clip(code, 0, 7)], 0).astype(np.int64)
            fd_r = Raster(ours_dirs, viewfinder=ViewFinder(affine=vf.affine, shape=h.shape, nodata=0))
            t_ours_acc, A = best_of(lambda: dev.accumulate(cl_env, code), r)
            t_ps_acc, PA = best_of(lambda: g.accumulation(fd_r), r)
            PA = np.asarray(PA)
            acc_equal = bool(np.array_equal(PA[inter], A[inter].astype(np.float64)))
            # breaching has no pysheds counterpart: the serial kernel against the Python reference
            t_ours_br, B = best_of(lambda: dev.breach(cl_env, h, kind), r)
            if n <= args.breach_ref_max:
                t_ref_br, RB = best_of(lambda: ref.breach(h, kind), 1)
                breaches.append((f"{n}^2 {label}", cells / t_ours_br / 1e6, cells / t_ref_br / 1e6,
                                 t_ref_br / t_ours_br, bool(np.array_equal(B, RB, equal_nan=True))))
            else:
                breaches.append((f"{n}^2 {label}", cells / t_ours_br / 1e6, float("nan"), float("nan"), None))
            for op, to, tp, check in (("fill", t_ours_fill, t_ps_fill, f"bit-exact={fill_equal}"),
                                      ("flowdir", t_ours_fd, t_ps_fd, f"agree={agree:.6f}"),
                                      ("accumulation", t_ours_acc, t_ps_acc, f"equal={acc_equal}")):
                rows.append((f"{n}^2 {label}", op, cells / to / 1e6, cells / tp / 1e6, tp / to, check))
            print(f"{n}^2 {label}: done", flush=True)

    print()
    print(f"{'DEM':20s} {'operation':13s} {'ours Mcell/s':>13s} {'pysheds Mcell/s':>16s} {'ratio':>7s}  check")
    for dem_name, op, o, p, ratio, check in rows:
        print(f"{dem_name:20s} {op:13s} {o:13.1f} {p:16.2f} {ratio:7.2f}  {check}")
    print()
    print("complete breaching (serial priority queue): our kernel vs the pure-Python reference (heapq)")
    print(f"{'DEM':20s} {'ours Mcell/s':>13s} {'Python Mcell/s':>15s} {'ratio':>7s}  bit-exact")
    for dem_name, o, p, ratio, same in breaches:
        print(f"{dem_name:20s} {o:13.2f} {p:15.3f} {ratio:7.1f}  {same}")


if __name__ == "__main__":
    main()
