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
    when a fixed time step breaks the CFL limit.

    Steps: the initial state's diagnostics open the budget; thermal
    weathering (_thermal); the storm (_storm), its steps with diagnostics
    and the adaptive time step at plan.is_check; the final checks."""
    t_start = time.perf_counter()
    d0 = backend.diag()
    if d0.nonfinite:
        raise _fail(f"the initial state has {d0.nonfinite} non-finite cells")
    r = _Run(backend, ph, plan, Budget(water0=d0.water, mass0=d0.dT + d0.sediment), backend.rows * backend.cols,
             progress or (lambda f, m: None))
    metrics = _thermal(r, after_thermal)
    metrics.update(_storm(r, d0))
    metrics["total_seconds"] = time.perf_counter() - t_start
    return metrics


@dataclass(frozen=True)
class _Run:
    """What every part of a run reads: the backend, its physics and plan, the
    budget (updated at each diagnostic), the cell count, the progress callback."""

    backend: Backend
    ph: Physics
    plan: Plan
    budget: Budget
    cells: int
    progress: Callable[[float, str], None]


def _thermal(r: _Run, after_thermal: Callable[[dict], None] | None) -> dict:
    """Thermal weathering in chunks of 256 iterations (progress 0 .. 0.25);
    its metrics, and the budget checked once after it."""
    t0 = time.perf_counter()
    n_th = r.plan.thermal_iterations
    done = 0
    while done < n_th:
        chunk = min(256, n_th - done)
        r.backend.thermal(chunk, cfrac=r.plan.thermal_c)
        done += chunk
        d = r.backend.diag()
        if d.nonfinite:
            raise _fail(f"thermal weathering blew up at iteration {done} (talus_angle_deg): {d.nonfinite} non-finite cells")
        r.progress(0.25 * done / max(n_th, 1), f"thermal weathering {done}/{n_th}")
    r.backend.finish()
    metrics = {"thermal_iterations": n_th, "thermal_c": r.plan.thermal_c, "thermal_seconds": time.perf_counter() - t0}
    if n_th:
        _, m_rel = r.budget.check(r.backend.diag())
        metrics["thermal_mass_residual_rel"] = m_rel
        if after_thermal is not None:
            after_thermal(r.backend.fields())
    return metrics


@dataclass
class _Storm:
    """The storm's running state from one step to the next."""

    dt: float  # the step the last diagnostic chose (or the fixed one)
    wave: float  # the fastest wave at the last diagnostic (m/s)
    wmax: float  # the deepest water at the last diagnostic (m)
    slump_rate: float  # bank-slumping iterations per simulated second (0: off)
    t: float = 0.0
    step: int = 0
    dts: list[float] = field(default_factory=list)
    courant_max: float = 0.0
    cfl_exceeded: int = 0
    dt_used_since_check: float = 0.0
    rain_owed: float = 0.0  # m of rain not yet added to the grid (less than one quantum)
    slump_clock: float = 0.0
    slump_iters: int = 0

    def done(self, plan: Plan) -> bool:
        if plan.max_steps is not None:
            return self.step >= plan.max_steps
        return self.t >= plan.duration_s * (1.0 - 1e-12)


def _storm(r: _Run, d0: Diag) -> dict:
    """The storm's steps (progress 0.25 .. 0.95), then the final checks; its metrics."""
    t0 = time.perf_counter()
    ph, plan = r.ph, r.plan
    slump_rate = ph.thermal_iterations_per_second(ph.bank_diffusivity) if ph.bank_diffusivity > 0 else 0.0
    # a dry start has no wave to measure: begin as if water moved at START_SPEED; the
    # checks at steps 1, 2, 4, 8 measure the real flow and set the step from it
    s = _Storm(dt=plan.fixed_dt if plan.fixed_dt else ph.dt_limit(max(d0.wave, START_SPEED)), wave=d0.wave,
               wmax=d0.wmax, slump_rate=slump_rate)
    while not s.done(plan):
        if s.step >= plan.max_total_steps:
            raise _fail(f"the storm needs more than {plan.max_total_steps} steps (t = {s.t:.4g} of {plan.duration_s:.4g} s, "
                        f"dt = {s.dt:.3g} s): lower storm_hours or raise cfl")
        if plan.is_check(s.step):
            _diagnose(r, s)
        this_dt = _step(r, s)
        _slump(r, s, this_dt)
    d, w_rel, m_rel = _final_check(r, s)
    r.backend.finish()
    return _storm_metrics(r, s, d, (w_rel, m_rel), time.perf_counter() - t0)


def _drifted(r: _Run, w_rel: float, m_rel: float) -> tuple[bool, bool]:
    """Whether the water and the terrain + sediment budgets drifted beyond round-off."""
    return w_rel > FAIL_WATER_REL, m_rel > FAIL_MASS_REL and r.budget.last["material_moved"] > 1e-9 * r.cells


def _diagnose(r: _Run, s: _Storm) -> None:
    """A diagnostic before step s.step: state and budget checks, the Courant
    number since the last one, a new adaptive dt, progress."""
    ph, plan, step = r.ph, r.plan, s.step
    d = r.backend.diag()
    _check_state(d, ph, plan, step, s.dt)
    w_rel, m_rel = r.budget.check(d)
    water_drifted, mass_drifted = _drifted(r, w_rel, m_rel)
    if water_drifted:
        raise _fail(f"water budget drifted by {w_rel:.2e} (relative) at step {step} "
                    f"(rain_mm_per_hour / dt_s / cfl): a numerical blow-up")
    if mass_drifted:
        raise _fail(f"terrain + sediment budget drifted by {m_rel:.2e} (relative) at step {step} "
                    f"(dissolve_rate_per_s / deposit_rate_per_s / dt_s): a numerical blow-up")
    s.wave = d.wave
    s.wmax = d.wmax
    if step > 0:
        _measure_courant(r, s)
    if not plan.fixed_dt:
        s.dt = min(ph.dt_limit(s.wave), DT_GROWTH * s.dt) if step > 0 else ph.dt_limit(max(s.wave, START_SPEED))
    frac = (step / plan.max_steps) if plan.max_steps else s.t / max(plan.duration_s, 1e-30)
    r.progress(0.25 + 0.7 * min(frac, 1.0), f"storm step {step}, t = {s.t / 3600.0:.3f} h, dt = {s.dt:.3g} s")
    s.dt_used_since_check = 0.0


