"""Complete breaching that tiles (worldlib.flow.drainage_breach) against
Lindsay's over the whole map (device.breach, one serial work-item; the
hydrology's breaching before), one run each (not part of `make test`).

    python -m bench.breach                       # 1024^2 raw and smoothed, tiles of 256 and 512
    python -m bench.breach --n 2048 --tiles 512 1024

DEMs: the heightmap stage's raw terrain at the default world's settings and
`--n` cells a side (rough: a third of its cells in depressions), and the
same smoothed by 16 passes of a 3x3 mean (as many depression cells, with
smooth floors: fewer cells carved). Per DEM: the depression cells; wall seconds of
Lindsay's kernel and of ours (the flood on the depression cells, the
carves), their ratio; the carved volume and cells of each and the volume
ratio; then per tile size the three tiled passes in one process (the tiles
one after another), their time against the untiled carve and the bitwise
check. Both surfaces are epsilon-filled after and checked to drain.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def _clock(f, *args):
    t0 = time.perf_counter()
    out = f(*args)
    return out, time.perf_counter() - t0


def _smoothed(h: np.ndarray, passes: int) -> np.ndarray:
    out = h.astype(np.float64)
    for _ in range(passes):
        p = np.pad(out, 1, mode="edge")
        out = sum(p[1 + dr:1 + dr + h.shape[0], 1 + dc:1 + dc + h.shape[1]]
                  for dr in (-1, 0, 1) for dc in (-1, 0, 1)) / 9.0
    return out.astype(np.float32)


def main() -> None:
    from pipeline.opencl import get_cl
    from stages.heightmap.stage import HeightmapParams, heights
    from worldlib.flow import device as dev
    from worldlib.flow import drainage_breach as db
    from worldlib.flow import reference as ref

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--tiles", type=int, nargs="+", default=[256, 512])
    args = ap.parse_args()
    env = get_cl()
    print(f"device: {env.fingerprint}")
    raw, _ = heights(env, HeightmapParams(resolution=args.n), 20261123)
    dx = 8192.0 / args.n
    dev.breach(env, ref.canonical(raw[:64, :64]), ref.cell_kinds(ref.canonical(raw[:64, :64])))  # warm-up
    for name, dem in (("raw", raw), ("smoothed", _smoothed(raw, 16))):
        h = ref.canonical(dem)
        kind = ref.cell_kinds(h)
        filled = dev.fill(env, h, kind, eps=False)
        lindsay, t_l = _clock(dev.breach, env, h, kind)
        t0 = time.perf_counter()
        surface = dev.fill(env, h, kind, eps=True)
        drainage = dev.d8(env, surface, kind, dx)
        t1 = time.perf_counter()
        paths, t_paths = _clock(db.carve_codes, h, filled, surface, drainage)
        ours, t_carve = _clock(db.breach, h, kind, paths)
        for b in (lindsay, ours):
            assert not (dev.d8(env, dev.fill(env, b, kind, eps=True), kind, dx) == ref.PIT).any()
        carved = lambda b: (float((h - b).astype(np.float64).sum()) * dx * dx, int((b < h).sum()))
        (v_l, c_l), (v_o, c_o) = carved(lindsay), carved(ours)
        ours_s = t_paths + t_carve
        print(f"{name} {args.n}^2: {int((filled > h).sum()):,} depression cells; Lindsay {t_l:.2f} s, ours "
              f"{ours_s:.2f} s (floods {t_paths:.2f}, carves {t_carve:.2f}; the drainage's fill and D8 "
              f"{t1 - t0:.2f} s more) = {ours_s / t_l:.2f}x; carved {v_l:.4g} m^3 in {c_l:,} cells vs ours "
              f"{v_o:.4g} m^3 in {c_o:,} cells = {v_o / v_l:.3f}x the volume")
        for tile in args.tiles:
            tiled, t_t = _clock(db.tiled_breach, h, paths, tile)
            same = "equal" if np.array_equal(tiled.view(np.int32), ours.view(np.int32)) else "DIFFERENT"
            print(f"  tiles of {tile}: three passes {t_t:.2f} s = {t_t / t_carve:.2f}x the untiled carve, bitwise {same}")


if __name__ == "__main__":
    main()
