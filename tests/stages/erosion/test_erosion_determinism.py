"""Properties 5 and 6: identical results across runs and work-group sizes (and
vector widths); the same world at two resolutions agrees after low-pass.

Resolution tolerance (measured, stated in the README of the bench output):
the change maps of the same analytic world at 64^2 and 256^2 (31 m and 8 m
cells), each low-passed with a 125 m Gaussian and compared on the coarse grid:
hydraulic erosion correlates at 0.95-0.96 with a relative L2 difference of
0.27-0.35 (0.1-0.3 h storms; 128^2 vs 512^2 gives the same); thermal weathering
correlates at 0.99 (relative L2 0.19). Tested at correlation >= 0.9 / 0.97 and
relative L2 <= 0.45 / 0.3. Erosion is not pointwise grid-convergent (channels
are a cell or two wide at every resolution), so the comparison is of the
low-passed fields, as in the issue."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from pipeline.opencl import x86_avx512
from stages.erosion import simulate
from stages.erosion.device import DeviceSim
from stages.erosion.reference import synthetic_world

from .helpers import physics, run_stage, world


def _fields(cl_env, h, ph, local, vw=None, steps=150, thermal=5, **code_path):
    sim = DeviceSim(cl_env, h, ph, local=local, vw=vw, **code_path)
    simulate.run(sim, ph, simulate.Plan(thermal_iterations=thermal, max_steps=steps))
    return sim.fields()


@pytest.mark.every_device
@pytest.mark.parametrize("boundary", ["open", "periodic"])
def test_identical_across_runs_work_group_sizes_and_vector_widths(cl_env, boundary):
    h, dx = world(96)
    h = h[:80, :90].copy()  # not a multiple of any work-group size
    ph = physics(dx, boundary, bank_diffusivity=2.0)  # bank slumping on too
    base = _fields(cl_env, h, ph, (8, 1))  # the defaults: 16 (or 8) cells per work-item in the storm, 8 in the talus rule
    variants = [((8, 1), 8), ((1, 1), 8), ((4, 4), 8), ((32, 1), 8), ((2, 8), 8), ((4, 1), 16), ((1, 2), 16)]
    for local, vw in variants:
        other = _fields(cl_env, h, ph, local, vw)
        for name in base:
            assert np.array_equal(base[name], other[name]), f"{name} differs with local {local}, vw {vw}"
    # the storm's code paths: tiles of nr rows by at most nv vectors (values shared inside a
    # tile, computed afresh at its edges; 80 rows are no multiple of 3 or 7), and AVX-512
    # where this CPU has it
    paths = [dict(nv=1), dict(nv=3, vw=8), dict(nv=2, avx512=False), dict(nv=1, avx512=False, vw=16),
             dict(nr=1), dict(nr=3, nv=2), dict(nr=7, nv=1, vw=8), dict(nr=80)]
    if x86_avx512(cl_env.device):
        paths += [dict(nv=1, avx512=True), dict(nv=4, avx512=True, vw=8)]
    for path in paths:
        other = _fields(cl_env, h, ph, (8, 1), **path)
        for name in base:
            assert np.array_equal(base[name], other[name]), f"{name} differs with {path}"
    assert np.abs(base["dT"]).max() > 0 and base["W"].max() > 0


def test_stage_outputs_identical_across_runs(tmp_path):
    h, dx = world(64)
    a, ma, _ = run_stage(h, dx, tmp_path, storm_hours=0.05)
    b, mb, _ = run_stage(h, dx, tmp_path, storm_hours=0.05)
    for name in a:
        x, y = a[name], b[name]
        x, y = (x.data, y.data) if hasattr(x, "data") else (x, y)
        assert x.tobytes() == y.tobytes(), name
    assert ma["steps"] == mb["steps"] and ma["dt_mean_s"] == mb["dt_mean_s"]


def _lowpassed_change(size, n, sigma_m, tmp_path, **params):
    h = synthetic_world(n, size_m=size, relief_m=0.15 * size, seed=7, min_wavelength_m=size / 32)
    out, m, _ = run_stage(h, size / n, tmp_path, **params)
    c = out["erosion.change"].data[..., 0].astype(np.float64)
    return gaussian_filter(c, sigma_m / (size / n), mode="nearest"), m


@pytest.mark.parametrize("what", ["hydraulic", "thermal"])
def test_resolution_independence(what, tmp_path):
    size, n, f, sigma = 2000.0, 64, 4, 125.0
    params = dict(thermal_years=0, storm_hours=0.1) if what == "hydraulic" else dict(thermal_years=3000, storm_hours=0)
    coarse, mc = _lowpassed_change(size, n, sigma, tmp_path, **params)
    fine, mf = _lowpassed_change(size, n * f, sigma, tmp_path, **params)
    fine = fine.reshape(n, f, n, f).mean(axis=(1, 3))
    rel = np.linalg.norm(coarse - fine) / np.linalg.norm(fine)
    corr = np.corrcoef(coarse.ravel(), fine.ravel())[0, 1]
    min_corr, max_rel = (0.9, 0.45) if what == "hydraulic" else (0.97, 0.3)
    assert corr >= min_corr and rel <= max_rel, (what, corr, rel)
    assert np.abs(fine).max() > (0.005 if what == "hydraulic" else 0.5)  # something to compare
    if what == "thermal":  # the same years are 16x the iterations on 4x finer cells
        assert mf["thermal_iterations"] >= 14 * mc["thermal_iterations"]
