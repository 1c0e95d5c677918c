"""Benchmark of the hydrology kernels against their peers (not part of `make test`).

    python -m bench.hydrology            # 1024^2 and 2048^2
    python -m bench.hydrology --full     # 8192^2 too (about 256 MB per float32 grid)
    python -m bench.hydrology --quick    # 512^2 and 1024^2
    python -m bench.hydrology --sizes 2048 --no-eroded --peers-only   # the peers table alone
    python -m bench.hydrology --erode-max 4096   # erode 4096^2 too (slow)

DEMs: stages.heightmap.stage.heights(HeightmapParams(resolution=n), seed) at
the default world's size (8192 m) ("raw"), and the same DEM eroded by the
erosion stage's run (through a RunContext) with the default world's settings
("eroded"). Eroding 4096^2 takes about 40 minutes on 2 cores, so by default
DEMs above --erode-max (1024) are eroded at 1024^2 and resampled by cubic
spline ("eroded1024up"); the erosion time is printed, not in the table.

For each DEM it times, best of --repeat at every size (after a warm-up on a small grid that
builds our programs and numba-compiles pysheds), host arrays in and out:
- the peers table: fill (plain Priority-Flood, no epsilon) and D8
  accumulation, ours and richdem-fork's, topotoolbox's and pysheds', on the
  same arrays, peers single-threaded as they come, with Mcell/s and ours /
  fastest peer (speed). Ours gets the cell kinds (computed once per world,
  not timed); the peers find their edges themselves. Fills: richdem
  FillDepressions(epsilon=False), topotoolbox GridObject.fillsinks (hybrid),
  pysheds sGrid.fill_depressions (float64, cast back), each checked bit for
  bit against ours. Accumulation of our D8 directions (from our epsilon
  fill), converted to each peer's encoding outside the timing: richdem
  FlowAccumFromProps of D8 proportions (the fork's flow_accumulation_from_d8
  result cannot be read back into numpy), topotoolbox's edge set + tsort +
  traversal (what FlowObject and flow_accumulation run), pysheds
  sGrid.accumulation; each compared cell by cell with ours;
- flowdir: D8 on the same filled DEM (ours on the epsilon-filled surface,
  which pysheds gets too, so the outputs are comparable), with the agreement
  fraction;
- breaching (no peer) against our pure-Python reference, with a bit-exactness check.
Needs `pip install -e .[bench]`; pysheds 0.5 calls np.in1d, shimmed.
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


def best_of_cpu(fn, repeat):
    """(best wall seconds, best CPU seconds of this process, all threads, the
    device's included on a CPU runtime, result): on a shared machine the CPU
    time shows the work apart from what other processes take."""
    best, cpu, out = float("inf"), float("inf"), None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return best, cpu, out


def dem(n: int, seed: int = 20261123) -> np.ndarray:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.heightmap.stage import HeightmapParams, heights

    h, _ = heights(cl_env, HeightmapParams(resolution=n), seed)
    return h


class quiet:
    """Silence a peer's C++ progress bars and prints (file descriptors 1 and
    2) while it runs."""

    def __enter__(self):
        import os
        import sys

        sys.stdout.flush()
        sys.stderr.flush()
        self.saved = [os.dup(1), os.dup(2)]
        self.null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(self.null, 1)
        os.dup2(self.null, 2)

    def __exit__(self, *exc):
        import os
        import sys

        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(self.saved[0], 1)
        os.dup2(self.saved[1], 2)
        for fd in (*self.saved, self.null):
            os.close(fd)


# our D8 codes (N, NE, E, SE, S, SW, W, NW) in each peer's encoding: richdem's
# neighbour numbers (1 W, 2 NW, 3 N, ... 8 SW), topotoolbox's direction bits
# on a C-order grid (found by routing a cone), pysheds' ESRI codes
RD_DIR = np.array([3, 4, 5, 6, 7, 8, 1, 2])
TT_DIR = np.array([4, 2, 1, 128, 64, 32, 16, 8], np.uint8)
PS_DIR = np.array([64, 128, 1, 2, 4, 8, 16, 32])


def _rd(a, no_data):
    import richdem as rd

    out = rd.rdarray(a, no_data=no_data)
    out.geotransform = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0]
    return out


def _tt_grid(h, dx):
    import topotoolbox as tt

    g = tt.GridObject()
    g.z, g.cellsize = h, dx
    return g


def _ps_grid(h, dx):
    from affine import Affine
    from pysheds.sgrid import sGrid
    from pysheds.sview import ViewFinder

    np.in1d = getattr(np, "in1d", np.isin)  # pysheds 0.5 calls np.in1d
    vf = ViewFinder(affine=Affine(dx, 0, 0, 0, -dx, 0), shape=h.shape, nodata=np.nan)
    return sGrid(viewfinder=vf), vf


def peer_fills(h: np.ndarray, dx: float) -> dict:
    """Each peer's plain depression fill (no epsilon) of canonical float32
    heights, as a function returning float32 heights (host array in, out)."""
    import richdem as rd
    from pysheds.sview import Raster

    g, vf = _ps_grid(h, dx)
    tg = _tt_grid(h, dx)
    return {
        "richdem": lambda: np.asarray(rd.FillDepressions(_rd(h, -np.inf), epsilon=False)),
        "topotoolbox": lambda: np.asarray(tg.fillsinks().z),
        "pysheds": lambda: np.asarray(g.fill_depressions(Raster(h.astype(np.float64), viewfinder=vf))).astype(np.float32),
    }


def peer_accums(code: np.ndarray, dx: float) -> dict:
    """Each peer's D8 accumulation of our directions (converted to its
    encoding outside the timing): a function returning the cell counts."""
    import richdem as rd
    from pysheds.sview import Raster, ViewFinder
    from topotoolbox import _flow, _stream
    from topotoolbox.flow_object import EdgeSet

    cc = np.clip(code, 0, 7)
    flows = code >= 0
    r, c = np.nonzero(flows)
    props = np.full(code.shape + (9,), -1, np.float32)  # richdem's D8 proportions
    props[r, c, 0] = 0
    props[r, c, RD_DIR[code[r, c]]] = 1
    props = rd.rd3array(props, no_data=-1)
    props.geotransform = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0]
    del r, c
    tdir = np.where(flows, TT_DIR[cc], 0).astype(np.uint8)

    def topotoolbox():  # edge set, topological sort, traversal: its FlowObject + flow_accumulation
        scan = np.zeros(tdir.shape, np.int64)
        w = np.zeros(_flow.edgeset_scan(scan, tdir), np.float32)
        _flow.flow_routing_d8_weights(w)
        _, src, tgt, frac = EdgeSet(tdir, scan, w).tsort()
        acc = np.ones(tdir.shape, np.float32)
        _stream.traverse_down_f32_add_mul(acc, np.ones_like(frac), src, tgt)
        return acc

    g, vf = _ps_grid(code, dx)
    pdir = Raster(np.where(flows, PS_DIR[cc], 0).astype(np.int64),
                  viewfinder=ViewFinder(affine=vf.affine, shape=code.shape, nodata=0))
    return {
        "richdem": lambda: np.asarray(rd.FlowAccumFromProps(props)),
        "topotoolbox": topotoolbox,
        "pysheds": lambda: np.asarray(g.accumulation(pdir)),
    }


def _same(ours: np.ndarray, peer: np.ndarray, interior: np.ndarray) -> str:
    """'all' when equal on every cell, 'interior' when only off the edge
    cells, else the count of differing interior cells."""
    a, b = ours.astype(np.float64), np.asarray(peer, np.float64)
    if np.array_equal(a, b, equal_nan=True):
        return "equal on all cells"
    diff = int((a[interior] != b[interior]).sum())
    if diff == 0:
        return f"equal on interior cells ({int((a != b).sum())} edge cells differ)"
    return f"{diff} interior cells differ"


def peers_table(cl_env, h: np.ndarray, dx: float, repeat: int) -> list:
    """Fill and D8 accumulation, ours and each peer's, best of repeat on the
    same host arrays: rows (operation, implementation, seconds, check)."""
    from worldlib.flow import device as dev
    from worldlib.flow import reference as ref

    kind = ref.cell_kinds(h)  # ours takes the cell kinds (computed once per world)
    interior = kind == ref.INTERIOR
    rows = []
    t, c, F = best_of_cpu(lambda: dev.fill(cl_env, h, kind, False), repeat)
    rows.append(("fill", "ours", t, c, "-"))
    for name, fn in peer_fills(h, dx).items():
        with quiet():
            t, c, P = best_of_cpu(fn, repeat)
        rows.append(("fill", name, t, c, "bit-exact" if np.array_equal(F, P, equal_nan=True) else _same(F, P, interior)))
    del P
    code = dev.d8(cl_env, dev.fill(cl_env, h, kind, True), kind, dx)
    t, c, A = best_of_cpu(lambda: dev.accumulate(cl_env, code), repeat)
    rows.append(("accumulation", "ours", t, c, "-"))
    for name, fn in peer_accums(code, dx).items():
        with quiet():
            t, c, P = best_of_cpu(fn, repeat)
        rows.append(("accumulation", name, t, c, _same(A, P, interior)))
    return rows


def print_peers(results: list) -> None:
    """The peers table, and ours / fastest peer (speed ratio) per operation."""
    print(f"{'DEM':14s} {'operation':13s} {'implementation':14s} {'seconds':>9s} {'CPU s':>7s} {'Mcell/s':>9s}"
          "  check vs ours")
    for dem_name, cells, rows in results:
        for op in ("fill", "accumulation"):
            mine = [r for r in rows if r[0] == op]
            for _, impl, t, c, check in mine:
                print(f"{dem_name:14s} {op:13s} {impl:14s} {t:9.3f} {c:7.3f} {cells / t / 1e6:9.1f}  {check}")
            ours = mine[0]
            fast = min(mine[1:], key=lambda r: r[2])
            print(f"{dem_name:14s} {op:13s} {'ratio':14s} ours / fastest peer ({fast[1]}): {fast[2] / ours[2]:.2f}x "
                  f"in seconds, {fast[3] / ours[3]:.2f}x in CPU time")


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
    ap.add_argument("--full", action="store_true", help="8192^2 too (256 MB per float32 grid)")
    ap.add_argument("--sizes", type=int, nargs="*")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--erode-max", type=int, default=1024,
                    help="largest size eroded by the erosion stage (4096^2 takes ~40 min on 2 cores); larger "
                    "DEMs are eroded at this size and resampled")
    ap.add_argument("--no-eroded", action="store_true")
    ap.add_argument("--peers-only", action="store_true", help="only the fill and accumulation peers table")
    ap.add_argument("--breach-ref-max", type=int, default=1024,
                    help="largest size at which the pure-Python breaching reference is timed (4096^2: ~80 s)")
    args = ap.parse_args()
    sizes = args.sizes or ([512, 1024] if args.quick else [1024, 2048] + ([8192] if args.full else []))

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

    rows, breaches, peers = [], [], []
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
            peers.append((f"{n}^2 {label}", cells, peers_table(cl_env, h, dx, r)))
            if args.peers_only:
                continue
            R = dev.fill(cl_env, h, kind, True)
            R64 = Raster(R.astype(np.float64), viewfinder=vf)
            t_ours_fd, code = best_of(lambda: dev.d8(cl_env, R, kind, dx), r)
            t_ps_fd, pfd = best_of(lambda: g.flowdir(R64), r)
            inter = kind == ref.INTERIOR
            agree = float((np.asarray(pfd)[inter] == dirmap[code[inter]]).mean())
            # breaching has no pysheds counterpart: the serial kernel against the Python reference
            t_ours_br, B = best_of(lambda: dev.breach(cl_env, h, kind), r)
            if n <= args.breach_ref_max:
                t_ref_br, RB = best_of(lambda: ref.breach(h, kind), 1)
                breaches.append((f"{n}^2 {label}", cells / t_ours_br / 1e6, cells / t_ref_br / 1e6,
                                 t_ref_br / t_ours_br, bool(np.array_equal(B, RB, equal_nan=True))))
            else:
                breaches.append((f"{n}^2 {label}", cells / t_ours_br / 1e6, float("nan"), float("nan"), None))
            rows.append((f"{n}^2 {label}", "flowdir", cells / t_ours_fd / 1e6, cells / t_ps_fd / 1e6,
                         t_ps_fd / t_ours_fd, f"agree={agree:.6f}"))
            print(f"{n}^2 {label}: done", flush=True)

    print()
    print_peers(peers)
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
