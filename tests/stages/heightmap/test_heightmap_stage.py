"""The stage contract, params validation and run()."""

import numpy as np
import pydantic
import pytest

from pipeline.contract import Params, RunContext, Stage
from pipeline.grid import Grid
from stages.heightmap import STAGE, HeightmapParams


def test_contract():
    assert isinstance(STAGE, Stage)
    assert STAGE.name == "heightmap" and STAGE.version >= 1 and STAGE.inputs == ()
    assert STAGE.uses_seed and STAGE.uses_opencl
    h = STAGE.output("heightmap.height")
    assert (h.kind, h.file, h.channels, h.units) == ("grid", "height.exr", ("height",), "m")
    s = STAGE.output("heightmap.hillshade")
    assert (s.kind, s.file, s.shape) == ("image", "hillshade.png", "terrain")
    assert issubclass(STAGE.params, Params)
    assert (STAGE.source_dir / "kernels.cl").is_file() and (STAGE.source_dir / "reference.py").is_file()
    for name, field in STAGE.params.model_fields.items():
        if name == "enabled":
            continue
        assert field.description, name
        assert "units" in (field.json_schema_extra or {}), name


def test_defaults_are_valid_and_frozen():
    p = HeightmapParams()
    assert p.generator == "warped" and p.resolution == 1024 and p.size_m == 8192.0
    with pytest.raises(pydantic.ValidationError):
        p.resolution = 5


@pytest.mark.parametrize("bad,key", [
    (dict(size_m=0.5), "size_m"),
    (dict(size_m=2e6), "size_m"),
    (dict(resolution=1), "resolution"),
    (dict(resolution=16385), "resolution"),
    (dict(octaves=0), "octaves"),
    (dict(octaves=17), "octaves"),
    (dict(lacunarity=1.2), "lacunarity"),
    (dict(lacunarity=4.5), "lacunarity"),
    (dict(hurst=-0.1), "hurst"),
    (dict(hurst=1.01), "hurst"),
    (dict(wavelength_m=0.0), "wavelength_m"),
    (dict(relief_m=-1.0), "relief_m"),
    (dict(fault_softness_m=0.0), "fault_softness_m"),
    (dict(fault_count=0), "fault_count"),
    (dict(generator="diamond"), "generator"),
    (dict(unknown_key=1), "unknown_key"),
    (dict(generator="fault", tileable=True), "tileable"),
    (dict(generator="dem", dem_path="x.exr", tileable=True), "tileable"),
    (dict(generator="dem"), "dem_path"),
    (dict(dem_min_m=0.0), "dem_max_m"),
    (dict(dem_min_m=10.0, dem_max_m=5.0), "dem_max_m"),
    (dict(window=(0, 0, 0, 5)), "window"),
    (dict(window=(-1, 0, 4, 5)), "window"),
    (dict(resolution=64, window=(60, 0, 5, 5)), "window"),
    (dict(resolution=64, window=(0, 0, 4)), "window"),
    (dict(size_m=10000.0, resolution=100, wavelength_m=150.0), "wavelength_m"),
    (dict(size_m=1000.0, warp_strength_m=1001.0), "warp_strength_m"),
])
def test_rejected(bad, key):
    with pytest.raises(pydantic.ValidationError) as e:
        HeightmapParams(**bad)
    assert key in {str(loc) for err in e.value.errors() for loc in err["loc"]}, e.value


def test_fault_tileable_message():
    with pytest.raises(pydantic.ValidationError, match="fault lines are not periodic"):
        HeightmapParams(generator="fault", tileable=True)


def test_window_from_toml_list():
    # configs are validated strictly (as the engine does): a TOML array must be accepted
    p = HeightmapParams.model_validate({"resolution": 64, "window": [1, 2, 3, 4]}, strict=True)
    assert p.tile == (1, 2, 3, 4)


@pytest.mark.parametrize("generator", ["fbm", "ridged", "warped", "fault"])
def test_run(cl_env, tmp_path, generator):
    calls = []
    ctx = RunContext(cl=cl_env, stage=STAGE, key="test", out_dir=tmp_path, seed=123, provenance={}, project_root=tmp_path,
                     progress=lambda f, m: calls.append(f))
    p = HeightmapParams(generator=generator, resolution=64, size_m=2048.0, wavelength_m=1024.0, window=(8, 4, 40, 30))
    out = STAGE.run(ctx, {}, p)
    assert set(out) == {"heightmap.height", "heightmap.hillshade"}
    g = out["heightmap.height"]
    assert isinstance(g, Grid) and g.data.dtype == np.float32 and g.shape == (30, 40)
    assert g.cell_size_m == 32.0 and g.origin_m == (8 * 32.0, 4 * 32.0)
    img = out["heightmap.hillshade"]
    assert img.dtype == np.uint8 and img.shape == (30, 40, 3)
    assert ctx.metrics["height_min_m"] <= ctx.metrics["height_mean_m"] <= ctx.metrics["height_max_m"]
    assert ctx.metrics["kernel_seconds"] >= 0
    assert calls and calls[-1] == 1.0 and calls == sorted(calls)
    assert list(tmp_path.iterdir()) == []  # run() writes nothing itself


def test_seed_changes_map_and_same_seed_does_not(cl_env, tmp_path):
    def bake(seed):
        ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path, seed=seed, provenance={}, project_root=tmp_path)
        return STAGE.run(ctx, {}, HeightmapParams(resolution=32))["heightmap.height"].data
    a, b, c = bake(1), bake(1), bake(2)
    assert a.tobytes() == b.tobytes()
    assert not np.array_equal(a, c)


def test_negative_and_huge_seeds(cl_env, tmp_path):
    for seed in (-5, 2**63 + 17):
        ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path, seed=seed, provenance={}, project_root=tmp_path)
        h = STAGE.run(ctx, {}, HeightmapParams(resolution=16))["heightmap.height"].data
        assert np.isfinite(h).all()


@pytest.mark.parametrize("kw", [
    dict(size_m=1e6, resolution=16384, window=(16370, 16370, 14, 14), wavelength_m=1e7, octaves=16, lacunarity=4.0),
    dict(size_m=1e6, resolution=16384, window=(0, 16370, 14, 14), generator="warped", warp_strength_m=1e6,
         warp_wavelength_m=1.0, wavelength_m=200.0, octaves=16, hurst=0.0),
    dict(size_m=1.0, resolution=16384, window=(5, 5, 9, 9), wavelength_m=1e7, tileable=True, generator="ridged"),
    dict(size_m=1e6, resolution=2, wavelength_m=1e6, generator="fault", fault_count=20000, fault_softness_m=1e-3),
    dict(relief_m=1e5, base_m=-1e5, resolution=8, generator="ridged", ridge_offset=2.0, ridge_gain=8.0),
])
def test_extreme_params_stay_finite_and_bounded(cl_env, tmp_path, kw):
    ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path, seed=7, provenance={}, project_root=tmp_path)
    p = HeightmapParams(**kw)
    h = STAGE.run(ctx, {}, p)["heightmap.height"].data
    assert np.isfinite(h).all()
    if p.generator != "fault":  # fault: relief is 3 standard deviations, not a bound
        assert np.abs(h.astype(np.float64) - p.base_m).max() <= p.relief_m * 1.0001
