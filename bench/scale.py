"""Cost per cell of every stage whose work grows with the world's cells
(not part of `make test`).

    python -m bench.scale                         # 1024^2, 2048^2, 4096^2
    python -m bench.scale --full                  # and 8192^2
    python -m bench.scale --sizes 512 1024        # a quick look
    python -m bench.scale --set tiling.tile_cells=1024 --executor dask
    python -m bench.scale --stages heightmap hydrology --set tiling.tile_cells=1024 --set hydrology.depression=fill

The default world (8 km) baked at n^2 cells, so the cell shrinks as n grows.
Each scaling stage runs alone in a fresh `worldbake bake` process (outputs =
[stage]; the stages before it are cached from the previous run), so the
process's peak RSS (getrusage of the child) and its CPU time are that
stage's, plus the interpreter and the stage's reads. Prints, per stage and
size: wall and CPU seconds, peak RSS, and each per Mcell; then for every
stage the ratio of the largest size's cost per cell to the smallest's
(issue 28: within 1.5 from 1024^2 to 4096^2). The ratios are measured in
one run on one machine, so they hold while the load does not change much.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# stages whose work grows with the cells, in bake order; the others (plants, impostors, volumes) are per species
SCALING = ("heightmap", "erosion", "hydrology", "vegetation", "world")
# what the world needs besides them, baked (untimed) before it: the per-species assets and the forest sectors
BEFORE_WORLD = ("plants", "impostors", "volumes", "forest_volumes")


def run_alone(build: Path, stage: str | tuple, cells: int, extra: list[str]) -> dict:
    """One `worldbake bake` process whose only stage to run is `stage`:
    its wall and CPU seconds and peak RSS (os.wait4: this child's own, with
    the worker processes it waited for)."""
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", str(build), "bake", "configs/default.toml",
           "--set", f"heightmap.resolution={cells}", "--set", f"outputs={json.dumps([stage] if isinstance(stage, str) else list(stage))}", "--replace", *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{err[-2000:]}")
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "rss_gb": usage.ru_maxrss / 2 ** 20}


def table(results: dict[int, dict[str, dict]], stages: tuple[str, ...] = SCALING) -> str:
    rows = [f"{'stage':<11}{'cells':>7}{'wall s':>9}{'CPU s':>9}{'RSS GB':>8}{'wall s/Mc':>11}{'CPU s/Mc':>10}"
            f"{'RSS MB/Mc':>11}"]
    for stage in stages:
        for n, per_stage in results.items():
            r, mc = per_stage[stage], n * n / 1e6
            rows.append(f"{stage:<11}{n:>6}²{r['wall_s']:>9.1f}{r['cpu_s']:>9.1f}{r['rss_gb']:>8.2f}"
                        f"{r['wall_s'] / mc:>11.2f}{r['cpu_s'] / mc:>10.2f}{1024 * r['rss_gb'] / mc:>11.1f}")
    sizes = list(results)
    if len(sizes) > 1:
        lo, hi = sizes[0], sizes[-1]
        rows.append(f"\ncost per cell at {hi}² / at {lo}² (issue 28: at most 1.5 from 1024² to 4096²)")
        for stage in stages:
            a, b = results[lo][stage], results[hi][stage]
            ratio = lambda key: (b[key] / (hi * hi)) / max(a[key] / (lo * lo), 1e-12)
            rows.append(f"  {stage:<11} wall {ratio('wall_s'):5.2f}  CPU {ratio('cpu_s'):5.2f}")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    ap.add_argument("--full", action="store_true", help="also 8192^2")
    ap.add_argument("--build", type=Path, default=REPO / "build_scale")
    ap.add_argument("--set", nargs="*", action="extend", default=[], help="config overrides, e.g. tiling.tile_cells=1024")
    ap.add_argument("--executor", default=None, help="passed to worldbake bake (e.g. dask)")
    ap.add_argument("--stages", nargs="+", choices=SCALING, default=list(SCALING), help="the stages to time")
    args = ap.parse_args()
    stages = tuple(s for s in SCALING if s in args.stages)
    sizes = sorted(set(args.sizes + ([8192] if args.full else [])))
    extra = [a for kv in args.set for a in ("--set", kv)] + (["--executor", args.executor] if args.executor else [])
    results: dict[int, dict[str, dict]] = {}
    for n in sizes:
        results[n] = {}
        for stage in stages:
            if stage == "world":
                run_alone(args.build, BEFORE_WORLD, n, extra)
            results[n][stage] = r = run_alone(args.build, stage, n, extra)
            print(f"{n}² {stage}: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, peak RSS {r['rss_gb']:.2f} GB",
                  flush=True)
    print(table(results, stages))


if __name__ == "__main__":
    main()
