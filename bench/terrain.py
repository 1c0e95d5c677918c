"""Terrain and slope statistics against run time, for each knob of
geological time (not part of `make test`).

    python -m bench.terrain                              # the default world at 1024^2, every knob
    python -m bench.terrain --sizes 512 1024 2048 --variants default
    python -m bench.terrain --seed 7 --variants default no-landslide
    python -m bench.terrain --set critical_slope_deg=30 deposition_g=2   # change the default first

The default world's heightmap at n^2 over 8192 m (bench.hydrology.dem), eroded
by stages/erosion/stream_power.run with configs/default.toml's [erosion]
parameters of geological time (read from the file, so the bench follows it);
each variant changes one knob: the channel-initiation area A_c, the critical
slope Sc of the landslides, the deposition coefficient G, the width the
incision's flow per metre is taken over, the routing.
The statistics are worldlib.terrain.stats.terrain_statistics on the result,
with the hydrology stage's routing (complete breaching, Priority-Flood+epsilon,
D8) and its default channel threshold (1e5 m^2): the numbers the bake writes
to the hydrology stage's stats.json (there after the talus rule and the storm
too), among them the slope of the height averaged to 30 m blocks
(slope_statistics). "noise" is the uneroded heightmap; "local" is
grid_anisotropy_local. Targets (issues 16 and 29): anisotropy <= 1.1,
depressions <= 5 %, Strahler >= 4, theta 0.35 .. 0.65, Hack 0.5 .. 0.65,
median slope 15 .. 30 degrees, at most 10 % of the area over 40, at least 8 %
under 10.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.toml"
# stream_power.run's argument for each [erosion] key of geological time (the rest are the talus rule's and the storm's)
RUN_ARGS = {"geological_years": "years", "geological_step_years": "dt_years", "stream_power_k": "k",
            "stream_power_m": "m", "stream_power_n": "n_exp", "uplift_mm_per_year": "uplift_m_per_year",
            "geological_routing": "routing", "channel_area_m2": "channel_area_m2",
            "hillslope_diffusivity_m2_per_year": "diffusivity_m2_per_year", "geological_breach": "breach",
            "geological_mfd_exponent": "mfd_exponent", "geological_flat_routing": "flat_routing",
            "geological_lake_fill": "fill_lakes", "geological_mfd_isotropic": "mfd_isotropic",
            "critical_slope_deg": "critical_slope", "deposition_g": "deposition_g",
            "incision_width_m": "incision_width_m"}


def run_kwargs(overrides: dict | None = None, dx: float = 8.0) -> dict:
    """stream_power.run's keyword arguments from default.toml's [erosion] (ErosionParams' defaults for the
    keys it leaves out), with `overrides` (param names) applied first."""
    import tomllib

    from stages.erosion.params import ErosionParams, channel_threshold_m2, strata_for

    table = tomllib.loads(CONFIG.read_text())["erosion"]
    table.update(overrides or {})
    p = ErosionParams(**{k: v for k, v in table.items() if k in ErosionParams.model_fields})
    kw = {arg: getattr(p, key) for key, arg in RUN_ARGS.items()}
    kw["uplift_m_per_year"] /= 1000.0
    kw["channel_area_m2"] = channel_threshold_m2(p, dx)
    kw["strata"] = strata_for(p)
    kw["critical_slope"] = math.tan(math.radians(kw["critical_slope"])) if kw["critical_slope"] > 0 else 0.0
    return kw


VARIANTS = {
    "noise": None,
    "default": {},
    "no-channel-threshold": dict(channel_area_m2=0.0, channel_specific_area_m=0.0),
    "A_c-x4": "channel_specific_area_m*4",
    "no-landslide": dict(critical_slope_deg=0.0),
    "Sc-40deg": dict(critical_slope_deg=40.0),
    "Sc-51deg": dict(critical_slope_deg=51.3),  # Roering's 1.25
    "G-0.5": dict(deposition_g=0.5),  # Yuan et al. 2019 deposition on
    "no-incision-width": dict(incision_width_m=0.0),  # incision by the cell's own A: the world changes with dx
    "strata-40m": dict(strata_thickness_m=40.0),  # lithology: 12 m hard beds (60 degrees, K / 2) every 40 m
    "old-default": dict(channel_area_m2=0.0, channel_specific_area_m=0.0, critical_slope_deg=0.0, deposition_g=0.0, geological_years=2.0e6,
                        geological_step_years=2.0e5, stream_power_k=2.0e-5, uplift_mm_per_year=0.5,
                        hillslope_diffusivity_m2_per_year=0.01),
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


def _variant_kwargs(name: str, base: dict, dx: float) -> dict:
    v = VARIANTS[name]
    if isinstance(v, str):  # "key*factor": the default's value scaled
        key, factor = v.split("*")
        import tomllib

        value = tomllib.loads(CONFIG.read_text())["erosion"].get(key, 0.0) * float(factor)
        v = {key: value}
    return run_kwargs({**base, **v}, dx)


def main() -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="*", default=[1024])
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--seed", type=int, default=20261123, help="the heightmap's seed (the default world's by default)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="[erosion] keys changed for every variant")
    ap.add_argument("--save", default=None, metavar="DIR", help="write each eroded height to DIR/<n>_<seed>_<variant>.npy")
    args = ap.parse_args()
    import tomllib

    from bench.hydrology import dem
    from stages.erosion import stream_power as sp

    base = {k: tomllib.loads(f"x = {v}")["x"] for k, v in (a.split("=", 1) for a in args.set)}
    print(f"device: {cl_env.fingerprint}; seed {args.seed}; [erosion] changes {base or 'none'}")
    rows = []
    for n in args.sizes:
        dx = 8192.0 / n
        h0 = dem(n, args.seed).astype(np.float64)
        for name in args.variants:
            t0, c0 = time.perf_counter(), time.process_time()
            res = None
            if VARIANTS[name] is None:
                h = h0
            else:
                res = sp.run(cl_env, h0, dx, **_variant_kwargs(name, base, dx))
                h = res.height
            seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
            st = statistics(h, dx)
            if args.save:
                Path(args.save).mkdir(parents=True, exist_ok=True)
                np.save(Path(args.save) / f"{n}_{args.seed}_{name}.npy", h.astype(np.float32))
            rows.append((n, name, seconds, cpu, st, res.stats if res else {}))
            print(f"{n}^2 {name}: {seconds:.1f} s wall, {cpu:.1f} s CPU", flush=True)
    print()
    print(f"{'grid':>5} {'variant':>20} {'wall s':>6} {'CPU s':>6} {'p10':>5} {'p50':>5} {'p90':>5} {'>40%':>5} "
          f"{'<10%':>5} {'aniso':>5} {'local':>5} {'depr%':>5} {'Str':>3} {'Hack':>5} {'theta':>5} {'relief':>6} "
          f"{'slid km3':>8} {'dep km3':>7}")
    for n, name, seconds, cpu, st, rs in rows:
        print(f"{n:5d} {name:>20} {seconds:6.1f} {cpu:6.1f} {st['slope_p10_deg']:5.1f} {st['slope_median_deg']:5.1f} "
              f"{st['slope_p90_deg']:5.1f} {100 * st['slope_share_over_40_deg']:5.1f} "
              f"{100 * st['slope_share_under_10_deg']:5.1f} {st['grid_anisotropy']:5.2f} "
              f"{st['grid_anisotropy_local']:5.2f} {100 * st['depression_area_fraction']:5.2f} "
              f"{st['strahler_order_max']:3d} {st['hack_exponent']:5.2f} {st['concavity_theta']:5.2f} "
              f"{st['relief_m']:6.0f} {rs.get('landslide_m3', 0) / 1e9:8.2f} {rs.get('deposited_m3', 0) / 1e9:7.2f}")


if __name__ == "__main__":
    main()
