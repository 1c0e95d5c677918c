"""Properties 3 and 4: no negative water or sediment, nothing non-finite, slopes
settle at the talus angle; and the stress set either runs clean or is refused
with a clear message (never a crash, never a blow-up written as a result).

Talus tolerance: after thermal weathering has run to convergence no
8-neighbour slope exceeds the talus angle by more than 0.05 degrees (measured:
below 0.001 degrees after 5000 iterations on a 64^2 mountain three times as
steep as the Alps, for 5, 35 and 85 degrees)."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import InputError, StageError
from stages.erosion.steps import slope_excess

from .helpers import run_stage, world

TALUS_TOL_DEG = 0.05
SHORT = dict(storm_hours=0.05)  # 3 minutes of storm: ~100-400 steps on 64^2


def _check_clean(out, m, h):
    """The invariants every finished run must satisfy."""
    W = out["erosion.water"].data
    S = out["erosion.sediment"].data
    H = out["erosion.height"].data
    for name, grid in out.items():
        if name != "erosion.hillshade":
            assert grid.data.dtype == np.float32 and np.isfinite(grid.data).all(), name
    assert W.min() >= 0.0 and S.min() >= 0.0
    assert m["water_min"] >= 0.0 and m["sediment_min"] >= 0.0
    assert m["water_budget_residual_rel"] <= 1e-6 and m["mass_budget_residual_rel"] <= 1e-6
    change = out["erosion.change"].data[..., 0]
    np.testing.assert_allclose(H, (h + change).astype(np.float32))


def _cliff():
    h = np.zeros((64, 64), np.float32)
    h[:, 32:] = 1000.0  # a vertical cliff of 1000 m
    return h


def _hole():
    h, _ = world(64)
    h = h.copy()
    h[30:33, 30:33] -= 1000.0  # a 1000 m deep hole
    return h


def _spike():
    h, _ = world(64)
    h = h.copy()
    h[20, 40] += 1000.0  # a one-cell spike
    return h


CASES = {
    "rain_100x_default": (lambda: world(64)[0], dict(rain_mm_per_hour=10000.0)),
    "talus_5": (lambda: world(64)[0], dict(talus_angle_deg=5.0, thermal_years=1e4)),
    "talus_85": (lambda: world(64)[0], dict(talus_angle_deg=85.0, thermal_years=1e4)),
    "cliff_1000m": (_cliff, dict(thermal_years=1e4)),
    "cliff_1000m_closed_no_thermal": (_cliff, dict(boundary="closed", thermal_years=0)),
    "hole_minus_1000m": (_hole, dict(thermal_years=1e4)),
    "hole_minus_1000m_no_thermal": (_hole, dict(thermal_years=0)),
    "spike_1_cell": (_spike, dict(thermal_years=1e4)),
    "spike_1_cell_no_thermal": (_spike, dict(thermal_years=0)),
    "flat": (lambda: np.zeros((64, 64), np.float32), dict()),
    "flat_periodic": (lambda: np.full((64, 64), 500.0, np.float32), dict(boundary="periodic")),
    "largest_adaptive_step_cfl_0.9": (lambda: world(64)[0], dict(cfl=0.9)),
    "fastest_exchange_rates": (lambda: world(64)[0], dict(dissolve_rate_per_s=100.0, deposit_rate_per_s=100.0,
                                                         sediment_capacity_s_per_m=100.0)),
    "frictionless": (lambda: world(64)[0], dict(friction=0.001)),
    "bank_slumping": (lambda: world(64)[0], dict(bank_diffusivity_m2_per_hour=1e6)),
    "evaporation_beats_rain": (lambda: world(64)[0], dict(evaporation_mm_per_hour=1e5)),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_stress_case_runs_clean(case, tmp_path):
    make, params = CASES[case]
    h = make()
    _, dx = world(64)
    out, m, calls = run_stage(h, dx, tmp_path, **{**SHORT, **params})
    _check_clean(out, m, h)
    assert m["steps"] > 0 and calls[-1][0] == 1.0
    if case == "evaporation_beats_rain":
        assert out["erosion.water"].data.max() == 0.0
    if case.startswith("flat"):
        assert not out["erosion.change"].data.any()  # nothing to erode on flat ground


@pytest.mark.parametrize("talus", [5.0, 35.0, 85.0])
def test_thermal_settles_at_the_talus_angle(talus, tmp_path):
    h, dx = world(64)
    h = h * 3.0
    # 5000+ iterations of the rule at 31 m cells
    out, m, _ = run_stage(h, dx, tmp_path, talus_angle_deg=talus, thermal_years=2.5e6, storm_hours=0.0)
    assert m["thermal_iterations"] >= 5000
    assert m["thermal_max_excess_deg"] <= TALUS_TOL_DEG, m["thermal_max_excess_deg"]
    assert m["thermal_fraction_above_talus"] == 0.0
    again = slope_excess(out["erosion.height"].data, dx, talus, periodic=False)
    assert again["max_excess_deg"] <= TALUS_TOL_DEG
    if talus < 80:
        assert np.abs(out["erosion.change"].data[..., 0]).max() > 1.0


def test_nan_in_the_input_is_a_clear_error(tmp_path):
    h, dx = world(64)
    h = h.copy()
    h[5, 7] = np.nan
    with pytest.raises(InputError, match=r"erosion: the input height has 1 NaN.*row 5, column 7"):
        run_stage(h, dx, tmp_path, **SHORT)
    h[5, 7] = np.inf
    with pytest.raises(InputError, match="NaN or infinite"):
        run_stage(h, dx, tmp_path, **SHORT)


def test_the_largest_fixed_step_is_refused_before_running(tmp_path):
    h, dx = world(64)
    with pytest.raises(InputError, match=r"dt_s = 3600 s breaks the CFL limit.*dt_s <= 28.1 s"):
        run_stage(h, dx, tmp_path, dt_s=3600.0, **SHORT)


def test_a_fixed_step_that_breaks_cfl_later_is_stopped_with_the_step(tmp_path):
    """Just under the static limit the first steps run; when the flow speeds up
    the stage stops and names the parameter, the step and the step that would do."""
    h, dx = world(64)
    with pytest.raises(StageError, match=r"erosion: dt_s = 28 s breaks the CFL limit at step \d+: Courant number"):
        run_stage(h, dx, tmp_path, dt_s=28.0, **SHORT)


def test_a_fixed_step_under_the_limit_runs(tmp_path):
    h, dx = world(64)
    out, m, _ = run_stage(h, dx, tmp_path, dt_s=0.5, **SHORT)
    _check_clean(out, m, h)
    assert m["dt_min_s"] == m["dt_max_s"] == 0.5 and m["courant_max"] <= 0.9


def test_too_much_thermal_work_is_refused(tmp_path):
    h, dx = world(64)
    with pytest.raises(InputError, match="thermal_years .* iterations of the talus rule"):
        run_stage(h, dx, tmp_path, thermal_years=1e7, scree_diffusivity_m2_per_year=1e6, **SHORT)


class _Sabotaged:
    """A device simulation that breaks at a given step, to see the stage stop."""

    def __init__(self, sim, at: int, what: str):
        self.sim, self.at, self.what, self.n = sim, at, what, 0
        self.rows, self.cols = sim.rows, sim.cols

    def step(self, k, want_wave=False):
        import pyopencl as cl

        self.sim.step(k, want_wave)
        self.n += 1
        if self.n == self.at:
            buf = self.sim.W[self.sim.cw] if self.what == "nan_water" else self.sim.dT[self.sim.cd]
            i = self.sim.index(5, 7)
            bad = np.array([50.0 if self.what == "mass" else np.nan], np.float32)
            cl.enqueue_copy(self.sim.queue, buf, bad, dst_offset=4 * i)

    def __getattr__(self, name):
        return getattr(self.sim, name)


@pytest.mark.parametrize("what, message", [
    ("nan", r"erosion: numerical blow-up at step 48: \d+ cells with NaN or Inf \(cfl = 0.5"),
    # a NaN depth is clamped to 0 by the next step (NaN > 0 is false); the water budget sees the loss
    ("nan_water", r"erosion: water budget drifted by .* at step 48 \(rain_mm_per_hour / dt_s / cfl\)"),
    ("mass", r"erosion: terrain \+ sediment budget drifted by .* at step 48"),
])
def test_a_blow_up_stops_the_stage_naming_the_step(cl_env, what, message):
    from stages.erosion import simulate
    from stages.erosion.device import DeviceSim

    from .helpers import physics

    h, dx = world(64)
    ph = physics(dx, "closed")
    sim = _Sabotaged(DeviceSim(cl_env, h, ph), at=40, what=what)
    with pytest.raises(StageError, match=message):
        simulate.run(sim, ph, simulate.Plan(max_steps=200))
