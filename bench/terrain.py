"""Terrain statistics against run time, for each knob of geological time
(not part of `make test`).

    python -m bench.terrain                          # the default world at 1024^2, every routing
    python -m bench.terrain --sizes 512 2048 --variants mfd
    python -m bench.terrain --steps 5 10 25 --variants mfd

The default world's heightmap at n^2 over 8192 m (bench.hydrology.dem), eroded
by stages/erosion/stream_power.run with the default.toml parameters of
geological time; each variant changes one knob (routing, flat routing, steps).
The statistics are pipeline/terrain_stats.terrain_statistics on the result,
with the hydrology stage's routing (complete breaching, Priority-Flood+epsilon,
D8) and its default channel threshold (1e5 m^2): the numbers the bake writes
to the hydrology stage's stats.json (there after the talus rule and the storm
too). "noise" is the uneroded heightmap; "local" is grid_anisotropy_local (each grid
wedge against its flanks: grid marks, not a landform trend near a grid direction). Targets of issue 16: anisotropy
<= 1.1, depressions <= 5 %, Strahler >= 4, theta 0.35 .. 0.65, Hack 0.5 .. 0.65.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

DEFAULT = dict(years=2.0e6, dt_years=2.0e5, k=2.0e-5, m=0.45, n_exp=1.0, uplift_m_per_year=5.0e-4,
               routing="mfd", diffusivity_m2_per_year=0.01, mfd_exponent=1.1, flat_routing="distance",
               fill_lakes=True)
VARIANTS = {
    "noise": None,
    "d8": dict(routing="d8", flat_routing="epsilon", fill_lakes=False),
    "rho8": dict(routing="rho8", flat_routing="epsilon", fill_lakes=False, breach=True),
    "mfd-epsilon-flats": dict(flat_routing="epsilon"),
    "mfd-plain-slope": dict(mfd_isotropic=False),  # without the isotropy scale of the incision (mfd_isotropy)
    "mfd": {},
}
from stages.hydrology.stage import CHANNEL_HEAD_AREA_M2 as CHANNEL_AREA_M2  # the hydrology stage's default


def statistics(h: np.ndarray, dx: float) -> dict:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.terrain.stats import terrain_statistics
    from worldlib.flow import device as flow
    from worldlib.flow import reference as ref

    h32 = ref.canonical(h.astype(np.float32))
    kind = ref.cell_kinds(h32)
    filled = flow.fill(cl_env, h32, kind, eps=False)
    routed = flow.fill(cl_env, flow.breach(cl_env, h32, kind), kind, eps=True)
    code = flow.d8(cl_env, routed, kind, dx)
    area = flow.accumulate(cl_env, code).astype(np.float64) * dx * dx
    return terrain_statistics(h32, filled, code, area, dx, CHANNEL_AREA_M2)


def main() -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="*", default=[1024])
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS))
    ap.add_argument("--steps", type=int, nargs="*", default=[10], help="geological steps over the 2e6 years")
    args = ap.parse_args()
    from bench.hydrology import dem
    from pipeline.opencl import get_cl
    from stages.erosion import stream_power as sp

    print(f"device: {get_cl().fingerprint}")
    rows = []
    for n in args.sizes:
        dx = 8192.0 / n
        h0 = dem(n).astype(np.float64)
        for name in args.variants:
            for steps in (args.steps if VARIANTS[name] is not None else [0]):
                t0, c0 = time.perf_counter(), time.process_time()
                if VARIANTS[name] is None:
                    h = h0
                else:
                    kw = {**DEFAULT, **VARIANTS[name], "dt_years": DEFAULT["years"] / steps}
                    h = sp.run(cl_env, h0, dx, **kw).height
                seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
                st = statistics(h, dx)
                rows.append((n, name, steps, seconds, cpu, st))
                print(f"{n}^2 {name} {steps} steps: {seconds:.1f} s wall, {cpu:.1f} s CPU", flush=True)
    print()
    print(f"{'grid':>6} {'variant':>18} {'steps':>5} {'wall s':>7} {'CPU s':>6} {'aniso':>6} {'local':>6} {'depr %':>6} {'Strahler':>8} "
          f"{'Hack':>5} {'theta':>6} {'Dd /km':>6} {'HI':>5}")
    for n, name, steps, seconds, cpu, st in rows:
        print(f"{n:6d} {name:>18} {steps:5d} {seconds:7.1f} {cpu:6.1f} {st['grid_anisotropy']:6.3f} {st['grid_anisotropy_local']:6.3f} "
              f"{100 * st['depression_area_fraction']:6.2f} {st['strahler_order_max']:8d} {st['hack_exponent']:5.2f} "
              f"{st['concavity_theta']:6.2f} {st['drainage_density_per_km']:6.2f} {st['hypsometric_integral']:5.2f}")


if __name__ == "__main__":
    main()
