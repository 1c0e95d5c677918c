"""Benchmark of the vegetation stage (not part of `make test`).

    python -m bench.vegetation            # the default world: 8192 m at 1024^2 (8 m cells)
    python -m bench.vegetation --quick    # 4096 m at 512^2, shorter sweeps

1. Poisson-disk sampling, constant radius: our OpenCL dart thrower (grid
   phases, `poisson_passes` passes) against scipy.stats.qmc.PoissonDisk
   (Bridson-style, ncandidates = 30) asked for the same number of points in
   the same square; points per second, the points' density constant
   kappa = n r^2 / area and their smallest distance / r. Ours also on the
   whole world square (scipy is too slow there).
2. Simulation sweep on the default world's terrain (heightmap defaults,
   moisture from the topographic position): for years and simulation cell
   size, the ecosystem's run time, the placement's run time, the placement's
   density error against its own target (max and mean relative error over
   64 x 64-cell windows above the floor), and the competition error: the
   mean relative difference of each species' target count per window from
   the reference run (finest cell, most years), summed over species.
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np


def terrain(resolution: int, size_m: float, seed: int):
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from pipeline.grid import Grid
    from stages.heightmap.stage import HeightmapParams, heights

    p = HeightmapParams(size_m=size_m, resolution=resolution)
    h, _ = heights(cl_env, p, seed)
    return Grid(h, size_m / resolution, ("height",), (0.0, 0.0))


def poisson_vs_scipy(side_m: float, r: float, passes: int, big_side_m: float) -> None:
    from scipy.spatial import cKDTree
    from scipy.stats import qmc

    from pipeline.opencl import get_cl
    from stages.vegetation import device
    from stages.vegetation import placement as pl

    dev = device.on(get_cl())

    def ours(side):
        cells = int(side // 4.0) + 1
        dom = pl.Domain(cells, cells, side / (cells - 1), (0.0, 0.0))
        rad = np.full((cells, cells), r, np.float32)
        pl.poisson_sample(rad[:8, :8], r, pl.Domain(8, 8, dom.dx, (0, 0)), 1, 1, dev)  # build
        t0 = time.perf_counter()
        pts, _, info = pl.poisson_sample(rad, r, dom, passes, 7, dev)
        t = time.perf_counter() - t0
        return pts[:, :2].astype(np.float64), t, dom.width * dom.depth

    def quality(xy, area):
        d, _ = cKDTree(xy).query(xy, k=2)
        return len(xy) * r * r / area, d[:, 1].min() / r

    print(f"=== Poisson disk, constant radius r = {r:g} m ===")
    print(f"{'sampler':44s} {'points':>9s} {'seconds':>9s} {'points/s':>11s} {'kappa':>7s} {'min d/r':>8s}")
    xy, t, area = ours(side_m)
    k, m = quality(xy, area)
    print(f"{'ours, OpenCL, %d passes, %g m square' % (passes, side_m):44s} {len(xy):9d} {t:9.3f} {len(xy) / t:11.0f} {k:7.3f} {m:8.3f}")
    n = len(xy)
    eng = qmc.PoissonDisk(d=2, radius=r / side_m, seed=7)
    t0 = time.perf_counter()
    s = eng.random(n) * side_m
    ts = time.perf_counter() - t0
    k2, m2 = quality(s, side_m * side_m)
    print(f"{'scipy qmc.PoissonDisk, same square, same n':44s} {len(s):9d} {ts:9.3f} {len(s) / ts:11.0f} {k2:7.3f} {m2:8.3f}")
    print(f"speed-up x{(len(xy) / t) / (len(s) / ts):.1f} (points per second)")
    xy, t, area = ours(big_side_m)
    k, m = quality(xy, area)
    print(f"{'ours, %g m square' % big_side_m:44s} {len(xy):9d} {t:9.3f} {len(xy) / t:11.0f} {k:7.3f} {m:8.3f}\n")


def sweep(grid, configs, reference, seed: int) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.vegetation import attributes as at
    from stages.vegetation import device
    from stages.vegetation import device as dev
    from stages.vegetation import ecosystem as eco
    from stages.vegetation import placement as pl
    from stages.vegetation.params import VegetationParams
    from stages.vegetation.stage import preference_table

    h = grid.data
    rows, cols = h.shape
    dx = grid.cell_size_m
    base = VegetationParams()
    t0 = time.perf_counter()
    a = at.compute(h, dx, base, device.on(cl_env))
    moist = at.fallback_moisture(h, dx, base.moisture_fallback_radius_m, base.moisture_fallback_scale_m)
    names = base.plant_species()
    suit = dev.suitability(cl_env, h, a["slope"], moist, a["sunlight"], a["curvature"], np.zeros(h.shape, np.uint8),
                           preference_table(base, names))
    print(f"=== simulation sweep: {rows}x{cols} cells of {dx:g} m; attributes and suitability {time.perf_counter() - t0:.2f} s ===")
    dom = pl.Domain(rows, cols, dx, (0.0, 0.0))
    W = pl.density_window(dom)

    def window_counts(n_t):
        nr, nc = rows // W, cols // W
        return (n_t[:, : nr * W, : nc * W] * dx * dx).reshape(len(names), nr, W, nc, W).sum(axis=(2, 4))

    def one(years, cell):
        p = base.model_copy(update={"years": years, "sim_cell_m": cell})
        t0 = time.perf_counter()
        g = eco.sim_grid(cols, rows, dx, cell)
        ss = eco.to_sim_grid(suit, dx, g)
        res = eco.simulate(ss, g, p, names, seed, device.on(cl_env))
        share = eco.relative_yield(res, p, ss, eco.alone_density(p, names, cell, seed, device.on(cl_env)), dx, (rows, cols))
        t_sim = time.perf_counter() - t0
        n_t, _ = pl.target_density(p, names, suit, share, dx, (0.0, 0.0), seed)
        t0 = time.perf_counter()
        placed = pl.place_species(p, names, n_t, dom, seed, device.on(cl_env))
        t_place = time.perf_counter() - t0
        errs = [pl.density_error(placed[n].x, placed[n].z, n_t[s], dom) for s, n in enumerate(names)]
        return {"t_sim": t_sim, "t_place": t_place, "n_t": n_t, "stats": res.stats,
                "max_err": max(e["max_relative_error"] for e in errs),
                "mean_err": float(np.mean([e["mean_relative_error"] for e in errs])),
                "placed": sum(len(placed[n].x) for n in names)}

    ref_run = one(*reference)
    ref_w = window_counts(ref_run["n_t"])
    mask = ref_w.sum(axis=0) >= pl.WINDOW_FLOOR_PLANTS
    print(f"reference: years {reference[0]}, cell {reference[1]:g} m: simulation {ref_run['t_sim']:.2f} s, "
          f"placement {ref_run['t_place']:.2f} s, {ref_run['placed']} plants")
    print(f"{'years':>6s} {'cell m':>7s} {'sim s':>7s} {'place s':>8s} {'plants':>8s} {'place max err':>14s} "
          f"{'place mean err':>15s} {'competition err':>16s} {'plateau':>8s} {'evenness':>9s}")
    for years, cell in configs:
        r = ref_run if (years, cell) == tuple(reference) else one(years, cell)
        w = window_counts(r["n_t"])
        comp = float((np.abs(w - ref_w).sum(axis=0)[mask] / ref_w.sum(axis=0)[mask]).mean())
        st = r["stats"]
        print(f"{years:6d} {cell:7g} {r['t_sim']:7.2f} {r['t_place']:8.2f} {r['placed']:8d} {r['max_err']:14.4f} "
              f"{r['mean_err']:15.4f} {comp:16.4f} {st.get('plateau_relative_change', float('nan')):8.4f} "
              f"{st['share_evenness']:9.3f}")
    print("(place err: placed vs the run's own target; competition err: each species' target per window vs the "
          "reference run, summed over species, relative to the total)\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="4096 m at 512^2 and shorter sweeps")
    ap.add_argument("--seed", type=int, default=20261123)
    args = ap.parse_args(argv)

    from pipeline.opencl import get_cl
    from stages.vegetation.params import VegetationParams

    env = get_cl()
    print(f"device: {env.fingerprint}")
    print(f"host:   {platform.processor() or platform.machine()}, python {platform.python_version()}, numpy {np.__version__}\n")
    passes = VegetationParams().poisson_passes
    poisson_vs_scipy(600.0 if args.quick else 1000.0, 5.0, passes, 4096.0 if args.quick else 8192.0)

    if args.quick:
        grid = terrain(512, 4096.0, args.seed)
        configs = [(0, 8.0), (25, 8.0), (50, 8.0), (100, 8.0), (100, 16.0), (100, 32.0), (200, 4.0)]
        reference = (200, 4.0)
    else:
        grid = terrain(1024, 8192.0, args.seed)
        configs = [(0, 8.0), (25, 8.0), (50, 8.0), (100, 8.0), (200, 8.0), (100, 4.0), (100, 16.0), (100, 32.0),
                   (200, 4.0)]
        reference = (200, 4.0)
    sweep(grid, configs, reference, args.seed)


if __name__ == "__main__":
    main()
