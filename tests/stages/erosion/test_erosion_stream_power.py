"""Stream-power erosion (Braun and Willett 2013): the kernel against its
pure-Python reference, and fastscapelib's test protocol (test_spl.cpp):
steady-state slopes, mass balance at base level, extreme K and dt."""

import numpy as np
import pytest

from stages.erosion import stream_power as sp
from worldlib.flow import device as flow


def channel(n_cells: int) -> np.ndarray:
    """A 1 x n river draining west to a base-level cell at column 0."""
    code = np.full((1, n_cells), 6, np.int8)
    code[0, 0] = -1
    return code


@pytest.mark.parametrize("n_exp", [1.0, 2.0, 4.0])
def test_steady_state_slope(cl_env, n_exp):
    """S = (U/K)^(1/n) A^(-m/n) along the river at steady state (rtol 1e-5,
    fastscapelib's tolerance): the discrete slope (h_i - h_r) / dx."""
    dx, k, m, u = 100.0, 1e-4, 0.4, 1e-3
    code = channel(50)
    area = flow.accumulate(cl_env, code).astype(np.float64) * dx * dx
    solver = sp._DeviceSolver(cl_env, 1, 50)
    h = np.zeros((1, 50))
    dt = 1e5
    for _ in range(400):
        h_up = h + np.where(code < 0, 0.0, u * dt)
        h, _ = solver.step(h_up, code, area, dx, k * dt, m, n_exp)
    slope = (h[0, 1:] - h[0, :-1]) / dx
    want = (u / k) ** (1 / n_exp) * area[0, 1:] ** (-m / n_exp)
    np.testing.assert_allclose(slope, want, rtol=1e-5, atol=1e-5)


@pytest.mark.every_device
@pytest.mark.parametrize("n_exp", [1.0, 1.5, 4.0])
def test_kernel_equals_reference(cl_env, n_exp):
    rng = np.random.default_rng(5)
    h = rng.random((23, 31)) * 200.0
    from worldlib.flow import reference as ref

    kind = ref.cell_kinds(h.astype(np.float32))
    code = flow.d8(cl_env, flow.fill(cl_env, ref.canonical(h.astype(np.float32)), kind, eps=True), kind, 10.0)
    area = flow.accumulate(cl_env, code).astype(np.float64) * 100.0
    got, it_dev = sp._DeviceSolver(cl_env, 23, 31).step(h, code, area, 10.0, 3e-3, 0.5, n_exp)
    want, it_ref = sp.reference_step(h, code, area, 10.0, 3e-3, 0.5, n_exp)
    # same float64 operations; pow may differ in the last ulp between libms
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    assert it_dev == it_ref
    assert (got <= h + 1e-9).all()  # the solve never raises a cell


def test_mass_balance_and_run(cl_env):
    """Eroded volume arrives at base level (exact integer accumulation); the
    terrain volume changes by uplift - outflow in float64."""
    from stages.heightmap.stage import HeightmapParams, heights

    h, _ = heights(cl_env, HeightmapParams(resolution=64, size_m=6400.0, wavelength_m=3200.0), 3)
    h = h.astype(np.float64)
    res = sp.run(cl_env, h, 100.0, years=2e5, dt_years=2e4, k=2e-5, m=0.45, n_exp=1.0, uplift_m_per_year=1e-3)
    assert res.steps == 10 and res.eroded_m3 > 0
    assert res.budget_relative_error <= 1e-12
    dvol = float((res.height - h).sum()) * 100.0 * 100.0
    assert abs(dvol - (res.uplifted_m3 - res.out_m3)) <= 1e-9 * max(res.uplifted_m3, res.out_m3)
    # the same run through the pure-Python solve
    ref_res = sp.run(cl_env, h, 100.0, years=2e5, dt_years=2e4, k=2e-5, m=0.45, n_exp=1.0, uplift_m_per_year=1e-3,
                     step_fn=sp.reference_step)
    np.testing.assert_allclose(res.height, ref_res.height, rtol=0, atol=1e-6)


@pytest.mark.parametrize("n_exp", [1.0, 2.0])
def test_extreme_k_dt_and_hole(cl_env, n_exp):
    """K = 1e8 and dt = 1e8 (fastscapelib's stress values) over a -1000 m
    hole: finite; without uplift the plateau is cut down to base level
    (500 m at the edges) and the hole, a depression, is not eroded; with
    uplift (100 km per step) everything stays finite and at or above base level."""
    h = np.full((20, 20), 500.0)
    h[5:9, 5:9] = 900.0
    h[10:14, 10:14] = -1000.0
    res = sp.run(cl_env, h, 10.0, years=2e8, dt_years=1e8, k=1e8, m=0.5, n_exp=n_exp, uplift_m_per_year=0.0)
    assert np.isfinite(res.height).all()
    np.testing.assert_array_equal(res.height[10:14, 10:14], -1000.0)
    assert res.height[5:9, 5:9].max() < 500.0 + 1e-3  # cut down to (nearly) base level
    up = sp.run(cl_env, h, 10.0, years=2e8, dt_years=1e8, k=1e8, m=0.5, n_exp=n_exp, uplift_m_per_year=1e-3)
    assert np.isfinite(up.height).all() and up.height.min() >= -1000.0
    assert up.budget_relative_error <= 1e-12


