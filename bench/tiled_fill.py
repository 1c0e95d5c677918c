"""The tiled fill (worldlib.flow.tiled_fill, Barnes 2016) against the
untiled device fill on the same DEM, one run each (not part of `make test`).

    python -m bench.tiled_fill                 # 2048^2, tiles of 256, 512, 1024
    python -m bench.tiled_fill --n 1024 --tiles 512 --eps-tile 0

DEM: the heightmap stage's raw terrain at the default world's settings and
`--n` cells a side. Times are wall seconds of one run on one process (the
tiles run one after another), after a warm-up that builds the programs:
pass 1 (per-tile device fill, then watersheds and spill edges), pass 2 (the
perimeter graph), pass 3 (per-tile max), and the ratio tiled / untiled.
Then the epsilon fill (the routing surface) untiled and by tiled rounds
(tiled_fill_eps). Every tiled result is checked bit for bit against the
untiled one.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def timed_tiled_fill(h: np.ndarray, tile: int, env) -> tuple[np.ndarray, dict]:
    """tiled_fill's three passes with a clock on each."""
    from worldlib.flow import tiled_fill as tf

    t = {"pass1_s": 0.0, "pass2_s": 0.0, "pass3_s": 0.0}
    padded = np.pad(h, 1, constant_values=np.nan)
    grid = tf.tile_slices(h.shape, tile)
    t0 = time.perf_counter()
    tiles = [[tf.fill_tile(h[rs, cs], tf.tile_kind(padded[rs.start:rs.stop + 2, cs.start:cs.stop + 2]), env)
              for rs, cs in row] for row in grid]
    t1 = time.perf_counter()
    levels = tf.solve_levels([[x.perimeter for x in row] for row in tiles])
    t2 = time.perf_counter()
    out = np.empty(h.shape, np.float32)
    for row, trow, lrow in zip(grid, tiles, levels):
        for (rs, cs), x, lv in zip(row, trow, lrow):
            out[rs, cs] = tf.finish_tile(x.filled, x.labels, lv)
    t3 = time.perf_counter()
    t.update(pass1_s=t1 - t0, pass2_s=t2 - t1, pass3_s=t3 - t2, total_s=t3 - t0,
             nodes=1 + sum(x.perimeter.n_labels for row in tiles for x in row))
    return out, t


def main() -> None:
    from pipeline.opencl import get_cl
    from stages.heightmap.stage import HeightmapParams, heights
    from worldlib.flow import device as dev
    from worldlib.flow import reference as ref
    from worldlib.flow import tiled_fill as tf

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2048)
    ap.add_argument("--tiles", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--eps-tile", type=int, default=512, help="tile of the epsilon fill's rounds (0: skip)")
    args = ap.parse_args()
    env = get_cl()  # the engine's choice of device
    print(f"device: {env.fingerprint}")
    raw, _ = heights(env, HeightmapParams(resolution=args.n), 20261123)
    h = ref.canonical(raw)
    kind = ref.cell_kinds(h)
    tf.tiled_fill(h[:64, :64], 32, env)  # warm-up: builds the programs
    t0 = time.perf_counter()
    want = dev.fill(env, h, kind, eps=False)
    untiled = time.perf_counter() - t0
    print(f"{args.n}^2, depression cells {int((want > h).sum())}; untiled device fill {untiled:.2f} s")
    print(f"{'tile':>6} {'tiles':>6} {'nodes':>8} {'pass1 s':>8} {'pass2 s':>8} {'pass3 s':>8} {'total s':>8} "
          f"{'/untiled':>8}  bitwise")
    for tile in args.tiles:
        got, t = timed_tiled_fill(h, tile, env)
        same = np.array_equal(got.view(np.uint32), want.view(np.uint32))
        n_tiles = len(tf.tile_slices(h.shape, tile)) * len(tf.tile_slices(h.shape, tile)[0])
        print(f"{tile:>6} {n_tiles:>6} {t['nodes']:>8} {t['pass1_s']:>8.2f} {t['pass2_s']:>8.2f} {t['pass3_s']:>8.2f} "
              f"{t['total_s']:>8.2f} {t['total_s'] / untiled:>8.2f}  {'equal' if same else 'DIFFERENT'}")
    if args.eps_tile:
        epsilon(env, h, kind, args.eps_tile)


def epsilon(env, h: np.ndarray, kind: np.ndarray, tile: int) -> None:
    """The epsilon fill (the routing surface): untiled vs tiled rounds."""
    from worldlib.flow import device as dev
    from worldlib.flow import tiled_fill as tf

    t0 = time.perf_counter()
    want = dev.fill(env, h, kind, eps=True)
    t1 = time.perf_counter()
    got, rounds = tf.tiled_fill_eps(h, tile, env)
    t2 = time.perf_counter()
    same = np.array_equal(got.view(np.uint32), want.view(np.uint32))
    print(f"epsilon fill: untiled {t1 - t0:.2f} s; tiles of {tile}: {rounds} rounds, {t2 - t1:.2f} s "
          f"({(t2 - t1) / (t1 - t0):.2f}x), {'equal' if same else 'DIFFERENT'}")


if __name__ == "__main__":
    main()
