"""Every OpenCL device that passes the probe, side by side, in one run.

    python -m bench.devices            # kernels of each stage, then a whole default bake per device
    python -m bench.devices --quick    # smaller kernels, the bake at 512^2
    python -m bench.devices --no-bake  # kernels only

Part 1 times the main kernel of each stage in this process, rounds
interleaved across devices (device A, device B, A, B, ...) so that load from
other processes on a shared machine falls on both alike; the figure is the
median over rounds, and the ratio column is the first device's time over each
other's (above 1: that device is faster). Part 2 bakes configs/default.toml
into a fresh build folder per device with WORLDBAKE_CL_DEVICE set, devices
alternating, and prints each stage's seconds. The default order of CPU
runtimes in pipeline/opencl.py is chosen from these figures.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _finish():
    from pipeline.opencl import get_cl

    get_cl().queue.finish()


def heightmap_case(n: int):
    from stages.heightmap.stage import HeightmapParams, heights

    params = HeightmapParams(resolution=n)
    return f"heightmap fBm {n}^2", lambda: heights(_current(), params, 7)


def erosion_case(n: int, steps: int = 20):
    from stages.erosion.device import DeviceSim
    from stages.erosion.physics import step_constants
    from stages.erosion.reference import synthetic_world
    from stages.erosion.params import ErosionParams, physics_for

    size_m = 8192.0
    h = synthetic_world(n, size_m=size_m, relief_m=1200.0, seed=7)
    ph = physics_for(ErosionParams(), size_m / n)
    k = step_constants(ph, 0.5 * size_m / n / 20.0)
    sims = {}  # one simulation per device; the first call on a device (the warm-up) builds it

    def run():
        sim = sims.get(id(_current()))
        if sim is None:
            sim = sims[id(_current())] = DeviceSim(_current(), h, ph)
            sim.step(k)
            sim.finish()
        for _ in range(steps):
            sim.step(k)
        sim.finish()

    return f"erosion storm {n}^2 x {steps} steps", run


def _current():
    from pipeline.opencl import get_cl

    return get_cl()


def hydrology_case(n: int):
    from stages.erosion.reference import synthetic_world
    from worldlib.flow import device as dev
    from worldlib.flow import reference as ref

    h = ref.canonical(synthetic_world(n, size_m=8.0 * n, relief_m=1200.0, seed=3))
    kind = ref.cell_kinds(h)

    def run():
        filled = dev.fill(_current(), h, kind, eps=True)
        code = dev.d8(_current(), filled, kind, 8.0)
        dev.accumulate(_current(), code)

    return f"hydrology fill+d8+accumulate {n}^2", run


def vegetation_case(n: int):
    from stages.erosion.reference import synthetic_world
    from stages.vegetation import attributes, device
    from stages.vegetation.params import VegetationParams

    h = synthetic_world(n, size_m=8.0 * n, relief_m=1200.0, seed=5)
    params = VegetationParams()
    return f"vegetation attributes (slope, horizon sunlight) {n}^2", lambda: attributes.compute(h, 8.0, params, device.on(_current()))


def plants_case(n: int):
    from stages.plants import geometry
    from stages.plants import reference as ref

    rng = np.random.default_rng(1)
    ring = np.zeros((n, ref.RING), np.float32)
    ring[:, 0:3] = rng.normal(size=(n, 3)) * 5
    t = rng.normal(size=(n, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    nrm = np.cross(t, [0.0, 0.0, 1.0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
    ring[:, 3:6], ring[:, 6:9], ring[:, 9:12] = nrm, np.cross(t, nrm), t
    ring[:, 12] = rng.random(n) * 0.3
    ring[:, 14:] = rng.random((n, 6))
    sides = rng.integers(3, 17, n).astype(np.int32)
    return f"plants tube rings {n} rings", lambda: geometry.tube_rings(_current(), ring, sides)


def kernels(devices, quick: bool, rounds: int) -> list[dict]:
    from pipeline.opencl import use_device

    n = 512 if quick else 1024
    cases = [heightmap_case(n), erosion_case(256 if quick else 512), hydrology_case(n), vegetation_case(n // 2),
             plants_case(20000 if quick else 100000)]
    rows = []
    for title, run in cases:
        times = {c.index: [] for c in devices}
        for c in devices:  # warm: build the programs, first touch
            with use_device(c.device):
                run()
                _finish()
        for _ in range(rounds):
            for c in devices:
                with use_device(c.device):
                    t0 = time.perf_counter()
                    run()
                    _finish()
                    times[c.index].append(time.perf_counter() - t0)
        med = {k: statistics.median(v) for k, v in times.items()}
        rows.append({"case": title, "seconds": med})
        first = devices[0].index
        cells = "  ".join(f"{med[c.index] * 1e3:9.1f} ms" + ("" if c.index == first else f" ({med[first] / med[c.index]:.2f}x)")
                          for c in devices)
        print(f"  {title:<52} {cells}", flush=True)
    return rows


def bakes(devices, quick: bool) -> dict:
    sets = ["--set", "heightmap.resolution=512"] if quick else []
    per = {c.index: {} for c in devices}
    with tempfile.TemporaryDirectory(prefix="worldbake-devices-") as tmp:
        for c in devices:
            build = Path(tmp) / c.index.replace(":", "_")
            env = dict(os.environ, WORLDBAKE_CL_DEVICE=c.index)
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "pipeline.cli", "--build", str(build), "bake",
                                   "configs/default.toml", *sets, "--json"], cwd=REPO, env=env,
                                  capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                print(f"  bake on {c.label} failed ({proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}")
                continue
            steps = json.loads(proc.stdout)[0]["steps"]
            per[c.index] = {s["stage"]: s["seconds"] for s in steps} | {"whole bake (wall)": wall}
    stages = list(dict.fromkeys(k for d in per.values() for k in d))
    first = devices[0].index
    for stage in stages:
        cells = []
        for c in devices:
            t = per[c.index].get(stage)
            ratio = "" if c.index == first or t is None or per[first].get(stage) is None else f" ({per[first][stage] / max(t, 1e-9):.2f}x)"
            cells.append(f"{t:9.2f} s{ratio}" if t is not None else f"{'-':>11}")
        print(f"  {stage:<52} {'  '.join(cells)}", flush=True)
    return per


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-bake", action="store_true")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args(argv)

    from pipeline import opencl

    candidates, chosen = opencl.probe_all(stop_at_first=False)
    for c in candidates:
        print(f"{c.index} {c.label}: {'ok' if c.ok else 'FAILED ' + c.error}")
    devices = [c for c in candidates if c.ok]
    if not devices:
        sys.exit("no working OpenCL device")
    print(f"a bake would use {chosen.label}\n")
    head = "  ".join(f"{c.platform[:24]:>24}" for c in devices)
    print(f"  {'kernel (median of ' + str(args.rounds) + ' interleaved rounds)':<52} {head}")
    results = {"devices": [c.as_dict() for c in devices], "kernels": kernels(devices, args.quick, args.rounds)}
    if not args.no_bake:
        print(f"\n  {'default bake' + (' at 512^2' if args.quick else '') + ', seconds per stage':<52} {head}")
        results["bakes"] = bakes(devices, args.quick)
    out = REPO / "bench" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "devices.json").write_text(json.dumps(results, indent=2))
    print(f"\nwritten {out / 'devices.json'}")


if __name__ == "__main__":
    main()
