"""Benchmark of the stream-power mode (geological time) against fastscapelib
(not part of `make test`).

    python -m bench.stream_power                 # 512^2 and 1024^2, 10 steps
    python -m bench.stream_power --sizes 256 --steps 20

Same DEM (the default world's heightmap at n^2 over 8192 m), same law
(dh/dt = U - K A^m S^n, n = 1), same uplift (every cell but the map edges),
same steps. fastscapelib: RasterGrid with fixed-value edges, FlowGraph with
SingleFlowRouter + PFloodSinkResolver, SPLEroder; ours: stream_power.run
(Priority-Flood+epsilon, D8 and exact accumulation on the OpenCL device,
serial implicit solve). Both the whole loop (routing, accumulation, solve),
best of --repeat. Agreement: the erosion depth of both after the run, as
relative RMS difference and correlation (D8 tie-breaks on flats differ, so
not bit-equal).
"""
from __future__ import annotations

import argparse

import numpy as np

K, M, N, UPLIFT, DT = 2.0e-5, 0.45, 1.0, 1.0e-3, 2.0e4


def fastscape(h0: np.ndarray, dx: float, steps: int) -> np.ndarray:
    import fastscapelib as fs

    grid = fs.RasterGrid(list(h0.shape), [dx, dx], fs.NodeStatus.FIXED_VALUE)
    graph = fs.FlowGraph(grid, [fs.SingleFlowRouter(), fs.PFloodSinkResolver()])
    eroder = fs.SPLEroder(graph, k_coef=K, area_exp=M, slope_exp=N, tolerance=1e-10)
    uplift = np.full(h0.shape, UPLIFT)
    uplift[[0, -1], :] = 0.0
    uplift[:, [0, -1]] = 0.0
    h = h0.copy()
    for _ in range(steps):
        up = h + DT * uplift
        graph.update_routes(up)
        area = graph.accumulate(1.0)
        h = up - eroder.erode(up, area, DT)
    return h


def ours(h0: np.ndarray, dx: float, steps: int) -> np.ndarray:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.erosion import stream_power as sp

    return sp.run(cl_env, h0, dx, years=steps * DT, dt_years=DT, k=K, m=M, n_exp=N, uplift_m_per_year=UPLIFT).height


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="*", default=[512, 1024])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    from bench.hydrology import best_of, dem
    from pipeline.opencl import get_cl

    print(f"device: {get_cl().fingerprint}")
    ours(dem(64).astype(np.float64), 128.0, 1)  # build the programs
    fastscape(dem(64).astype(np.float64), 128.0, 1)
    rows = []
    for n in args.sizes:
        h0 = dem(n).astype(np.float64)
        dx = 8192.0 / n
        t_ours, h_ours = best_of(lambda: ours(h0, dx, args.steps), args.repeat)
        t_fs, h_fs = best_of(lambda: fastscape(h0, dx, args.steps), args.repeat)
        e_ours, e_fs = h0 + args.steps * DT * UPLIFT - h_ours, h0 + args.steps * DT * UPLIFT - h_fs
        inner = (slice(1, -1), slice(1, -1))
        a, b = e_ours[inner].ravel(), e_fs[inner].ravel()
        rel = float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2)))
        corr = float(np.corrcoef(a, b)[0, 1])
        cells = n * n * args.steps
        rows.append((n, cells / t_ours / 1e6, cells / t_fs / 1e6, t_fs / t_ours, rel, corr, float(b.mean())))
        print(f"{n}^2 done", flush=True)
    print()
    print(f"stream power, {args.steps} steps of {DT:g} years, K={K:g} m={M} n={N} U={UPLIFT * 1000:g} mm/year")
    print(f"{'grid':>6} {'ours Mcell-steps/s':>19} {'fastscapelib':>13} {'ratio':>6} {'erosion rel RMS diff':>21} "
          f"{'correlation':>11} {'mean erosion m':>15}")
    for n, o, f, ratio, rel, corr, mean in rows:
        print(f"{n:6d} {o:19.2f} {f:13.2f} {ratio:6.2f} {rel:21.4f} {corr:11.4f} {mean:15.2f}")


if __name__ == "__main__":
    main()
