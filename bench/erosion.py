"""Benchmark of the erosion stage (not part of `make test`).

    python -m bench.erosion                  # everything (a few minutes on 2 cores)
    python -m bench.erosion --quick          # smaller sizes, shorter runs
    python -m bench.erosion --roofline-only  # part 1 only

It prints, in one run on the same device:
1. roofline: per-step kernel time at 512^2, 1024^2 and 2048^2, cell-steps per
   second, and the achieved bandwidth (compulsory bytes of the flux and update
   kernels per cell-step / time) against a copy kernel, measured back to back
   in interleaved rounds in the same process; plus the rate of the whole time
   loop (diagnostics, adaptive step, host work included).
   The copy is the fastest of three copy kernels in each round: a plain float4
   copy, 8 float16 per work-item (the fastest from cache), and streaming
   stores that skip reading the destination first (the fastest from DRAM: 48
   against 36 GB/s for the plain copy at 2048^2 on the 2-core Zen 4 machine).
   The copy is the roofline only if it runs from the same level of the memory
   hierarchy as the step. So its two buffers together are as large as the
   step's working set (the 13 padded arrays flux + update touch, 52 B per
   cell: 13.7 MB at 512^2, inside the 32 MB L3; 55 MB and 218 MB at 1024^2 and
   2048^2, in DRAM), and its source is written before it is read (untouched
   pages all map to the zero page, which reads from cache). A copy moving the
   step's 104 B per cell instead (27 MB at 512^2) would half miss the L3 and
   flatter the step at 512^2; one smaller than the working set would run from
   a faster level. Bandwidth counts only the compulsory bytes (every array
   read and written once per kernel, BYTES_PER_CELL), never neighbour re-reads
   or write-allocate traffic, for the kernels and the copy alike. The fraction
   is of the best of the interleaved rounds of each, and, more robust on a
   shared 2-core machine whose timings are noisy, the median (and quartiles)
   over rounds of the step against the copy of the same round;
2. speed-up of the OpenCL kernels over the numpy reference (reference.py), the
   same steps on the same grid (and whether the results are bit-identical);
3. run time against error: the final height of fixed-step runs compared with
   a run with a 4x smaller step (time discretisation error) and with a run on a
   2x finer grid, block-averaged to the coarse grid (space discretisation
   error), for several step sizes and resolutions;
4. resolution independence: the default parameters on the same world at
   256^2 and 1024^2 (8 km), change maps low-passed and compared.
Worlds are `stages.erosion.reference.synthetic_world`, analytic terrain that
samples the same landscape at any resolution. Results also go to
bench/out/erosion.json.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

SIZE_M = 8192.0
LOOP_STEPS = 600  # steps of the timed whole loop in the roofline (from a dry start)


def _world(n: int, size_m: float = SIZE_M) -> tuple[np.ndarray, float]:
    from stages.erosion.reference import synthetic_world

    return synthetic_world(n, size_m=size_m, relief_m=1200.0 * size_m / SIZE_M, seed=7), size_m / n


def roofline(sizes: list[int], reps: int, rounds: int = 20) -> list[dict]:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.erosion import simulate
    from bench.erosion_profile import BYTES_PER_CELL, COPY_KERNELS, profile
    from stages.erosion.device import DeviceSim
    from stages.erosion.physics import step_constants
    from stages.erosion.params import ErosionParams, physics_for, plan_for

    rows = []
    per_step = BYTES_PER_CELL["flux"] + BYTES_PER_CELL["update"]
    for n in sizes:
        h, dx = _world(n)
        p = ErosionParams(thermal_years=0.0)
        ph = physics_for(p, dx)
        plan = plan_for(p, dx, ph)
        # PoCL builds each kernel for its work-group size at the first launch (and loads it from its cache
        # in a new process): a short loop first, so the timed one measures the loop and not that
        plan.max_steps = 32
        simulate.run(DeviceSim(cl_env, h, ph), ph, plan)
        sim = DeviceSim(cl_env, h, ph)
        plan.max_steps = LOOP_STEPS  # the whole loop, water flowing (the kernels are timed on its final state)
        m = simulate.run(sim, ph, plan)
        prof = profile(sim, step_constants(ph, m["dt_mean_s"]), reps=reps, rounds=rounds)
        t_step = prof["flux"] + prof["update"]
        copy_gbs = prof["copy_bytes"] / prof["copy"] / 1e9
        bw = per_step * n * n / t_step / 1e9
        # per round, the step against the copy of the same round (measured a few ms apart, so a load spike
        # from another tenant hits both): the median and quartiles of these paired fractions
        step_rounds = np.add(prof["rounds_flux"], prof["rounds_update"])
        paired = (per_step * n * n / step_rounds) / (prof["copy_bytes"] / np.asarray(prof["rounds_copy"]))
        t_th = prof["thermal_send"] + prof["thermal_apply"]
        rows.append(dict(
            n=n, flux_ms=prof["flux"] * 1e3, update_ms=prof["update"] * 1e3, step_ms=t_step * 1e3,
            mcell_steps_per_s=n * n / t_step / 1e6, bytes_per_cell_step=per_step, achieved_gbs=bw,
            copy_gbs=copy_gbs, fraction_of_copy=bw / copy_gbs, copy_bytes=prof["copy_bytes"],
            paired_fraction_of_copy=dict(zip(("q25", "median", "q75"), np.percentile(paired, [25, 50, 75]).tolist())),
            rounds_ms={name: [1e3 * t for t in prof[f"rounds_{name}"]] for name in ("copy", "flux", "update")},
            thermal_ms=t_th * 1e3, thermal_gbs=BYTES_PER_CELL["thermal"] * n * n / t_th / 1e9,
            loop_mcell_steps_per_s=m["cell_steps_per_second"] / 1e6, copy_kernel=prof["copy_kernel"],
            copy_kernel_gbs={c: prof["copy_bytes"] / prof[c] / 1e9 for c in COPY_KERNELS},
        ))
        del sim
    return rows


def speedup(n: int, steps: int) -> dict:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.erosion.device import DeviceSim
    from stages.erosion.physics import step_constants
    from stages.erosion.reference import ReferenceSim
    from stages.erosion.params import ErosionParams, physics_for

    h, dx = _world(n)
    ph = physics_for(ErosionParams(), dx)
    k = step_constants(ph, 0.5 * dx / 20.0)
    dev, ref = DeviceSim(cl_env, h, ph), ReferenceSim(h, ph)
    dev.step(k)
    dev.finish()  # build and first touch outside the clock
    t0 = time.perf_counter()
    for _ in range(steps):
        dev.step(k)
    dev.finish()
    t_dev = (time.perf_counter() - t0) / steps
    ref.step(k)
    t0 = time.perf_counter()
    for _ in range(steps):
        ref.step(k)
    t_ref = (time.perf_counter() - t0) / steps
    dev.thermal(1)
    ref.thermal(1)
    t0 = time.perf_counter()
    dev.thermal(5)
    dev.finish()
    t_dev_th = (time.perf_counter() - t0) / 5
    t0 = time.perf_counter()
    ref.thermal(5)
    t_ref_th = (time.perf_counter() - t0) / 5
    fd, fr = dev.fields(), ref.fields()
    same = all(np.array_equal(fd[name], fr[name]) for name in ("dT", "W", "S", "M", "F"))
    return dict(n=n, steps=steps, numpy_ms=t_ref * 1e3, opencl_ms=t_dev * 1e3, speedup=t_ref / t_dev,
                thermal_numpy_ms=t_ref_th * 1e3, thermal_opencl_ms=t_dev_th * 1e3, thermal_speedup=t_ref_th / t_dev_th,
                bit_identical=same)


def _fixed_run(n: int, size_m: float, dt: float, hours: float) -> tuple[np.ndarray, float, dict]:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.erosion import simulate
    from stages.erosion.device import DeviceSim
    from stages.erosion.params import ErosionParams, physics_for, plan_for

    h, dx = _world(n, size_m)
    p = ErosionParams(thermal_years=0.0, storm_hours=hours, dt_s=dt)
    ph = physics_for(p, dx)
    plan = plan_for(p, dx, ph)
    sim = DeviceSim(cl_env, h, ph)
    t0 = time.perf_counter()
    m = simulate.run(sim, ph, plan)
    sec = time.perf_counter() - t0
    return (h + sim.fields()["dT"]).astype(np.float64), sec, m


def time_vs_error(sizes: list[int], size_m: float, hours: float, courants: list[float], wave: float,
                  sigma_m: float) -> list[dict]:
    """Fixed steps dt = C dx / wave for each Courant number C; errors of the
    final height (RMS, m) against dt/4 on the same grid and against a 2x finer
    grid (dt/2, block-averaged; raw and low-passed with a sigma_m Gaussian),
    relative to the RMS height change."""
    from scipy.ndimage import gaussian_filter

    from pipeline.errors import StageError

    rows = []
    for n in sizes:
        dx = size_m / n
        for c in courants:
            dt = c * dx / wave
            try:
                hgt, sec, m = _fixed_run(n, size_m, dt, hours)
                h_ref_dt, sec_ref, _ = _fixed_run(n, size_m, dt / 4, hours)
                h_fine, sec_fine, _ = _fixed_run(2 * n, size_m, dt / 2, hours)
            except StageError as e:
                rows.append(dict(n=n, dt=dt, refused=str(e)))
                continue
            h0, _ = _world(n, size_m)
            change_rms = float(np.sqrt(np.mean((h_ref_dt - h0) ** 2)))
            fine_on_coarse = h_fine.reshape(n, 2, n, 2).mean(axis=(1, 3))
            e_dt = float(np.sqrt(np.mean((hgt - h_ref_dt) ** 2)))
            e_dx = float(np.sqrt(np.mean((hgt - fine_on_coarse) ** 2)))
            h0f, _ = _world(2 * n, size_m)
            # the 2x grid samples the analytic world at other points: compare changes, not heights
            c_coarse = hgt - h0
            c_fine = (h_fine - h0f).reshape(n, 2, n, 2).mean(axis=(1, 3))
            e_dx_change = float(np.sqrt(np.mean((c_coarse - c_fine) ** 2)))
            lp = lambda a: gaussian_filter(a, sigma_m / dx, mode="nearest")  # noqa: E731
            e_dx_lp = float(np.sqrt(np.mean((lp(c_coarse) - lp(c_fine)) ** 2)))
            lp_rms = float(np.sqrt(np.mean(lp(c_fine) ** 2)))
            rows.append(dict(n=n, dx_m=dx, dt_s=dt, courant_max=m["courant_max"], steps=m["steps"], seconds=sec,
                             change_rms_m=change_rms, err_vs_dt4_m=e_dt, err_vs_dt4_rel=e_dt / max(change_rms, 1e-12),
                             err_vs_2x_grid_m=e_dx_change, err_vs_2x_grid_rel=e_dx_change / max(change_rms, 1e-12),
                             err_vs_2x_grid_lowpass_m=e_dx_lp, err_vs_2x_grid_lowpass_rel=e_dx_lp / max(lp_rms, 1e-12),
                             seconds_dt4=sec_ref, seconds_2x=sec_fine, height_err_vs_2x_m=e_dx))
    return rows


def resolution(n_coarse: int, factor: int, sigma_m: float) -> dict:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from scipy.ndimage import gaussian_filter

    from pipeline.contract import RunContext
    from pipeline.grid import Grid
    from stages.erosion import STAGE, ErosionParams

    out = {}
    for n in (n_coarse, n_coarse * factor):
        h, dx = _world(n)
        ctx = RunContext(cl=cl_env, stage=STAGE, key="bench", out_dir=Path("."), seed=0, provenance={}, project_root=Path("."))
        t0 = time.perf_counter()
        res = STAGE.run(ctx, {"height": Grid(h, cell_size_m=dx)}, ErosionParams())
        sec = time.perf_counter() - t0
        c = res["erosion.change"].data[..., 0].astype(np.float64)
        out[n] = (gaussian_filter(c, sigma_m / dx, mode="nearest"), sec, ctx.metrics)
    a = out[n_coarse][0]
    b = out[n_coarse * factor][0].reshape(n_coarse, factor, n_coarse, factor).mean(axis=(1, 3))
    return dict(coarse=n_coarse, fine=n_coarse * factor, sigma_m=sigma_m,
                rel_l2=float(np.linalg.norm(a - b) / np.linalg.norm(b)), correlation=float(np.corrcoef(a.ravel(), b.ravel())[0, 1]),
                lowpassed_change_max_m=float(np.abs(b).max()),
                seconds_coarse=out[n_coarse][1], seconds_fine=out[n_coarse * factor][1],
                steps_coarse=out[n_coarse][2]["steps"], steps_fine=out[n_coarse * factor][2]["steps"],
                water_budget_fine=out[n_coarse * factor][2]["water_budget_residual_rel"],
                mass_budget_fine=out[n_coarse * factor][2]["mass_budget_residual_rel"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smaller sizes and shorter runs")
    ap.add_argument("--reps", type=int, default=5, help="launches per kernel timing round")
    ap.add_argument("--rounds", type=int, default=20, help="interleaved timing rounds (best and paired median reported)")
    ap.add_argument("--roofline-only", action="store_true", help="only part 1, the roofline")
    args = ap.parse_args(argv)

    from pipeline.opencl import get_cl

    env = get_cl()
    print(f"device: {env.fingerprint}")
    print(f"host: {platform.processor() or platform.machine()}, python {platform.python_version()}, numpy {np.__version__}")
    results: dict = {"device": env.fingerprint}
    t_all = time.perf_counter()

    sizes = [256, 512] if args.quick else [512, 1024, 2048]
    print("\n1. Roofline: the two per-step kernels (flux + update) vs a copy kernel over as large a working set")
    rows = roofline(sizes, args.reps, args.rounds)
    results["roofline"] = rows
    print(f"{'grid':>6} {'flux ms':>8} {'update ms':>9} {'step ms':>8} {'Mcell-steps/s':>14} {'B/cell':>7} "
          f"{'GB/s':>6} {'copy GB/s':>9} {'of copy':>8} {'paired: median [quartiles]':>27} {'loop Mcs/s':>10} {'thermal ms':>10} "
          f"{'copies GB/s: float4 / 8xfloat16 / streaming':>44}")
    for r in rows:
        cg, pf = r["copy_kernel_gbs"], r["paired_fraction_of_copy"]
        print(f"{r['n']:>5}² {r['flux_ms']:8.2f} {r['update_ms']:9.2f} {r['step_ms']:8.2f} {r['mcell_steps_per_s']:14.0f} "
              f"{r['bytes_per_cell_step']:7d} {r['achieved_gbs']:6.1f} {r['copy_gbs']:9.1f} {100 * r['fraction_of_copy']:7.0f}% "
              f"{100 * pf['median']:13.0f}% [{100 * pf['q25']:3.0f}-{100 * pf['q75']:3.0f}%] "
              f"{r['loop_mcell_steps_per_s']:10.0f} {r['thermal_ms']:10.2f} "
              f"{cg['copy4']:>18.1f} / {cg['copy16x8']:.1f} / {cg['copy16_stream']:.1f}")
    print("   (of copy: best round of the step against best round of the copy; paired: the step of each round against "
          f"the copy of the same round, over {args.rounds} rounds. The copy of each round is the "
          "fastest of the three copy kernels. Their buffers add up to "
          "the step's working set (13 arrays, 52 B/cell): at 512^2 both run from the 32 MB L3, above from DRAM. "
          f"loop Mcs/s: the whole time loop of {LOOP_STEPS} steps from a dry start, diagnostics (at steps 1, 2, 4, 8, then every 16) and host work included, "
          f"after a short untimed loop that builds the kernels)")
    if args.roofline_only:
        _write(results, t_all)
        return

    n_sp = 128 if args.quick else 256
    print(f"\n2. Speed-up over the numpy reference ({n_sp}² , same steps)")
    sp = speedup(n_sp, 5 if args.quick else 10)
    results["speedup"] = sp
    print(f"   storm step: numpy {sp['numpy_ms']:.1f} ms, OpenCL {sp['opencl_ms']:.2f} ms -> {sp['speedup']:.0f}x; "
          f"talus iteration: numpy {sp['thermal_numpy_ms']:.1f} ms, OpenCL {sp['thermal_opencl_ms']:.2f} ms -> "
          f"{sp['thermal_speedup']:.0f}x; results bit-identical: {sp['bit_identical']}")

    print("\n3. Run time against error (fixed steps dt = C dx / 20 m/s, 2 km world, storm of 0.1 h, no thermal)")
    te_sizes = [64, 128] if args.quick else [64, 128, 256]
    te = time_vs_error(te_sizes, 2048.0, 0.1, [0.8, 0.4, 0.2, 0.1], 20.0, 125.0)
    results["time_vs_error"] = te
    print(f"{'grid':>6} {'dx m':>6} {'dt s':>7} {'Courant':>7} {'steps':>6} {'run s':>6} {'RMS change m':>12} "
          f"{'err vs dt/4':>18} {'err vs 2x grid':>18} {'low-passed':>10}")
    for r in te:
        if "refused" in r:
            print(f"{r['n']:>5}² dt {r['dt']:.3g} s refused: {r['refused']}")
            continue
        print(f"{r['n']:>5}² {r['dx_m']:6.1f} {r['dt_s']:7.3f} {r['courant_max']:7.2f} {r['steps']:6d} {r['seconds']:6.2f} "
              f"{r['change_rms_m']:12.4f} {r['err_vs_dt4_m']:9.4f} m {100 * r['err_vs_dt4_rel']:5.1f}% "
              f"{r['err_vs_2x_grid_m']:9.4f} m {100 * r['err_vs_2x_grid_rel']:5.0f}% {100 * r['err_vs_2x_grid_lowpass_rel']:9.0f}%")
    print("   err vs dt/4: RMS of final height minus the same run with dt/4; err vs 2x grid: RMS of the height change "
          "minus the change on a 2x finer grid (dt/2) block-averaged, % of the RMS change; low-passed: the same after a "
          "125 m Gaussian on both, % of the low-passed RMS change")

    rc, rf = (128, 4) if args.quick else (256, 4)
    print(f"\n4. Resolution independence: default parameters, 8 km world, {rc}² vs {rc * rf}², change maps low-passed "
          f"(Gaussian sigma 250 m)")
    rs = resolution(rc, rf, 250.0)
    results["resolution"] = rs
    print(f"   correlation {rs['correlation']:.3f}, relative L2 difference {rs['rel_l2']:.3f} (largest low-passed change "
          f"{rs['lowpassed_change_max_m']:.2f} m); run {rs['seconds_coarse']:.1f} s / {rs['seconds_fine']:.1f} s, "
          f"{rs['steps_coarse']} / {rs['steps_fine']} steps; budgets at {rc * rf}²: water {rs['water_budget_fine']:.1e}, "
          f"mass {rs['mass_budget_fine']:.1e}")

    _write(results, t_all)


def _write(results: dict, t_all: float) -> None:
    results["bench_seconds"] = time.perf_counter() - t_all
    out = Path(__file__).resolve().parent / "out"
    out.mkdir(exist_ok=True)
    name = "erosion-roofline.json" if "speedup" not in results else "erosion.json"
    (out / name).write_text(json.dumps(results, indent=1))
    print(f"\n(total {results['bench_seconds']:.0f} s; written to bench/out/{name})")


if __name__ == "__main__":
    main()
