"""Geological time: the implicit isotropic hillslope diffusion against its
dense reference, Rho8 routing, and a landscape evolution run that keeps its
volume budget and carves a valley network."""
import math

import numpy as np
import pytest

from worldlib.terrain.stats import grid_anisotropy
from stages.erosion import hillslope
from stages.erosion import stream_power as sp


@pytest.mark.parametrize("shape", [(7, 9), (12, 5)])
def test_diffusion_equals_dense_reference(shape):
    rng = np.random.default_rng(2)
    h = rng.random(shape) * 50.0
    got = hillslope.step(h, 4.0, 300.0)
    want = hillslope.reference_step(h, 4.0, 300.0)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(got[0], h[0])  # the edge is base level
    np.testing.assert_array_equal(got[:, -1], h[:, -1])


def test_diffusion_is_stable_and_isotropic_at_huge_steps():
    """A narrow bump spreads into a round hill: no overshoot, no new extremes,
    the same width along the axes and the diagonals."""
    n = 129
    h = np.zeros((n, n))
    h[n // 2, n // 2] = 1000.0
    out = hillslope.step(h, 10.0, 1e6)  # D dt / dx^2 = 1e4
    assert np.isfinite(out).all() and out.min() >= -1e-9 and out.max() < 1000.0
    c = n // 2
    axis = out[c, c + 20]
    diagonal = out[c + round(20 / math.sqrt(2)), c + round(20 / math.sqrt(2))]
    assert axis == pytest.approx(diagonal, rel=0.02)


def test_rho8_picks_downhill_and_mixes_axes_with_diagonals():
    """On a plane facing 22 degrees off east, D8 sends every cell east; Rho8
    sends a share diagonally (south-east), and every receiver is lower."""
    n = 40
    r, c = np.mgrid[0:n, 0:n].astype(float)
    a = math.radians(22.0)
    z = -(c * math.cos(a) + r * math.sin(a))
    interior = np.zeros((n, n), bool)
    interior[1:-1, 1:-1] = True
    code = sp.rho8(z, interior, 1.0, sp.counter_uniform(sp.RHO8_KEY, 0, n * n))
    inner = code[1:-1, 1:-1]
    assert set(np.unique(inner).tolist()) <= {2, 3}  # east or south-east
    share_diagonal = float((inner == 3).mean())
    assert 0.1 < share_diagonal < 0.9
    # deterministic: the same draws for the same key and step, others for the next step
    again = sp.rho8(z, interior, 1.0, sp.counter_uniform(sp.RHO8_KEY, 0, n * n))
    np.testing.assert_array_equal(code, again)
    other = sp.rho8(z, interior, 1.0, sp.counter_uniform(sp.RHO8_KEY, 1, n * n))
    assert (other != code).any()
    assert (code[~interior] == -1).all()


def test_landscape_evolution_keeps_its_budget_and_carves_valleys(cl_env):
    from stages.heightmap.stage import HeightmapParams, heights

    h, _ = heights(cl_env, HeightmapParams(resolution=96, size_m=1536.0, wavelength_m=768.0), 4)
    h = h.astype(np.float64)
    dx = 16.0
    res = sp.run(cl_env, h, dx, years=2e5, dt_years=2e4, k=2e-5, m=0.45, n_exp=1.0, uplift_m_per_year=5e-4,
                 routing="rho8", diffusivity_m2_per_year=1e-2, breach=True)
    assert res.steps == 10 and res.eroded_m3 > 0
    assert res.budget_relative_error <= 1e-12
    assert res.stats["stream_power_volume_budget_relative_error"] <= 1e-9
    assert np.isfinite(res.height).all()
    # deterministic
    again = sp.run(cl_env, h, dx, years=2e5, dt_years=2e4, k=2e-5, m=0.45, n_exp=1.0, uplift_m_per_year=5e-4,
                   routing="rho8", diffusivity_m2_per_year=1e-2, breach=True)
    np.testing.assert_array_equal(res.height, again.height)
    assert np.isfinite(grid_anisotropy(res.height))


@pytest.mark.every_device  # stream_power.cl's mfd_area and mfd_solve against their reference on each runtime
@pytest.mark.parametrize("p_exp, channel_area", [(1.1, 0.0), (4.0, 2000.0)])
def test_mfd_kernels_equal_reference(cl_env, p_exp, channel_area):
    from worldlib.flow import reference as ref

    rng = np.random.default_rng(11)
    h = rng.random((19, 26)) * 120.0
    kind = ref.cell_kinds(h.astype(np.float32))
    z = sp.routing_surface(cl_env, h, kind, "distance")
    got, area, _ = sp._DeviceMFDSolver(cl_env, 19, 26).step(h, z, kind == ref.INTERIOR, 10.0, 5e-3, 0.45, p_exp,
                                                            channel_area)
    want, area_ref, _ = sp.mfd_reference_step(h, z, kind == ref.INTERIOR, 10.0, 5e-3, 0.45, p_exp, channel_area)
    np.testing.assert_allclose(area, area_ref, rtol=1e-12)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert (got <= h + 1e-9).all()
    # every cell's area reaches base level once: the map's area arrives at the edge
    assert area[kind != ref.INTERIOR].sum() == pytest.approx(h.size * 100.0, rel=1e-12)


def test_distance_routing_drains_every_cell_and_converges_on_the_outlet(cl_env):
    """A round closed basin: every interior cell has a strictly lower
    neighbour on the routing surface, and the surface over the filled lake
    falls toward the outlet with the Euclidean distance."""
    from worldlib.flow import reference as ref

    n = 61
    r, c = np.mgrid[0:n, 0:n].astype(float)
    rad = np.hypot(r - 30, c - 30)
    h = 100.0 + 0.5 * np.minimum(rad, 25.0) ** 1.2 + 0.05 * (n - c)  # a bowl inside a tilted plane
    h[30, 55:] = h[30, 54] - 0.01 * np.arange(1, 7)  # a notch: the outlet to the east edge
    kind = ref.cell_kinds(h.astype(np.float32))
    z = sp.routing_surface(cl_env, h, kind, "distance").astype(np.float64)
    zp = np.pad(z, 1, constant_values=np.inf)
    lower = np.zeros((n, n), bool)
    for k in range(8):
        lower |= zp[1 + sp.DR[k]:1 + sp.DR[k] + n, 1 + sp.DC[k]:1 + sp.DC[k] + n] < z
    assert lower[kind == ref.INTERIOR].all()
    # inside the lake the surface rises with distance from the outlet side (east), like a cone
    assert z[30, 10] > z[30, 30] > z[30, 45]
    assert z[10, 30] > z[30, 45] and z[50, 30] > z[30, 45]
    assert z[10, 30] == pytest.approx(z[50, 30], abs=0.02)  # symmetric about the outlet's row


def test_mfd_landscape_evolution_budget_no_pits_and_determinism(cl_env):
    from stages.heightmap.stage import HeightmapParams, heights

    h, _ = heights(cl_env, HeightmapParams(resolution=80, size_m=1280.0, wavelength_m=640.0), 6)
    h = h.astype(np.float64)
    kw = dict(routing="mfd", diffusivity_m2_per_year=1e-2, mfd_exponent=1.1, flat_routing="distance",
              fill_lakes=True)
    res = sp.run(cl_env, h, 16.0, 2e5, 4e4, 2e-5, 0.45, 1.0, 5e-4, **kw)
    assert res.stats["stream_power_volume_budget_relative_error"] <= 1e-9
    assert res.stats["lake_fill_m3"] > 0  # the noise's depressions were filled
    z = res.height
    zp = np.pad(z, 1, constant_values=np.inf)
    lower = np.zeros(z.shape, bool)
    for k in range(8):
        lower |= zp[1 + sp.DR[k]:1 + sp.DR[k] + 80, 1 + sp.DC[k]:1 + sp.DC[k] + 80] < z
    assert lower[1:-1, 1:-1].all()  # no pit: every cell drains
    again = sp.run(cl_env, h, 16.0, 2e5, 4e4, 2e-5, 0.45, 1.0, 5e-4, **kw)
    np.testing.assert_array_equal(res.height, again.height)
    ref_run = sp.run(cl_env, h, 16.0, 2e5, 4e4, 2e-5, 0.45, 1.0, 5e-4, mfd_step_fn=sp.mfd_reference_step, **kw)
    np.testing.assert_allclose(res.height, ref_run.height, rtol=0, atol=1e-6)


def test_mfd_isotropy_makes_incision_on_a_plane_the_same_in_every_direction():
    """On a plane, the mfd solve's slope (sum of share * drop / distance over
    the lower neighbours) is 0.856 of the gradient down an axis but 0.776 at
    22.5 degrees; scaled by mfd_isotropy, the incision rate is K A^m |grad h|
    whatever the plane's direction."""
    from worldlib.flow import reference as ref

    n, dx, k_dt, gradient = 21, 10.0, 1e-3, 0.3
    r, c = np.mgrid[0:n, 0:n] * dx
    plain, scaled = [], []
    for aspect in (0.0, 10.0, 22.5, 30.0, 45.0, 112.5):
        a = np.radians(aspect)
        h = 1000.0 + gradient * (np.cos(a) * c + np.sin(a) * r)
        kind = ref.cell_kinds(h.astype(np.float32))
        z = h.astype(np.float32)
        inside = kind == ref.INTERIOR
        for scale, out in ((None, plain), (sp.mfd_isotropy(h, dx, 1.1), scaled)):
            new, _, _ = sp.mfd_reference_step(h, z, inside, dx, k_dt, 0.0, 1.1, 0.0, scale=scale)
            out.append((h - new)[n // 2, n // 2] / (k_dt * gradient))
    assert max(plain) / min(plain) > 1.09  # the bias the scale removes
    np.testing.assert_allclose(scaled, 1.0, rtol=2e-3)


def test_ascending_order_is_a_stable_argsort():
    rng = np.random.default_rng(5)
    z = np.round(rng.normal(0.0, 3.0, (31, 17)), 1).astype(np.float32)  # many ties, negatives
    z[0, :4] = [-0.0, 0.0, -0.0, np.float32(1e-40)]
    np.testing.assert_array_equal(sp.ascending_order(z), np.argsort(z.ravel(), kind="stable"))
