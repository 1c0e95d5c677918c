"""The stage contract: declaration, params, outputs, metrics, progress."""
from __future__ import annotations

import numpy as np
import pydantic
import pytest

from pipeline.contract import Params, Stage
from stages.erosion import STAGE, ErosionParams
from stages.erosion.params import physics_for, thermal_iterations

from .helpers import run_stage, world

GRIDS = {
    "erosion.height": ("height",),
    "erosion.water": ("water.depth",),
    "erosion.flow": ("flow.vx", "flow.vz", "flow.speed"),
    "erosion.sediment": ("sediment.depth",),
    "erosion.change": ("change.net", "change.wear", "change.deposition"),
    "erosion.moisture": ("moisture",),
}


def test_declaration():
    assert isinstance(STAGE, Stage) and STAGE.name == "erosion" and STAGE.uses_opencl and STAGE.uses_seed  # the microrelief
    assert [i.one_of for i in STAGE.inputs] == [("heightmap.height",)]
    declared = {a.name: a for a in STAGE.outputs}
    assert set(declared) == set(GRIDS) | {"erosion.hillshade"}
    for name, channels in GRIDS.items():
        assert declared[name].kind == "grid" and declared[name].channels == channels
    assert declared["erosion.height"].file == "height.exr"
    assert declared["erosion.hillshade"].kind == "image"


def test_params_are_physical_validated_and_frozen():
    p = ErosionParams()
    assert issubclass(ErosionParams, Params) and p.enabled and p.boundary == "open" and p.dt_s is None
    for field in ErosionParams.model_fields.values():
        assert field.description
    with pytest.raises(pydantic.ValidationError):
        ErosionParams(boundary="mirror")
    with pytest.raises(pydantic.ValidationError):
        ErosionParams(talus_angle_deg=90.0)
    with pytest.raises(pydantic.ValidationError):
        ErosionParams(rain_mm_per_hour=-1.0)
    with pytest.raises(pydantic.ValidationError):
        ErosionParams(no_such_param=1)
    with pytest.raises(pydantic.ValidationError):
        p.rain_mm_per_hour = 5.0  # frozen
    # the units: 36 mm/h is 1e-5 m/s; 45 degrees is a talus slope of 1; 1 h is 3600 s
    ph = physics_for(ErosionParams(rain_mm_per_hour=36.0, talus_angle_deg=45.0, moisture_time_hours=1.0), 10.0)
    assert ph.rain == pytest.approx(1e-5) and ph.talus_tan == pytest.approx(1.0) and ph.moisture_tau == 3600.0
    # the same years are 4x the talus-rule iterations on 2x finer cells
    q = ErosionParams(thermal_years=1024.0, scree_diffusivity_m2_per_year=1.0)
    assert thermal_iterations(q, 8.0) == 1024 / (0.5 * 64) == 32  # one iteration is 0.5 dx^2 / D years
    assert thermal_iterations(q, 4.0) == 4 * 32


def test_run_outputs_and_metrics(tmp_path):
    h, dx = world(48)
    # moisture averages over 36 s of a 3 minute storm: wet channels approach 1
    out, m, calls = run_stage(h, dx, tmp_path, storm_hours=0.05, moisture_time_hours=0.01)
    assert set(out) == set(GRIDS) | {"erosion.hillshade"}
    for name, channels in GRIDS.items():
        g = out[name]
        assert g.channels == channels and g.data.dtype == np.float32 and g.shape == h.shape and g.cell_size_m == dx
    shade = out["erosion.hillshade"]
    assert shade.dtype == np.uint8 and shade.shape == h.shape + (3,)
    net, wear, dep = (out["erosion.change"].data[..., k] for k in range(3))
    assert np.array_equal(wear, np.maximum(-net, 0)) and np.array_equal(dep, np.maximum(net, 0))
    assert wear.max() > 0 and dep.max() > 0
    moist = out["erosion.moisture"].data
    assert moist.min() >= 0 and moist.max() <= 1 and moist.max() > 0.5
    flow = out["erosion.flow"].data
    np.testing.assert_allclose(flow[..., 2], np.hypot(flow[..., 0], flow[..., 1]), rtol=1e-6)
    for key in ("steps", "dt_min_s", "dt_max_s", "dt_mean_s", "storm_seconds", "thermal_seconds",
                "water_budget_residual_rel", "mass_budget_residual_rel", "courant_max", "cell_steps_per_second",
                "thermal_iterations", "thermal_max_excess_deg", "wear_volume_m3", "deposition_volume_m3"):
        assert key in m, key
    assert m["water_budget_residual_rel"] <= 1e-6 and m["mass_budget_residual_rel"] <= 1e-6
    assert m["wear_volume_m3"] == pytest.approx(m["deposition_volume_m3"] + m["budget_sediment_suspended"] * dx * dx
                                                + m["budget_sediment_outflow"] * dx * dx, rel=1e-4)
    fractions = [f for f, _ in calls]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0


def test_a_disabled_storm_and_thermal_change_nothing(tmp_path):
    h, dx = world(32)
    out, m, _ = run_stage(h, dx, tmp_path, storm_hours=0.0, thermal_years=0.0)
    assert np.array_equal(out["erosion.height"].data, h) and m["steps"] == 0


def test_geological_time_runs_before_talus_and_storm(tmp_path):
    """The stream-power mode through the stage: rivers incise (wear), the
    eroded volume reaches base level, progress stays monotonic, and the
    change map holds geology, talus and storm together."""
    h, dx = world(48)
    out, m, progress = run_stage(h, dx, tmp_path, geological_years=2e5, geological_step_years=2e4,
                                 uplift_mm_per_year=0.5, storm_hours=0.01)
    calls = [f for f, _ in progress]
    assert m["stream_power_steps"] == 10 and m["stream_power_eroded_m3"] > 0
    assert m["stream_power_budget_relative_error"] <= 1e-12
    assert m["stream_power_volume_budget_relative_error"] <= 1e-9
    net = out["erosion.change"].data[..., 0].astype(np.float64)
    np.testing.assert_allclose(net, out["erosion.height"].data.astype(np.float64) - h, atol=1e-3)
    assert calls == sorted(calls) and calls[-1] == 1.0


def test_geological_time_refuses_too_many_steps(tmp_path):
    from pipeline.errors import InputError

    h, dx = world(16)
    with pytest.raises(InputError, match="geological_step_years"):
        run_stage(h, dx, tmp_path, geological_years=1e9, geological_step_years=1.0)
