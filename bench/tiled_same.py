"""Does a tiled bake write the untiled bake's files? (issue 28, item 1; not
part of `make test`, whose tests check the same on small worlds.)

    python -m bench.tiled_same                              # 2048^2, tiles of 512, on Dask
    python -m bench.tiled_same --size 1024 --tile 256 --executor local --set hydrology.depression=fill

Bakes the config twice into fresh build folders, untiled in this process and
with `[tiling] tile_cells` on the executor given, then compares every stage
the world uses: the keys (the tiling is in no key), and every file of each
run but its manifest (a run record), byte for byte. Prints per stage whether
it ran tiled (its passes) or whole, its seconds in each bake, and the files
equal; exit 1 when anything differs.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def bake(build: Path, config: str, sets: list[str], executor: str) -> tuple[dict[str, str], float]:
    shutil.rmtree(build, ignore_errors=True)
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", str(build), "bake", config, "--json", "--executor",
           executor, *[a for s in sets for a in ("--set", s)]]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env={**os.environ, "WORLDBAKE_REPORT": "0"})
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    steps = json.loads(proc.stdout)[0]["steps"]
    return {s["stage"]: s["key"] for s in steps}, time.perf_counter() - t0


def files(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != "manifest.json"}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="configs/default.toml")
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--executor", default="dask")
    ap.add_argument("--set", nargs="*", default=[], help="more config overrides")
    ap.add_argument("--build", type=Path, default=REPO / "build_tiled_same")
    args = ap.parse_args()
    sets = [f"heightmap.resolution={args.size}", *args.set]
    whole, t_whole = bake(args.build / "whole", args.config, sets, "local")
    print(f"untiled, local: {t_whole:.0f} s", flush=True)
    tiled, t_tiled = bake(args.build / "tiled", args.config, sets + [f"tiling.tile_cells={args.tile}"], args.executor)
    print(f"tiles of {args.tile}, {args.executor}: {t_tiled:.0f} s", flush=True)
    bad = 0
    print(f"\n{'stage':<15}{'how':<58}{'s whole':>9}{'s tiled':>9}  files")
    for stage, key in whole.items():
        if tiled.get(stage) != key:
            print(f"{stage:<15}keys differ: {key} / {tiled.get(stage)}")
            bad += 1
            continue
        a, b = (files(args.build / w / "artifacts" / stage / key) for w in ("whole", "tiled"))
        same = sum(1 for f in a if b.get(f) == a[f])
        bad += (same != len(a)) or set(a) != set(b)
        ma, mb = (json.loads((args.build / w / "artifacts" / stage / key / "manifest.json").read_text())
                  for w in ("whole", "tiled"))
        passes = mb["metrics"].get("tiling", {}).get("passes")
        how = (f"tiled: {len(passes)} passes, {sum(p['tiles'] for p in passes)} tile tasks"
               + (f" ({mb['metrics']['tiled_steps']})" if "tiled_steps" in mb["metrics"] else "")) if passes else "whole"
        print(f"{stage:<15}{how[:57]:<58}{ma['timings']['run_s']:>9.1f}{mb['timings']['run_s']:>9.1f}  "
              f"{same}/{len(a)} equal")
    print("\nALL EQUAL" if not bad else f"\n{bad} stages differ")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
