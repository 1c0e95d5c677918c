"""Property 7: every kernel agrees with its numpy reference (reference.py) on
small grids.

Tolerance: exact, bit for bit. The kernels use only IEEE-754 basic operations
(+ - * / sqrt and compare-select), in the same order, with FP contraction off
and correctly rounded division and square root, so the two must produce the
same float32 values. Any difference is a real discrepancy in the maths, not
round-off. Grids of 37 x 29 cells exercise the padding and the lanes beyond the
grid edge; every boundary condition is covered."""
from __future__ import annotations

import numpy as np
import pytest

from stages.erosion import simulate
from stages.erosion.device import DeviceSim
from stages.erosion.physics import step_constants
from stages.erosion.reference import TINY, ReferenceSim, flux, thermal_step, update

from .helpers import physics, world

pytestmark = pytest.mark.every_device  # kernels against their references on each runtime

FIELDS = ("dT", "W", "S", "M", "vx", "vz", "F")


def _start(boundary: str, rows: int = 29, cols: int = 37):
    h, dx = world(64)
    h = h[:rows, :cols].copy()
    rng = np.random.default_rng(3)
    w0 = (rng.random(h.shape) * 0.3).astype(np.float32)
    s0 = (rng.random(h.shape) * 0.01 * (w0 > 0.1)).astype(np.float32)
    ph = physics(dx, boundary, bank_diffusivity=0.0)
    return h, dx, w0, s0, ph


@pytest.mark.parametrize("boundary", ["closed", "open", "periodic"])
def test_steps_match_reference_bit_for_bit(cl_env, boundary):
    h, dx, w0, s0, ph = _start(boundary)
    dev = DeviceSim(cl_env, h, ph, water=w0, sediment=s0)
    ref = ReferenceSim(h, ph, water=w0, sediment=s0)
    for n in range(40):
        k = step_constants(ph, 0.3 + 0.01 * (n % 7))
        dev.step(k, want_wave=(n % 5 == 4))
        ref.step(k, want_wave=(n % 5 == 4))
        if n % 10 == 9:
            dev.thermal(1, wet_min=0.01)  # bank slumping: only into wet cells
            ref.thermal(1, wet_min=0.01)
    fd, fr = dev.fields(), ref.fields()
    for name in FIELDS:
        np.testing.assert_array_equal(fd[name], fr[name], err_msg=f"{boundary}: {name}")
    dd, dr = dev.diag(), ref.diag()
    assert dd.wave == dr.wave and dd.wmin == dr.wmin and dd.smin == dr.smin and dd.wmax == dr.wmax
    for field in ("water", "dT", "sediment", "evaporated", "abs_dT"):  # the same float64 sums in the same order
        assert getattr(dd, field) == getattr(dr, field), field
    for field in ("out_water", "out_sediment"):  # per face on the device, per side in numpy
        assert getattr(dd, field) == pytest.approx(getattr(dr, field), rel=1e-12, abs=1e-12), field


