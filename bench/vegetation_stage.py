"""One stage of a world config, run again from its stored inputs, with its
wall and process CPU seconds (not part of `make test`):

    python -m bench.vegetation_stage vegetation      # configs/default.toml
    python -m bench.vegetation_stage plants --set vegetation.years=50

The stages before it must be in the store (bake the world once); the stage
itself is run into its own key's folder again (an existing one is replaced),
exactly as a bake runs it. Prints the stage's wall and CPU seconds (the
OpenCL runtime's threads included), its peak memory, and the per-phase
timings its metrics report (vegetation: wall and CPU per phase; plants: per
species mesh, textures, LOD chain and look measures).
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from pipeline.bake import _progress_printer, key_step, plan_bake, run_step
    from pipeline.config import load_config
    from pipeline.graph import build_graph
    from pipeline.registry import all_stages
    from pipeline.store import Store

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stage")
    ap.add_argument("--config", default="configs/default.toml")
    ap.add_argument("--build", default="build")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args(argv)
    stages = all_stages()
    graph = build_graph(stages)
    config = load_config(Path(a.config), stages, project_root=Path("."), sets=a.set)
    store = Store(Path(a.build))
    keys: dict[str, str] = {}
    for ps in plan_bake(graph, config):
        ks = key_step(ps, store, graph, keys)
        if ps.stage.name == a.stage:
            shutil.rmtree(store.folder(a.stage, ks.key), ignore_errors=True)
            c0, t0 = time.process_time(), time.perf_counter()
            m = run_step(store, ks, config, graph, _progress_printer(a.stage))
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
            print(f"{a.stage} {ks.key}: wall {wall:.2f} s, CPU {cpu:.2f} s (this process; worker processes not "
                  f"counted), peak {peak:.2f} GB")
            metrics = m["metrics"]
            if "timings" in metrics:
                print(json.dumps(metrics["timings"]))
            for name, s in metrics.get("species", {}).items():
                lod = sum(e.get("simplify_seconds", 0.0) for e in s.get("lods", []))
                print(f"  {name:14s} total {s.get('seconds_total', 0):6.2f} s  LOD chain {lod:6.2f} s  textures "
                      f"{s.get('seconds_foliage_textures', 0):5.2f} s  looks {s.get('seconds_look_measures', 0):5.2f} s")
            return 0
        if not store.has(ps.stage.name, ks.key):
            print(f"{ps.stage.name} {ks.key} is not in the store: bake the world first", file=sys.stderr)
            return 1
        keys[ps.stage.name] = ks.key
    print(f"no stage {a.stage!r} in the plan", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
