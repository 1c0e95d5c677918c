"""The erosion on a tiled world (stages/erosion/tiled.py) and geological
time on its own grid (geological_cell_m): the pieces a tile computes are the
whole map's cells bit for bit, and geology on coarser blocks keeps the
volume and stays near the fine solve. The tiled bake's files against the
untiled ones: tests/pipeline/test_tiled_bake.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.contract import CheckContext, GridInfo
from pipeline.tiles import tiles_of
from stages.erosion import ErosionParams
from stages.erosion.coarse_grid import (Prolongation, block_mean_of_smooth, block_mean_of_linear, coarse_span,
                                        prolong_linear)
from pipeline.opencl import get_cl
from stages.erosion.stage import check
from stages.erosion.steps import geology, slope_excess, slope_excess_counts, slope_excess_of, solve_geology
from stages.erosion.tiled import whole_reason
from worldlib.terrain.blocks import block_mean

from .helpers import run_stage, world

WINDOWS = [(0, 0, 5, 7), (3, 2, 11, 13), (17, 9, 20, 1), (1, 1, 1, 1)]


@pytest.mark.parametrize("f", [2, 3, 4, 8])
def test_a_prolongations_window_is_the_whole_maps_cells(f):
    rng = np.random.default_rng(f)
    c = rng.normal(size=(9, 7)) * 5.0
    for pro in (Prolongation.linear(c, f), Prolongation.conserving(c, f),
                Prolongation.positive(np.abs(c) * (rng.random(c.shape) > 0.4), f)):
        whole = pro.whole()
        assert whole.shape == (9 * f, 7 * f)
        for r0, c0, rows, cols in WINDOWS + [(9 * f - 3, 7 * f - 5, 3, 5)]:
            rows, cols = min(rows, 9 * f - r0), min(cols, 7 * f - c0)
            want = whole[r0:r0 + rows, c0:c0 + cols]
            assert np.array_equal(pro.window(r0, c0, rows, cols), want)
            part = pro.part(r0, c0, rows, cols)  # what a tile is sent: a few coarse cells
            assert part.field.shape[0] <= rows // f + 5 and part.field.shape[1] <= cols // f + 5
            assert np.array_equal(part.window(r0, c0, rows, cols), want)


def test_the_coarse_block_means_of_the_interpolation_are_the_fine_ones():
    rng = np.random.default_rng(1)
    c = rng.normal(size=(6, 10))
    for f in (2, 3, 5, 8):
        np.testing.assert_allclose(block_mean_of_linear(c, f), block_mean(prolong_linear(c, f), f), atol=1e-12)
        smooth = Prolongation(f, c, None, None, c.shape, smooth=True).whole()
        np.testing.assert_allclose(block_mean_of_smooth(c, f), block_mean(smooth, f), atol=1e-12)
    assert coarse_span(0, 8, 8, 4) == (0, 2) and coarse_span(8, 8, 8, 4) == (0, 3) and coarse_span(1, 1, 4, 9) == (0, 2)
    assert coarse_span(0, 8, 8, 4, smooth=True) == (0, 3) and coarse_span(8, 8, 8, 9, smooth=True) == (0, 4)


def test_the_conserving_prolongation_has_no_kinks_at_the_coarse_cells():
    """Its gradient is continuous (C2): a hillshade of 1 m cells shows no 8 m
    grid. The bilinear one's slope jumps at every coarse cell centre: its
    largest change of slope between neighbouring cells is several times the
    B-spline's on this smooth change."""
    x = np.linspace(0.0, 3.0, 12)
    c = np.add.outer(np.sin(x) * 40.0, np.cos(x) * 25.0)  # a smooth coarse change, metres
    f = 8
    kink = {}
    for name, pro in (("smooth", Prolongation.conserving(c, f)), ("linear", Prolongation.linear(c, f))):
        second = np.abs(np.diff(pro.whole(), n=2, axis=1))[:, 2 * f:-2 * f]  # slope changes along the rows
        kink[name] = second.max()
    assert kink["smooth"] < 0.35 * kink["linear"], kink


