"""Tiled D8 directions and accumulation (worldlib.flow.tiled_accum, Barnes
2017) against the untiled device calls on the same routing surface, one run
each (not part of `make test`).

    python -m bench.tiled_accum                 # 2048^2, tiles of 256, 512, 1024
    python -m bench.tiled_accum --n 1024 --tiles 512

DEM: the heightmap stage's raw terrain at the default world's settings and
`--n` cells a side, epsilon-filled (the hydrology stage's routing surface).
Times are wall seconds of one run in one process (the tiles run one after
another), after a warm-up that builds the programs: d8 (per tile with its
halo), accumulation of cell counts in its three passes, the quantized
runoff (two per-tile passes for the scale, then the weighted accumulation),
and each total's ratio tiled / untiled. Every tiled result is checked bit
for bit against the untiled one.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def timed_accumulate(code: np.ndarray, tile: int, weights, env) -> tuple[np.ndarray, dict]:
    """tiled_accumulate's three passes with a clock on each."""
    from worldlib.flow import tiled_accum as ta
    from worldlib.flow.tiled_fill import tile_slices

    grid = tile_slices(code.shape, tile)
    wt = (lambda rs, cs: None) if weights is None else (lambda rs, cs: weights[rs, cs])
    t0 = time.perf_counter()
    perims = [[ta.accumulate_tile(code[rs, cs], (rs.start, cs.start), wt(rs, cs), env) for rs, cs in row]
              for row in grid]
    t1 = time.perf_counter()
    inflow = ta.solve_inflow(perims)
    t2 = time.perf_counter()
    out = np.empty(code.shape, np.uint32 if weights is None else np.int64)
    for row, irow in zip(grid, inflow):
        for (rs, cs), fin in zip(row, irow):
            out[rs, cs] = ta.finish_tile(code[rs, cs], fin, wt(rs, cs), env)
    t3 = time.perf_counter()
    nodes = sum(p.code.size for row in perims for p in row)
    return out, {"pass1_s": t1 - t0, "pass2_s": t2 - t1, "pass3_s": t3 - t2, "total_s": t3 - t0, "nodes": nodes}


def _clock(f, *args):
    t0 = time.perf_counter()
    out = f(*args)
    return out, time.perf_counter() - t0


def _same(a, b) -> str:
    return "equal" if np.array_equal(a, b) else "DIFFERENT"


def main() -> None:
    from pipeline.opencl import get_cl
    from stages.heightmap.stage import HeightmapParams, heights
    from worldlib.flow import device as dev
    from worldlib.flow import reference as ref
    from worldlib.flow import tiled_accum as ta

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2048)
    ap.add_argument("--tiles", type=int, nargs="+", default=[256, 512, 1024])
    args = ap.parse_args()
    env = get_cl()  # the engine's choice of device
    print(f"device: {env.fingerprint}")
    raw, _ = heights(env, HeightmapParams(resolution=args.n), 20261123)
    h = ref.canonical(raw)
    kind = ref.cell_kinds(h)
    R = dev.fill(env, h, kind, eps=True)
    dx = 8.0
    runoff = np.where(kind != ref.NODATA, 0.5 + 0.3 * np.cos(np.arange(h.size) * 1e-3).reshape(h.shape), 0.0) * dx * dx
    ta.tiled_accumulate(dev.d8(env, R[:64, :64], kind[:64, :64], dx), 32, None, env)  # warm-up: builds the programs
    dev.accumulate(env, dev.d8(env, R[:64, :64], kind[:64, :64], dx), np.ones((64, 64), np.int64))
    code, t_d8 = _clock(dev.d8, env, R, kind, dx)
    counts, t_acc = _clock(dev.accumulate, env, code)
    (q, scale), t_q = _clock(dev.quantize, runoff)
    qacc, t_qacc = _clock(dev.accumulate, env, code, q)
    print(f"{args.n}^2 untiled: d8 {t_d8:.2f} s, accumulate {t_acc:.2f} s, quantize {t_q:.2f} s, "
          f"weighted accumulate {t_qacc:.2f} s")
    print(f"{'tile':>6} {'nodes':>8} {'d8 s':>6} {'/untl':>6} | {'pass1':>6} {'pass2':>6} {'pass3':>6} {'acc s':>6} "
          f"{'/untl':>6} | {'quant s':>7} {'/untl':>6} | {'w.acc s':>7} {'/untl':>6}  bitwise")
    for tile in args.tiles:
        code_t, t1 = _clock(ta.tiled_d8, R, dx, tile, env)
        acc_t, t = timed_accumulate(code, tile, None, env)
        (q_t, scale_t), t3 = _clock(ta.tiled_quantize, runoff, tile)
        qacc_t, tw = timed_accumulate(code, tile, q_t, env)
        same = [_same(code_t, code), _same(acc_t, counts), _same(q_t, q) if scale_t == scale else "DIFFERENT",
                _same(qacc_t, qacc)]
        print(f"{tile:>6} {t['nodes']:>8} {t1:>6.2f} {t1 / t_d8:>6.2f} | {t['pass1_s']:>6.2f} {t['pass2_s']:>6.2f} "
              f"{t['pass3_s']:>6.2f} {t['total_s']:>6.2f} {t['total_s'] / t_acc:>6.2f} | {t3:>7.2f} {t3 / t_q:>6.2f} | "
              f"{tw['total_s']:>7.2f} {tw['total_s'] / t_qacc:>6.2f}  d8/acc/quantize/w.acc: {' '.join(same)}")


if __name__ == "__main__":
    main()
