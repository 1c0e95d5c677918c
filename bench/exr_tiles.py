"""Grid EXR I/O: scanline (the engine's format before tiling) against tiled
(pipeline.exr, file tiles of exr.TILE), one run each (not part of `make test`).

    python -m bench.exr_tiles            # 4096^2, one channel
    python -m bench.exr_tiles --n 2048

The map: a smooth float32 terrain-like field (a sum of sine octaves, metres)
of `--n` cells a side, one channel, as a function of the cell's global
index, so a tile can be made on its own. Printed, wall seconds of one run:
writes (scanline whole; tiled whole; tiled window by window in world tiles
of 1024^2 shuffled; tiled by rows of file tiles), reads (whole; one
1024^2 window; every 1024^2 window), file sizes, and the peak RSS of child
processes that write the map tile by tile (each tile made on the fly, in
order and last tile first) against one that holds the whole map and one
that writes a single tile (the imports and libraries every process pays).
Every tiled file is checked byte for byte against the whole write and every
read against the map.
"""
from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OCTAVES = [(0.0011, 0.0007, 400.0), (0.0031, 0.0043, 120.0), (0.011, 0.009, 35.0), (0.037, 0.041, 8.0),
           (0.13, 0.11, 1.5), (0.41, 0.37, 0.3)]


def terrain(r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
    """The field on cells [r0, r0 + rows) x [c0, c0 + cols)."""
    r = np.arange(r0, r0 + rows, dtype=np.float64)[:, None]
    c = np.arange(c0, c0 + cols, dtype=np.float64)[None, :]
    h = np.zeros((rows, cols))
    for i, (fr, fc, amp) in enumerate(OCTAVES):
        h += amp * np.sin(fr * r + 1.7 * i) * np.cos(fc * c + 0.3 * i + 0.001 * r)
    return h.astype(np.float32)


def write_scanline(path: Path, data: np.ndarray) -> None:
    """A grid as the engine wrote it before tiling."""
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(data.shape[1], data.shape[0], 1, oiio.FLOAT)
    spec.channelnames = ("height",)
    spec.attribute("compression", "zip")
    spec.attribute("worldbake:cell_size_m", 1.0)
    spec.attribute("worldbake:origin_m", json.dumps([0.0, 0.0]))
    spec.attribute("DateTime", "")
    out = oiio.ImageOutput.create(str(path))
    if not (out.open(str(path), spec) and out.write_image(data[:, :, None]) and out.close()):
        raise OSError(f"cannot write {path}")


def clock(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t, out


def child(n: int, mode: str, path: str) -> None:
    """Write the map in one way and print this process's peak RSS (MB)."""
    from pipeline import exr
    from pipeline.grid import Grid

    t = exr.TILE
    tiles = [(r, c) for r in range(0, n, t) for c in range(0, n, t)]
    if mode == "whole":  # the map in memory, made by rows of tiles
        data = np.empty((n, n), np.float32)
        for r in range(0, n, t):
            data[r:r + t] = terrain(r, 0, min(t, n - r), n)
        exr.write_grid(path, Grid(data, 1.0))
    elif mode == "baseline":  # the imports, one tile made and written: what every mode pays
        exr.write_grid(path, Grid(terrain(0, 0, t, t), 1.0))
    else:
        with exr.GridWriter(path, (n, n), ("height",), 1.0) as out:
            for r, c in tiles if mode == "tiles in order" else tiles[::-1]:
                out.write_window(r, c, terrain(r, c, t, t))
    # VmHWM, not getrusage: Linux carries ru_maxrss over exec from the forking parent
    hwm = next(line for line in Path("/proc/self/status").read_text().splitlines() if line.startswith("VmHWM:"))
    print(int(hwm.split()[1]) / 1024)


def peak_rss(n: int, mode: str, path: Path) -> float:
    out = subprocess.run([sys.executable, "-m", "bench.exr_tiles", "--n", str(n), "--child", mode, str(path)],
                         capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


def write_windows(path: Path, data: np.ndarray, order, rows: int, cols: int) -> None:
    from pipeline import exr

    with exr.GridWriter(path, data.shape, ("height",), 1.0) as out:
        for r, c in order:
            out.write_window(r, c, data[r:r + rows, c:c + cols])


def writes(n: int, data: np.ndarray, work: Path) -> None:
    from pipeline import exr
    from pipeline.grid import Grid

    w = min(1024, n)
    worlds = [(r, c) for r in range(0, n, w) for c in range(0, n, w)]
    random.Random(1).shuffle(worlds)
    rows = [(r, 0) for r in range(0, n, exr.TILE)]
    runs = [("scanline whole (before)", "scanline.exr", write_scanline, (data,)),
            ("tiled whole (write_grid)", "tiled.exr", exr.write_grid, (Grid(data, 1.0),)),
            (f"tiled, {w}^2 windows shuffled", "windows.exr", write_windows, (data, worlds, w, w)),
            (f"tiled, rows of {exr.TILE}-cell tiles", "rows.exr", write_windows, (data, rows, exr.TILE, n))]
    print(f"{'write':40s} {'s':>7s} {'MB':>8s}")
    for label, name, fn, args in runs:
        s, _ = clock(fn, work / name, *args)
        print(f"{label:40s} {s:7.3f} {(work / name).stat().st_size / 1e6:8.2f}")
    same = all((work / f).read_bytes() == (work / "tiled.exr").read_bytes() for f in ("windows.exr", "rows.exr"))
    print(f"tiled files byte-identical: {same}")


def reads(n: int, data: np.ndarray, work: Path) -> None:
    from pipeline import exr

    w = min(1024, n)
    print(f"{'read':40s} {'scanline s':>10s} {'tiled s':>8s}")
    for label, fn in [("whole (read_grid)", lambda p: [exr.read_grid(p)]),
                      (f"one {w}^2 window in the middle", lambda p: [exr.read_window(p, n // 2, n // 2 - w // 2,
                                                                                       min(w, n - n // 2), w)]),
                      (f"every {w}^2 window", lambda p: [exr.read_window(p, r, c, w, w)
                                                         for r in range(0, n, w) for c in range(0, n, w)])]:
        secs = []
        for name in ("scanline.exr", "tiled.exr"):
            s, grids = clock(fn, work / name)
            secs.append(s)
            for g in grids:
                c0 = round(g.origin_m[0])
                r0 = round(g.origin_m[1])
                assert np.array_equal(g.data, data[r0:r0 + g.shape[0], c0:c0 + g.shape[1]]), (name, label)
        print(f"{label:40s} {secs[0]:10.3f} {secs[1]:8.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--child", nargs=2, metavar=("MODE", "PATH"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.n, *args.child)
        return
    n = args.n
    with tempfile.TemporaryDirectory(dir=Path.cwd() / "build" if (Path.cwd() / "build").is_dir() else None) as tmp:
        work = Path(tmp)
        data = terrain(0, 0, n, n)
        print(f"{n}^2 cells, one float32 channel ({data.nbytes / 1e6:.0f} MB in memory)")
        writes(n, data, work)
        reads(n, data, work)
        del data
        print(f"{'peak RSS of a writer process':40s} {'MB':>8s}")
        for mode in ("baseline", "whole", "tiles in order", "tiles last first"):
            print(f"{mode:40s} {peak_rss(n, mode, work / f'{mode}.exr'):8.0f}")
        same = (work / "tiles in order.exr").read_bytes() == (work / "tiles last first.exr").read_bytes() \
            == (work / "whole.exr").read_bytes()
        print(f"child files byte-identical: {same}")


if __name__ == "__main__":
    main()