def _measure_courant(r: _Run, s: _Storm) -> None:
    """The Courant number of the largest step since the last diagnostic: a
    fixed dt that breaks the CFL limit stops the run, an adaptive one is counted."""
    ph, plan = r.ph, r.plan
    cr = s.dt_used_since_check * s.wave / ph.dx
    s.courant_max = max(s.courant_max, cr)
    if cr > ph.cfl_limit:
        if plan.fixed_dt:
            allowed = ph.cfl_limit * ph.dx / max(s.wave, 1e-30)
            raise _fail(
                f"dt_s = {plan.fixed_dt:g} s breaks the CFL limit at step {s.step}: Courant number "
                f"{cr:.2f} > {ph.cfl_limit} (fastest wave {s.wave:.3g} m/s, cell {ph.dx:.4g} m); "
                f"use dt_s <= {allowed:.3g} s or leave dt_s unset for the adaptive step")
        s.cfl_exceeded += 1


def _step(r: _Run, s: _Storm) -> float:
    """One storm step (the last one shortened to end at duration_s) with the
    rain due in whole quanta; returns its dt."""
    ph, plan = r.ph, r.plan
    this_dt = s.dt
    if plan.max_steps is None and s.t + this_dt > plan.duration_s:
        this_dt = plan.duration_s - s.t
    # rain falls in whole quanta (see rain_quantum); what is left over is owed to the next step
    s.rain_owed += ph.rain * this_dt
    q = rain_quantum(s.wmax, s.rain_owed)
    rain_now = math.floor(s.rain_owed / q) * q
    s.rain_owed -= rain_now
    k = step_constants(ph, this_dt, rain_depth=rain_now)
    r.backend.step(k, want_wave=plan.is_check(s.step + 1))
    r.budget.rain += r.cells * float(k.rain_dt)
    s.dt_used_since_check = max(s.dt_used_since_check, this_dt)
    s.dts.append(this_dt)
    s.t += this_dt
    s.step += 1
    return this_dt


def _slump(r: _Run, s: _Storm, this_dt: float) -> None:
    """Bank slumping: the talus rule into wet cells, whole iterations as their time comes due."""
    if s.slump_rate > 0:
        s.slump_clock += this_dt * s.slump_rate
        n = int(s.slump_clock)
        if n:
            r.backend.thermal(n, wet_min=r.ph.wet_depth)
            s.slump_clock -= n
            s.slump_iters += n


def _final_check(r: _Run, s: _Storm) -> tuple[Diag, float, float]:
    """The state and budgets after the last step, and the last Courant number."""
    d = r.backend.diag()
    _check_state(d, r.ph, r.plan, s.step, s.dt)
    w_rel, m_rel = r.budget.check(d)
    if any(_drifted(r, w_rel, m_rel)):
        raise _fail(f"budget drifted at the end (step {s.step}): water {w_rel:.2e}, terrain + sediment {m_rel:.2e}")
    if s.step:
        cr = s.dt_used_since_check * d.wave / r.ph.dx
        s.courant_max = max(s.courant_max, cr)
    return d, w_rel, m_rel


def _storm_metrics(r: _Run, s: _Storm, d: Diag, residuals: tuple[float, float], storm_s: float) -> dict:
    bud, cells, step = r.budget, r.cells, s.step
    w_rel, m_rel = residuals
    dta = np.array(s.dts) if s.dts else np.zeros(1)
    return dict(
        steps=step,
        simulated_seconds=s.t,
        rain_not_fallen_m=s.rain_owed,
        dt_min_s=float(dta.min()), dt_max_s=float(dta.max()), dt_mean_s=float(dta.mean()),
        courant_max=s.courant_max, cfl_exceeded_checks=s.cfl_exceeded,
        slump_iterations=s.slump_iters,
        storm_seconds=storm_s,
        cell_steps_per_second=(cells * step / storm_s) if storm_s > 0 and step else 0.0,
        water_budget_residual_rel=w_rel, mass_budget_residual_rel=m_rel,
        water_budget_worst_rel=bud.worst_water_rel, mass_budget_worst_rel=bud.worst_mass_rel,
        budget_checks=bud.checks,
        water_min=d.wmin, sediment_min=d.smin, max_wave_speed=d.wave,
        **{f"budget_{k}": v for k, v in bud.last.items()},
    )


def _check_state(d: Diag, ph: Physics, plan: Plan, step: int, dt: float) -> None:
    step_param = f"dt_s = {plan.fixed_dt:g}" if plan.fixed_dt else f"cfl = {ph.cfl:g}, dt = {dt:.3g} s"
    if d.nonfinite:
        raise _fail(f"numerical blow-up at step {step}: {d.nonfinite} cells with NaN or Inf ({step_param})")
    if d.wmin < 0.0:
        raise _fail(f"negative water depth {d.wmin:.3g} m at step {step} ({step_param})")
    if d.smin < 0.0:
        raise _fail(f"negative sediment {d.smin:.3g} m at step {step} (dissolve_rate_per_s / deposit_rate_per_s, "
                    f"{step_param})")
