"""The time loop, shared by the device simulator and the numpy reference:
thermal weathering, then the storm with an adaptive (or checked fixed) time
step, the float64 water and mass budgets, and the blow-up checks."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from pipeline.errors import StageError

from .physics import THERMAL_C, Physics, StepConstants, rain_quantum, step_constants
from .state import Diag

# A budget that drifts this far is a broken invariant, not round-off: the stage stops.
FAIL_WATER_REL = 1e-4
FAIL_MASS_REL = 1e-4
START_SPEED = 10.0  # m/s, the flow speed assumed before the first measurement
DT_GROWTH = 1.2  # the adaptive step grows at most this much from one check to the next


class Backend(Protocol):
    def step(self, k: StepConstants, want_wave: bool = False) -> None: ...
    def thermal(self, iterations: int, wet_min: float = -1.0, cfrac: float = THERMAL_C) -> None: ...
    def diag(self) -> Diag: ...
    def finish(self) -> None: ...
    def fields(self) -> dict[str, np.ndarray]: ...


@dataclass
class Plan:
    """What to run: thermal iterations before the storm, then the storm."""

    thermal_iterations: int = 0
    thermal_c: float = THERMAL_C  # Olsen's c of those iterations (scaled down when less than one iteration is due)
    duration_s: float = 0.0
    fixed_dt: float | None = None
    max_steps: int | None = None  # stop after this many steps (tests)
    check_every: int = 16  # steps between diagnostics (and adaptive dt updates); the first come at 1, 2, 4, 8

    def is_check(self, step: int) -> bool:
        """Diagnostics (and a new adaptive dt) before this step: at 0, 1, 2, 4, 8
        while the flow starts, then every check_every steps."""
        if step < self.check_every:
            return step & (step - 1) == 0
        return step % self.check_every == 0
    max_total_steps: int = 10_000_000  # refuse to go on beyond this (a step collapsed to nothing)


@dataclass
class Budget:
    """The float64 water and terrain + sediment budgets, checked at every diagnostic.
    Water: stored = initial + rain - evaporated - boundary outflow, relative to
    the larger of stored water and rain. Terrain + sediment: sum(dT + S) +
    sediment out = initial, relative to the volume of material moved
    (sum |dT| + S + out), the strictest scale (not the whole mountain)."""

    water0: float
    mass0: float
    rain: float = 0.0
    evaporated: float = 0.0
    checks: int = 0
    worst_water_rel: float = 0.0
    worst_mass_rel: float = 0.0
    last: dict = field(default_factory=dict)

    def check(self, d: Diag) -> tuple[float, float]:
        self.evaporated += d.evaporated
        expected = self.water0 + self.rain - self.evaporated - d.out_water
        w_res = d.water - expected
        w_scale = max(d.water, self.rain, self.water0, 1e-30)
        mass = d.dT + d.sediment + d.out_sediment
        m_res = mass - self.mass0
        m_scale = max(d.abs_dT + d.sediment + d.out_sediment, 1e-30)
        w_rel, m_rel = abs(w_res) / w_scale, abs(m_res) / m_scale
        self.checks += 1
        self.worst_water_rel = max(self.worst_water_rel, w_rel)
        self.worst_mass_rel = max(self.worst_mass_rel, m_rel)
        self.last = dict(
            water_stored=d.water, rain=self.rain, evaporated=self.evaporated, outflow=d.out_water,
            water_residual=w_res, water_residual_rel=w_rel,
            mass_residual=m_res, mass_residual_rel=m_rel, material_moved=m_scale,
            sediment_suspended=d.sediment, sediment_outflow=d.out_sediment,
        )
        return w_rel, m_rel


def _fail(msg: str) -> StageError:
    return StageError(f"erosion: {msg}")


def run(backend: Backend, ph: Physics, plan: Plan, *, progress: Callable[[float, str], None] | None = None,
        after_thermal: Callable[[dict], None] | None = None) -> dict:
    """Run the plan on a backend; returns the metrics. Raises StageError on a
    blow-up (non-finite values, negative water or sediment, budget drift) or
    when a fixed time step breaks the CFL limit."""
    prog = progress or (lambda f, m: None)
    t_start = time.perf_counter()
    d0 = backend.diag()
    if d0.nonfinite:
        raise _fail(f"the initial state has {d0.nonfinite} non-finite cells")
    cells = backend.rows * backend.cols
    bud = Budget(water0=d0.water, mass0=d0.dT + d0.sediment)
    metrics: dict = {}

    # -- thermal weathering --------------------------------------------------
    t0 = time.perf_counter()
    n_th = plan.thermal_iterations
    done = 0
    while done < n_th:
        chunk = min(256, n_th - done)
        backend.thermal(chunk, cfrac=plan.thermal_c)
        done += chunk
        d = backend.diag()
        if d.nonfinite:
            raise _fail(f"thermal weathering blew up at iteration {done} (talus_angle_deg): {d.nonfinite} non-finite cells")
        prog(0.25 * done / max(n_th, 1), f"thermal weathering {done}/{n_th}")
    backend.finish()
    metrics["thermal_iterations"] = n_th
    metrics["thermal_c"] = plan.thermal_c
    metrics["thermal_seconds"] = time.perf_counter() - t0
    if n_th:
        d = backend.diag()
        _, m_rel = bud.check(d)
        metrics["thermal_mass_residual_rel"] = m_rel
        if after_thermal is not None:
            after_thermal(backend.fields())

    # -- the storm -----------------------------------------------------------
    t0 = time.perf_counter()
    slump_rate = ph.thermal_iterations_per_second(ph.bank_diffusivity) if ph.bank_diffusivity > 0 else 0.0
    slump_clock = 0.0
    slump_iters = 0
    t = 0.0
    step = 0
    dts: list[float] = []
    wave = d0.wave
    courant_max = 0.0
    cfl_exceeded = 0
    # a dry start has no wave to measure: begin as if water moved at START_SPEED; the
    # checks at steps 1, 2, 4, 8 measure the real flow and set the step from it
    dt = plan.fixed_dt if plan.fixed_dt else ph.dt_limit(max(wave, START_SPEED))
    dt_used_since_check = 0.0
    rain_owed = 0.0  # m of rain not yet added to the grid (less than one quantum)
    wmax = d0.wmax

    def done_running() -> bool:
        if plan.max_steps is not None:
            return step >= plan.max_steps
        return t >= plan.duration_s * (1.0 - 1e-12)

    while not done_running():
        if step >= plan.max_total_steps:
            raise _fail(f"the storm needs more than {plan.max_total_steps} steps (t = {t:.4g} of {plan.duration_s:.4g} s, "
                        f"dt = {dt:.3g} s): lower storm_hours or raise cfl")
        if plan.is_check(step):
            d = backend.diag()
            _check_state(d, ph, plan, step, dt)
            w_rel, m_rel = bud.check(d)
            if w_rel > FAIL_WATER_REL:
                raise _fail(f"water budget drifted by {w_rel:.2e} (relative) at step {step} "
                            f"(rain_mm_per_hour / dt_s / cfl): a numerical blow-up")
            if m_rel > FAIL_MASS_REL and bud.last["material_moved"] > 1e-9 * cells:
                raise _fail(f"terrain + sediment budget drifted by {m_rel:.2e} (relative) at step {step} "
                            f"(dissolve_rate_per_s / deposit_rate_per_s / dt_s): a numerical blow-up")
            wave = d.wave
            wmax = d.wmax
            if step > 0:
                cr = dt_used_since_check * wave / ph.dx
                courant_max = max(courant_max, cr)
                if cr > ph.cfl_limit:
                    if plan.fixed_dt:
                        allowed = ph.cfl_limit * ph.dx / max(wave, 1e-30)
                        raise _fail(
                            f"dt_s = {plan.fixed_dt:g} s breaks the CFL limit at step {step}: Courant number "
                            f"{cr:.2f} > {ph.cfl_limit} (fastest wave {wave:.3g} m/s, cell {ph.dx:.4g} m); "
                            f"use dt_s <= {allowed:.3g} s or leave dt_s unset for the adaptive step")
                    cfl_exceeded += 1
            if not plan.fixed_dt:
                dt = min(ph.dt_limit(wave), DT_GROWTH * dt) if step > 0 else ph.dt_limit(max(wave, START_SPEED))
            frac = (step / plan.max_steps) if plan.max_steps else t / max(plan.duration_s, 1e-30)
            prog(0.25 + 0.7 * min(frac, 1.0), f"storm step {step}, t = {t / 3600.0:.3f} h, dt = {dt:.3g} s")
            dt_used_since_check = 0.0
        this_dt = dt
        if plan.max_steps is None and t + this_dt > plan.duration_s:
            this_dt = plan.duration_s - t
        # rain falls in whole quanta (see rain_quantum); what is left over is owed to the next step
        rain_owed += ph.rain * this_dt
        q = rain_quantum(wmax, rain_owed)
        rain_now = math.floor(rain_owed / q) * q
        rain_owed -= rain_now
        k = step_constants(ph, this_dt, rain_depth=rain_now)
        backend.step(k, want_wave=plan.is_check(step + 1))
        bud.rain += cells * float(k.rain_dt)
        dt_used_since_check = max(dt_used_since_check, this_dt)
        dts.append(this_dt)
        t += this_dt
        step += 1
        if slump_rate > 0:
            slump_clock += this_dt * slump_rate
            n = int(slump_clock)
            if n:
                backend.thermal(n, wet_min=ph.wet_depth)
                slump_clock -= n
                slump_iters += n
    d = backend.diag()
    _check_state(d, ph, plan, step, dt)
    w_rel, m_rel = bud.check(d)
    if w_rel > FAIL_WATER_REL or (m_rel > FAIL_MASS_REL and bud.last["material_moved"] > 1e-9 * cells):
        raise _fail(f"budget drifted at the end (step {step}): water {w_rel:.2e}, terrain + sediment {m_rel:.2e}")
    if step:
        cr = dt_used_since_check * d.wave / ph.dx
        courant_max = max(courant_max, cr)
    backend.finish()
    storm_s = time.perf_counter() - t0
    dta = np.array(dts) if dts else np.zeros(1)
    metrics.update(
        steps=step,
        simulated_seconds=t,
        rain_not_fallen_m=rain_owed,
        dt_min_s=float(dta.min()), dt_max_s=float(dta.max()), dt_mean_s=float(dta.mean()),
        courant_max=courant_max, cfl_exceeded_checks=cfl_exceeded,
        slump_iterations=slump_iters,
        storm_seconds=storm_s,
        cell_steps_per_second=(cells * step / storm_s) if storm_s > 0 and step else 0.0,
        water_budget_residual_rel=w_rel, mass_budget_residual_rel=m_rel,
        water_budget_worst_rel=bud.worst_water_rel, mass_budget_worst_rel=bud.worst_mass_rel,
        budget_checks=bud.checks,
        water_min=d.wmin, sediment_min=d.smin, max_wave_speed=d.wave,
        **{f"budget_{k}": v for k, v in bud.last.items()},
        total_seconds=time.perf_counter() - t_start,
    )
    return metrics


def _check_state(d: Diag, ph: Physics, plan: Plan, step: int, dt: float) -> None:
    step_param = f"dt_s = {plan.fixed_dt:g}" if plan.fixed_dt else f"cfl = {ph.cfl:g}, dt = {dt:.3g} s"
    if d.nonfinite:
        raise _fail(f"numerical blow-up at step {step}: {d.nonfinite} cells with NaN or Inf ({step_param})")
    if d.wmin < 0.0:
        raise _fail(f"negative water depth {d.wmin:.3g} m at step {step} ({step_param})")
    if d.smin < 0.0:
        raise _fail(f"negative sediment {d.smin:.3g} m at step {step} (dissolve_rate_per_s / deposit_rate_per_s, "
                    f"{step_param})")