def test_a_tiles_block_means_are_the_whole_maps():
    a = np.random.default_rng(2).normal(size=(48, 40)) * 1000.0
    whole = block_mean(a, 4)
    for r0, c0, rows, cols in ((0, 0, 16, 16), (16, 24, 32, 16), (44, 36, 4, 4)):
        assert np.array_equal(block_mean(a[r0:r0 + rows, c0:c0 + cols], 4), whole[r0 // 4:(r0 + rows) // 4,
                                                                                  c0 // 4:(c0 + cols) // 4])


def test_the_tiles_slope_pairs_add_up_to_the_whole_maps():
    h = np.random.default_rng(4).normal(size=(70, 45)).cumsum(axis=0) * 3.0
    for periodic in (False, True):
        want = slope_excess(h, 2.0, 35.0, periodic)
        assert want["fraction_above_tolerance"] > 0
        if periodic:
            continue
        counts = []
        for t in tiles_of(h.shape, 16):  # the tiling's own 16-cell stand-in for a small map
            r0, c0, rows, cols = t.window(1)
            counts.append(slope_excess_counts(h[r0:r0 + rows, c0:c0 + cols], t.inner(1), 2.0, 35.0))
        assert slope_excess_of(*counts) == want


def test_why_a_world_runs_whole():
    p = ErosionParams(geological_years=1e6, geological_cell_m=8.0, storm_cell_m=8.0)
    assert whole_reason(p, (2048, 2048), 4.0, 512) is None
    assert "own cells" in whole_reason(p, (1024, 1024), 8.0, 512)  # geology on the terrain's cells
    assert "periodic" in whole_reason(p.model_copy(update={"boundary": "periodic"}), (2048, 2048), 4.0, 512)
    assert "storm" in whole_reason(ErosionParams(storm_cell_m=0.0), (2048, 2048), 4.0, 512)
    assert "divide" in whole_reason(p.model_copy(update={"storm_cell_m": 12.0, "geological_years": 0.0}),
                                    (2049, 2049), 4.0, 512)  # blocks of 3


def test_a_tiled_world_is_checked_for_a_tile_and_the_coarse_grids():
    p = ErosionParams(geological_years=1e6, geological_cell_m=8.0, storm_cell_m=8.0)
    inputs = {"height": GridInfo((8192, 8192), 1.0, "heightmap.resolution")}
    whole = check(p, CheckContext(seed=0, project_root=Path("."), inputs=inputs))
    tiled = check(p, CheckContext(seed=0, project_root=Path("."), inputs=inputs, tile_cells=1024))
    assert whole.memory_bytes == 296 * 8192 ** 2  # the storm and geology state of every cell
    assert tiled.memory_bytes < 0.5e9 and "tile" in tiled.memory_how


GEOLOGY = dict(boundary="open", storm_hours=0.0, thermal_years=0.0, geological_years=1.0e6,
               geological_step_years=1.0e5, stream_power_k=4e-5, uplift_mm_per_year=0.1, geological_routing="mfd",
               geological_flat_routing="distance", geological_lake_fill=True, channel_specific_area_m=250.0,
               hillslope_diffusivity_m2_per_year=0.03, critical_slope_deg=33.0, incision_width_m=8.0)


def test_geology_on_its_own_grid_keeps_the_volume_and_follows_the_fine_solve(tmp_path):
    """128 x 128 cells of 4 m, a million years as the default world's: on 8 m
    blocks the change correlates 0.997 with the solve on the 4 m cells,
    relative RMS 0.09 (measured; 256 x 256: 0.987 and 0.16, on 16 m blocks
    0.975 and 0.22), about a tenth of the time."""
    h, dx = world(128, size_m=512.0, relief_m=128.0, seed=7)
    fine, fm, _ = run_stage(h, dx, tmp_path / "fine", **GEOLOGY)
    coarse, cm, _ = run_stage(h, dx, tmp_path / "coarse", geological_cell_m=8.0, **GEOLOGY)
    assert cm["geological_cell_factor"] == 2 and cm["geological_cell_size_m"] == 8.0
    assert "geological_cell_factor" not in fm and fm["geological_cell_size_m"] == 4.0
    a = coarse["erosion.height"].channel("height").astype(np.float64) - h
    b = fine["erosion.height"].channel("height").astype(np.float64) - h
    corr = np.corrcoef(a.ravel(), b.ravel())[0, 1]
    rel = np.sqrt(((a - b) ** 2).mean() / (b ** 2).mean())
    assert corr > 0.99 and rel < 0.15, (corr, rel)
    # the fine cells carry the coarse solve: block by block its heights' B-spline, the map's volume to float32
    params = ErosionParams(geological_cell_m=8.0, **GEOLOGY)
    h32 = h.astype(np.float32)
    after, _ = geology(get_cl(), h32, dx, params, lambda f, m: None, seed=1)  # 4 m cells: no microrelief
    coarse_h = block_mean(h32, 2)
    solved = solve_geology(get_cl(), coarse_h, 2 * dx, params, lambda f, m: None).height
    change = block_mean(after.astype(np.float64) - h32, 2)
    assert np.abs(change).max() > 1.0
    np.testing.assert_allclose(change, block_mean_of_smooth(solved, 2) - coarse_h, rtol=0, atol=3e-5)
    assert abs(change.sum() - (solved - coarse_h).sum()) <= 1e-6 * np.abs(solved - coarse_h).sum()


def test_a_tile_with_no_slope_above_the_talus_angle_is_left_as_the_kernels_leave_it():
    """The tiled rounds skip a window where no neighbours differ by more than
    the talus threshold: the device's iterations leave its change bit for bit."""
    from stages.erosion.device import DeviceSim
    from stages.erosion.physics import talus_thresholds
    from stages.erosion.params import physics_for
    from stages.erosion.tiled import _any_above_talus

    ph = physics_for(ErosionParams(talus_angle_deg=40.0), 2.0)
    t_ax, t_dg = talus_thresholds(ph)
    rng = np.random.default_rng(5)
    gentle = (np.add.outer(np.arange(40.0), np.arange(36.0)) * 0.9).astype(np.float32)  # 0.9 m per 2 m cell: 24 deg
    change = (rng.normal(size=gentle.shape) * 0.01).astype(np.float32)
    assert not _any_above_talus(gentle, change, t_ax, t_dg)
    sim = DeviceSim(get_cl(), gentle, ph, change=change, thermal_only=True)
    sim.thermal(8)
    assert np.array_equal(sim.change(), change)
    steep = gentle.copy()
    steep[20, 18] += 5.0  # one spike: 5 m over 2 m cells
    assert _any_above_talus(steep, change, t_ax, t_dg)
    sim = DeviceSim(get_cl(), steep, ph, change=change, thermal_only=True)
    sim.thermal(8)
    assert not np.array_equal(sim.change(), change)