@pytest.mark.parametrize("cols", [37, 40, 8, 1])
def test_diagnostics_count_non_finite_cells_and_leave_them_out(cl_env, cols):
    """The diagnostics kernel reads 8 cells at a time: rows whose length is not
    a multiple of 8 end in lanes past the grid, which must count for nothing.
    Non-finite cells are counted and left out of the sums, the same as numpy."""
    h, dx, w0, s0, ph = _start("open", 29, cols)
    w0[3, cols - 1] = np.nan
    w0[7, 0] = np.inf
    s0[11, cols // 2] = -np.inf
    s0[3, cols - 1] = np.nan  # the same cell twice: counted once
    dev = DeviceSim(cl_env, h, ph, water=w0, sediment=s0)
    ref = ReferenceSim(h, ph, water=w0, sediment=s0)
    dd, dr = dev.diag(), ref.diag()
    assert dd.nonfinite == dr.nonfinite == 3
    ok = np.isfinite(w0) & np.isfinite(s0)
    assert dd.water == dr.water and dd.sediment == dr.sediment
    assert dd.water == pytest.approx(float(w0[ok].astype(np.float64).sum()), rel=1e-12)
    assert dd.wmin == float(w0[ok].min()) and dd.wmax == float(w0[ok].max()) and dd.smin == float(s0[ok].min())


@pytest.mark.parametrize("boundary", ["closed", "periodic"])
def test_thermal_matches_reference_bit_for_bit(cl_env, boundary):
    h, dx, _, _, ph = _start(boundary)
    h = h * 4.0  # steep: most cells exceed the talus angle
    dev, ref = DeviceSim(cl_env, h, ph), ReferenceSim(h, ph)
    dev.thermal(25)
    ref.thermal(25)
    np.testing.assert_array_equal(dev.fields()["dT"], ref.fields()["dT"])
    assert np.abs(ref.dT).max() > 1.0  # something happened


def test_whole_run_matches_reference(cl_env):
    """The same driver (adaptive dt, checks, thermal phase) over both backends."""
    h, dx, _, _, ph = _start("open", 24, 24)
    plan = simulate.Plan(thermal_iterations=3, duration_s=0.0, max_steps=120, check_every=16)
    md = simulate.run(DeviceSim(cl_env, h, ph), ph, plan)
    mr = simulate.run(ReferenceSim(h, ph), ph, plan)
    for key in ("steps", "simulated_seconds", "dt_min_s", "dt_max_s", "courant_max", "budget_water_stored",
                "budget_outflow", "budget_sediment_suspended"):
        assert md[key] == pytest.approx(mr[key], rel=1e-12), key


def test_reference_pieces_are_sane():
    """The numpy twin itself: a single pipe step on a two-cell tilt sends water
    downhill and conserves it; a talus step moves scree off a spike."""
    Tb = np.array([[1.0, 0.0]], np.float32)
    z = np.zeros_like(Tb)
    W = np.array([[0.5, 0.0]], np.float32)
    ph = physics(10.0, "closed")
    k = step_constants(ph, 0.1)
    F, _ = flux(Tb, z, W, np.zeros((1, 2, 4), np.float32), k, "closed")
    assert F[0, 0, 0] > 0 and F[0, 0, 1:].sum() == 0 and F[0, 1].sum() == 0  # only east, only from the high cell
    dT, W1, S1, *_ = update(Tb, z, W, z, F, z, z, step_constants(ph, 0.1), "closed")
    lost = 2 * float(k.rain_dt) - 2 * float(k.evap_dt)
    assert float(W1.astype(np.float64).sum()) == pytest.approx(0.5 + lost, abs=1e-7)
    h = np.array([[0.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 0.0]], np.float32)
    d = thermal_step(h, np.zeros_like(h), physics(10.0, "closed"))
    assert d[1, 1] < 0 and np.all(np.delete(d.ravel(), 4) > 0)
    assert float(d.astype(np.float64).sum()) == pytest.approx(0.0, abs=1e-4)


@pytest.mark.parametrize("boundary", ["closed", "open", "periodic"])
def test_outflow_never_exceeds_the_water_a_cell_holds(boundary):
    """The sediment a face carries is S (q dt/dx) / W with no cap of its own:
    it relies on flux leaving every cell more water than sum q dt/dx (after
    the roundings of q and of the sum), and on cells with subnormal water
    sending nothing. Checked on violent states: 1000 m steps, water from
    subnormal to 50 m, large stored fluxes, long and short time steps."""
    rng = np.random.default_rng(11)
    shape = (24, 31)
    for dt in (0.02, 0.5, 5.0):
        for trial in range(4):
            Tb = (rng.random(shape) * 1000.0 * (rng.random(shape) < 0.3)).astype(np.float32)
            W = (10.0 ** rng.uniform(-44, 1.7, shape)).astype(np.float32)
            W[rng.random(shape) < 0.2] = 0.0
            F = (rng.random(shape + (4,)) * 10.0 ** rng.uniform(-3, 3)).astype(np.float32)
            ph = physics(10.0, boundary)
            k = step_constants(ph, dt)
            Fn, _ = flux(Tb, np.zeros_like(Tb), W, F, k, boundary)
            c = k.c_dt_dx
            sumqc = (((Fn[..., 0] + Fn[..., 1]) + Fn[..., 2]) + Fn[..., 3]) * c
            assert np.all(sumqc <= W), (dt, trial, float(np.max(sumqc - W)))
            assert np.all(Fn[W <= TINY] == 0), (dt, trial)
            assert np.any(Fn > 0)