@pytest.mark.parametrize("n_exp", [1.0, 2.0])
def test_equals_fastscapelib_on_a_draining_surface(cl_env, n_exp):
    """fastscapelib (RasterGrid with fixed-value edges, SingleFlowRouter +
    PFloodSinkResolver, SPLEroder) on a rough cone with no depression, 5
    steps with uplift: the same heights to 1e-9 m. (Where the terrain has
    depressions the two route across the filled flats with different
    epsilon patterns, so they differ there: see bench/stream_power.py.)"""
    fs = pytest.importorskip("fastscapelib")
    n, dx, k, m, u, dt = 48, 100.0, 2e-5, 0.45, 1e-3, 2e4
    yy, xx = np.mgrid[0:n, 0:n]
    h0 = 1000.0 - np.hypot(xx - n / 2, yy - n / 2) * 5.0 + np.random.default_rng(1).random((n, n)) * 0.5
    grid = fs.RasterGrid([n, n], [dx, dx], fs.NodeStatus.FIXED_VALUE)
    graph = fs.FlowGraph(grid, [fs.SingleFlowRouter(), fs.PFloodSinkResolver()])
    eroder = fs.SPLEroder(graph, k_coef=k, area_exp=m, slope_exp=n_exp, tolerance=1e-12)
    uplift = np.full((n, n), u)
    uplift[[0, -1], :] = 0.0
    uplift[:, [0, -1]] = 0.0
    h = h0.copy()
    for _ in range(5):
        up = h + dt * uplift
        graph.update_routes(up)
        h = up - eroder.erode(up, graph.accumulate(1.0), dt)
    ours = sp.run(cl_env, h0, dx, years=5 * dt, dt_years=dt, k=k, m=m, n_exp=n_exp, uplift_m_per_year=u)
    assert np.abs(ours.height - h).max() <= 1e-9
    assert (h0 + 5 * dt * uplift - h).max() > 10.0  # real incision happened



def test_incision_by_flow_per_metre_of_width_is_the_same_at_any_cell_size(cl_env):
    """incision_width_m: K (w A / dx)^m S. On a tilted plane the mfd area per
    metre of contour A / dx is the upslope length L whatever the cells, so
    one short step lowers the plane by K (w L)^m S dt on 20 m and on 10 m
    cells alike (with the cell's own A the finer grid cuts 2^-m as deep); at
    dx = w the width changes nothing; d8 ignores it (one cell carries all the flow)."""
    k, m, slope, dt = 2e-5, 0.45, 0.05, 1e3
    assert sp.incision_k(k, m, 8.0, 0.0) == k and sp.incision_k(k, m, 8.0, 8.0) == k
    assert sp.incision_k(k, m, 4.0, 8.0) == pytest.approx(k * 2.0 ** m, rel=1e-15)
    at = np.array([200.0, 400.0, 600.0])  # m east of the base-level edge at x = 0 (the plane's foot)

    def lowering(dx: float, width: float) -> np.ndarray:
        rows, cols = int(400 / dx), int(800 / dx)
        x = (np.arange(cols) + 0.5) * dx
        h = np.tile(slope * x, (rows, 1)) + 1.0  # rising east from the base-level edge
        res = sp.run(cl_env, h, dx, dt, dt, k, m, 1.0, 0.0, routing="mfd", incision_width_m=width)
        assert res.stats["stream_power_k_used"] == pytest.approx(sp.incision_k(k, m, dx, width), rel=1e-15)
        return np.interp(at, x, (h - res.height)[rows // 2])

    coarse, fine = lowering(20.0, 20.0), lowering(10.0, 20.0)
    np.testing.assert_allclose(fine, coarse, rtol=0.05)
    np.testing.assert_allclose(fine, k * (20.0 * (800.0 - at)) ** m * slope * dt, rtol=0.1)  # L from the east edge
    own = lowering(10.0, 0.0)  # the cell's own A on the finer grid: shallower
    np.testing.assert_allclose(own / fine, 2.0 ** -m, rtol=0.05)
    d8 = sp.run(cl_env, np.tile(np.arange(8.0), (6, 1)) + 1.0, 10.0, 1e5, 1e5, k, m, 1.0, 1e-3, routing="d8",
                incision_width_m=20.0)
    assert d8.stats["stream_power_k_used"] == k
