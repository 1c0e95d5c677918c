"""Bad input is refused before any work: exit 2, one message naming the file
and the key, nothing written. Each case a new user tried (issue 21) is kept
here; `worldbake` runs in-process on a copy of configs/."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from pipeline.cli import main

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def project(tmp_path):
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    return tmp_path


def refused(project: Path, capsys, *args: str, config: str = "configs/bad.toml") -> str:
    """Run `worldbake bake`; assert exit 2, one line on stderr, nothing written."""
    status = main(["--project", str(project), "bake", str(project / config) if not Path(config).is_absolute()
                   else config, *args])
    err = capsys.readouterr().err
    assert status == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert not (project / "build").exists()
    return err


def bad(project: Path, text: str, name: str = "bad.toml") -> None:
    (project / "configs" / name).write_bytes(text.encode() if isinstance(text, str) else text)


@pytest.mark.parametrize("text, pattern", [
    ('extends = "default.toml"\nname = "../up"\n', r"bad.toml: name: must be .*got '../up'"),
    ('extends = "default.toml"\nname = "a/b"\n', r"bad.toml: name: must be"),
    ('extends = "default.toml"\nname = "' + "x" * 300 + '"\n', r"bad.toml: name: must be 1 to 64"),
    ('extends = "default.toml"\n[variants."../x"]\nworld.roughness = 0.5\n', r"variants.../x: must be"),
    ('extends = "default.toml"\n[variants.' + "v" * 100 + ']\nworld.roughness = 0.5\n', r"variants.v+: must be"),
    ('extends = "default.toml"\n[plants.species."a/b"]\npreset = "shrub"\n', r"plants.species.a/b: must be"),
    ('extends = "default.toml"\n[world]\nroughness = nan\n', r"bad.toml: world.roughness: must be a finite number"),
    ('extends = "default.toml"\n[heightmap]\nsize_m = inf\n', r"bad.toml: heightmap.size_m: must be a finite number"),
    ('extends = "default.toml"\n[variants.v]\nworld.bogus = 1\n', r"world.bogus: unknown key"),
    ('extends = "default.toml"\n[variants.v]\nworld.roughness = 7.0\n', r"\[variants.v\]: world.roughness"),
    ("x = " + "[" * 50000 + "]" * 50000 + "\n", r"bad.toml: (not valid TOML|x: tables nested)"),
    ("[" + ".".join(["a"] * 40) + "]\n", r"bad.toml: a(\.a)*: tables nested more than 16 deep"),
    ('extends = "default.toml"\n[heightmap]\n' + ".".join(["a"] * 20000) + " = 1\n",
     r"bad.toml: heightmap(\.a)+(\.\.\.)?: tables nested more than 16 deep"),
    ('extends = "default.toml"\ndescription = 5\n', r"bad.toml: description: must be a str .*got 5"),
    ('extends = "default.toml"\nname = 7\n', r"bad.toml: name: must be a str"),
    ('extends = "default.toml"\n' + "#" * (2 << 20) + "\n", r"bad.toml: 2,097,17\d bytes; a config file may hold at most"),
])
def test_bad_config_is_refused_before_work(project, capsys, text, pattern):
    bad(project, text)
    err = refused(project, capsys)
    assert re.search(pattern, err), err


def test_variants_are_checked_when_the_base_world_is_baked(project, capsys):
    bad(project, 'extends = "default.toml"\n[variants.v]\nheightmap.no_such = 1\n')
    assert "heightmap.no_such: unknown key" in refused(project, capsys)


@pytest.mark.parametrize("assignment", ['extends="default.toml"', "variants.x.world.roughness=0.5"])
def test_set_cannot_change_extends_or_variants(project, capsys, assignment):
    err = refused(project, capsys, "--set", assignment, config="configs/default.toml")
    assert re.search(r"--set .*cannot be set from the command line", err), err


def test_config_outside_the_project_is_refused(project, tmp_path_factory, capsys):
    outside = tmp_path_factory.mktemp("elsewhere") / "w.toml"
    outside.write_text((project / "configs" / "default.toml").read_text())
    assert "outside the project" in refused(project, capsys, config=str(outside))
    (project / "configs" / "link.toml").symlink_to(outside)
    assert "outside the project" in refused(project, capsys, config="configs/link.toml")


def test_a_utf8_byte_order_mark_is_accepted(project, capsys):
    bad(project, b"\xef\xbb\xbf" + b'extends = "default.toml"\nname = "bom"\n', "bom.toml")
    status = main(["--project", str(project), "plan", str(project / "configs" / "bom.toml")])
    assert status == 0, capsys.readouterr().err
    assert "world bom:" in capsys.readouterr().out


BAD_SPECIES = '''extends = "default.toml"
[plants]
build = ["grass", "bad"]
[plants.species.bad]
preset = "shrub"
[plants.species.bad.lsystem]
axiom = "S(1)"
iterations = 3
[[plants.species.bad.lsystem.rules]]
pred = "S(s)"
succ = "F(s) S(SUCC)"
'''


@pytest.mark.parametrize("succ, pattern", [
    ("s/(s-1)", r"float division by zero \(with s = 1.0\)"),
    ("exp(s*1000)", r"math range error"),
    ("s*1e300*1e300", r"gives inf, not a finite number"),
    ("s+", r"cannot parse expression 's\+'"),
    ("q", r"unknown name 'q'"),
])
def test_lsystem_rules_are_evaluated_before_work(project, capsys, succ, pattern):
    bad(project, BAD_SPECIES.replace("SUCC", succ))
    err = refused(project, capsys)
    assert re.search(r"bad.toml: plants.species.bad.lsystem: species 'bad', lsystem.rules\[0\] \(S\(s\) -> ", err), err
    assert re.search(pattern, err), err


def test_nan_tropism_is_refused_naming_the_key(project, capsys):
    bad(project, 'extends = "default.toml"\n[plants.species.shrub]\npreset = "shrub"\n'
                 '[plants.species.shrub.lsystem]\ntropism_strength = nan\n')
    assert "plants.species.shrub.lsystem.tropism_strength: must be a finite number" in refused(project, capsys)


def _raster(path: Path, data) -> None:
    import numpy as np

    from pipeline import exr
    from pipeline.grid import Grid
    exr.write_grid(path, Grid(np.asarray(data, np.float32), 1.0))


def test_dem_is_opened_and_checked_at_validation_naming_the_key(project, capsys):
    import numpy as np
    dem = np.full((16, 16), 100.0)
    dem[3, 4] = np.nan
    _raster(project / "dem.exr", dem)
    bad(project, 'extends = "default.toml"\n[heightmap]\ngenerator = "dem"\ndem_path = "dem.exr"\n')
    err = refused(project, capsys)
    assert re.search(r"bad.toml: heightmap.dem_path: DEM file .*dem.exr contains 1 NaN .* row 3, column 4", err), err


def test_a_raster_declaring_too_many_pixels_is_refused_before_reading(project, capsys, monkeypatch):
    import numpy as np

    from worldlib.terrain import dem
    monkeypatch.setattr(dem, "MAX_PIXELS", 100)  # a 16x16 file stands for a 32768^2 one
    _raster(project / "dem.exr", np.zeros((16, 16)))
    bad(project, 'extends = "default.toml"\n[heightmap]\ngenerator = "dem"\ndem_path = "dem.exr"\n')
    assert re.search(r"heightmap.dem_path: DEM file .* declares 16x16 pixels, more than the 100", refused(project, capsys))


@pytest.mark.parametrize("value, pattern", [(-1.0, r"has negative rain"), (float("nan"), r"contains 1 NaN")])
def test_rain_map_is_checked_at_validation_naming_the_key(project, capsys, value, pattern):
    import numpy as np
    rain = np.full((8, 8), 800.0)
    rain[2, 2] = value
    _raster(project / "rain.exr", rain)
    bad(project, 'extends = "default.toml"\n[hydrology]\nrain_map_path = "rain.exr"\n')
    err = refused(project, capsys)
    assert re.search(r"bad.toml: hydrology.rain_map_path: rain map .*rain.exr " + pattern, err), err


@pytest.mark.parametrize("assignment, pattern", [
    ("heightmap.resolution=16384", r"the run would hold about [\d.]+ GiB \(the terrain's 268,435,456 cells.*"
     r"its input height is 16384 x 16384 cells, set by heightmap.resolution"),
    ("world.texture_size=16384", r"--set: world: the run would hold about 64.9 GiB \(world.texture_size = 16384"),
    ("heightmap.size_m=1000000", r"vegetation: the run would hold about [\d.]+ GiB .*15,625,000,000 simulation cells"),
    ("vegetation.sim_cell_m=0.01", r"vegetation: the run would hold .*vegetation.sim_cell_m = 0.01"),
    ("vegetation.horizon_step_growth=1.0001", r"--set: vegetation.horizon_step_growth: 1.0001 takes 52,341 samples"),
    ("erosion.geological_step_years=100", r"erosion: geological_years = [0-9.e+]+ at geological_step_years = 100 is "
     r"[0-9.e+]+ steps \(at most"),
    ("erosion.dt_s=100", r"erosion: dt_s = 100 s breaks the CFL limit"),
])
def test_runs_too_large_are_refused_with_the_estimate(project, capsys, monkeypatch, assignment, pattern):
    monkeypatch.setenv("WORLDBAKE_MAX_MEMORY_GB", "16")  # the same answer on any machine
    err = refused(project, capsys, "--set", assignment, config="configs/default.toml")
    assert re.search(pattern, err), err


def test_a_storm_of_too_many_steps_is_refused_before_work(project, capsys):
    err = refused(project, capsys, "--set", "erosion.storm_hours=1000", "--set", "heightmap.size_m=1000",
                  config="configs/default.toml")
    assert re.search(r"--set: erosion.storm_hours: 1000 hours on 7.8125 m cells needs at least about 5.58e\+06 "
                     r"adaptive steps", err), err


def _plain_raster(path: Path, data) -> None:
    """A float EXR stating no cell size (stretched over the square world)."""
    import numpy as np
    import OpenImageIO as oiio

    data = np.ascontiguousarray(np.asarray(data, np.float32)[:, :, None])  # (rows, cols, 1): OIIO's layout
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(data.shape[1], data.shape[0], 1, "float"))
    assert out.write_image(data)
    out.close()


DEM_CONFIG = 'extends = "default.toml"\n[heightmap]\ngenerator = "dem"\ndem_path = "dem.exr"\n'


@pytest.mark.parametrize("write", [_plain_raster, _raster], ids=["stretched", "own_cells"])
def test_a_dem_of_two_rows_is_refused_before_any_stage_runs(project, capsys, write):
    import numpy as np
    write(project / "dem.exr", np.zeros((2, 4096)))
    bad(project, DEM_CONFIG)
    err = refused(project, capsys)
    assert re.search(r"^worldbake: error: configs/bad.toml: heightmap.dem_path: DEM file .*dem.exr is 4096x2 pixels: "
                     r"a DEM needs at least 3 pixels on each side", err), err


def test_a_dem_that_is_not_square_is_refused_before_any_stage_runs(project, capsys):
    import numpy as np
    _plain_raster(project / "dem.exr", np.zeros((30, 40)))
    bad(project, DEM_CONFIG)
    err = refused(project, capsys)
    assert re.search(r"configs/bad.toml: heightmap.dem_path: DEM file .*dem.exr is 40x30 pixels but the world is "
                     r"square", err), err


@pytest.mark.parametrize("value", [1e30, -3.4e38, 2e5])
def test_dem_heights_out_of_range_are_refused_before_any_stage_runs(project, capsys, value):
    import numpy as np
    dem = np.full((16, 16), 100.0)
    dem[5, 7] = value
    _raster(project / "dem.exr", dem)
    bad(project, DEM_CONFIG)
    err = refused(project, capsys)
    assert re.search(r"configs/bad.toml: heightmap.dem_path: DEM file .*dem.exr holds a height of [-0-9.e+]+ m "
                     r"\(row 5, column 7\), beyond the \+-100,000 m", err), err


def test_a_normalised_dem_is_checked_in_metres(project, capsys):
    import numpy as np
    dem = np.linspace(0.0, 1.0, 256).reshape(16, 16)
    dem[9, 2] = 50.0  # 50 x 4 km: 200 km
    _raster(project / "dem.exr", dem)
    bad(project, DEM_CONFIG + "dem_min_m = 0.0\ndem_max_m = 4000.0\n")
    assert re.search(r"holds a height of 2e\+05 m \(row 9, column 2\)", refused(project, capsys))


def test_a_dem_stating_its_cells_in_degrees_is_refused(project, capsys):
    import numpy as np

    from pipeline import exr
    from pipeline.grid import Grid
    exr.write_grid(project / "dem.exr", Grid(np.zeros((16, 16), np.float32), 1.0 / 3600.0))
    bad(project, DEM_CONFIG)
    err = refused(project, capsys)
    assert re.search(r"configs/bad.toml: heightmap.dem_path: DEM file .*dem.exr: its attribute worldbake:cell_size_m "
                     r"states cells of 0.000277778 m, outside 0.01 .. 100000 m", err), err


def test_a_rain_map_in_the_wrong_units_is_refused(project, capsys):
    import numpy as np
    _raster(project / "rain.exr", np.full((8, 8), 800.0e3))  # mm/year as micrometres
    bad(project, 'extends = "default.toml"\n[hydrology]\nrain_map_path = "rain.exr"\n')
    err = refused(project, capsys)
    assert re.search(r"configs/bad.toml: hydrology.rain_map_path: rain map .*rain.exr has 8e\+05 mm/year of rain "
                     r"\(row 0, column 0\), more than 20000 mm/year", err), err


def test_the_default_storm_passes_the_step_estimate(project, capsys):
    for hours in ("0.15", "0.35"):
        assert main(["--project", str(project), "plan", str(project / "configs" / "default.toml"),
                     "--set", f"erosion.storm_hours={hours}"]) == 0, capsys.readouterr().err
    capsys.readouterr()


def test_a_long_storm_is_refused_naming_the_step_limit_and_its_knob(project, capsys, monkeypatch):
    err = refused(project, capsys, "--set", "erosion.storm_hours=1000", config="configs/default.toml")
    assert re.search(r"^worldbake: error: --set: erosion.storm_hours: 1000 hours on 8 m cells needs at least about "
                     r"1.75e\+07 adaptive steps .*more than the 2,000,000 a storm may take \(erosion's MAX_STEPS; "
                     r"WORLDBAKE_MAX_STEPS raises it\)", err), err
    bad(project, 'extends = "default.toml"\n[erosion]\nstorm_hours = 1000.0\n')
    assert re.search(r"^worldbake: error: configs/bad.toml: erosion.storm_hours: ", refused(project, capsys))
    monkeypatch.setenv("WORLDBAKE_MAX_STEPS", "100")
    err = refused(project, capsys, config="configs/default.toml")  # 0.15 h: at least 135 steps
    assert "more than the 100 a storm may take (WORLDBAKE_MAX_STEPS = 100)" in err, err
    monkeypatch.setenv("WORLDBAKE_MAX_STEPS", "1e8")
    assert main(["--project", str(project), "plan", str(project / "configs" / "bad.toml")]) == 0


def test_the_memory_refusal_names_the_file_that_set_the_size(project, capsys, monkeypatch):
    monkeypatch.setenv("WORLDBAKE_MAX_MEMORY_GB", "16")
    bad(project, 'extends = "default.toml"\n[heightmap]\nresolution = 16384\n')
    err = refused(project, capsys)
    assert re.search(r"^worldbake: error: configs/bad.toml: erosion: the run would hold about 74.0 GiB .*set by "
                     r"heightmap.resolution", err), err
    bad(project, 'extends = "default.toml"\n[world]\ntexture_size = 16384\n')
    assert re.search(r"^worldbake: error: configs/bad.toml: world: the run would hold", refused(project, capsys))


def test_a_chain_of_extends_longer_than_the_limit_is_refused(project, capsys):
    bad(project, 'extends = "default.toml"\n', "c0.toml")
    for i in range(1, 18):
        bad(project, f'extends = "c{i - 1}.toml"\n', f"c{i}.toml")
    err = refused(project, capsys, config="configs/c17.toml")
    assert re.search(r"extends: a chain of more than 16 config files", err), err


def test_fine_ground_texels_are_estimated_at_the_real_udim_tile_size(project, capsys, monkeypatch):
    # 8192 m at 0.05 m: the UDIM row limit of 10 columns makes each tile 16384^2 texels, not the configured 2048^2
    monkeypatch.setenv("WORLDBAKE_MAX_MEMORY_GB", "16")
    err = refused(project, capsys, "--set", "world.ground_texel_m=0.05", config="configs/default.toml")
    assert re.search(r"^worldbake: error: --set: world: the run would hold about 32.6 GiB \(2 ground tiles of "
                     r"16384\^2 texels x 64 B \(world.ground_texel_m = 0.05: 10 x 10 UDIM tiles\)", err), err
    bad(project, 'extends = "default.toml"\n[world]\nground_texel_m = 0.05\n')
    assert re.search(r"^worldbake: error: configs/bad.toml: world: the run would hold", refused(project, capsys))


@pytest.mark.parametrize("assignments, pattern", [
    (("vegetation.years=100000", "vegetation.step_years=1"),
     r"--set: vegetation.years: the run would do about 1.05e\+11 cell-steps \(1,048,576 simulation cells x 100,001 "
     r"steps .* poisson_passes\), more than the 1e\+10 a run may do \(the vegetation stage's limit"),
    (("vegetation.poisson_passes=64", "vegetation.years=20000", "vegetation.step_years=2"),
     r"--set: vegetation.years: the run would do about [\d.e+]+ cell-steps"),
    (("impostors.samples=8", "impostors.ao_rays=64"),
     r"--set: impostors.ao_rays: the run would do about 1.75e\+10 rays per species \(4,194,304 atlas texels x 8\^2 "
     r"samples x \(1 \+ 64 ao_rays\) .*more than the 1e\+10 a run may do \(the impostors stage's limit"),
    (("impostors.heldout_stride=1", "impostors.heldout_px=1024", "impostors.heldout_samples=16"),
     r"--set: impostors.heldout_stride: the run would do about 1.74e\+11 rays per species .* 648 held-out views x "
     r"1024\^2 pixels x 16\^2 heldout_samples\)"),
    (("volumes.voxels=256", "volumes.solid_columns=16", "volumes.error_views=4", "volumes.error_view_pixels=1024"),
     r"--set: volumes.error_view_pixels: the run would do about [\d.e+]+ voxel-samples per species .*more than the "
     r"4e\+09 a run may do \(the volumes stage's limit"),
    (("forest_volumes.error_sectors=2000",),
     r"--set: forest_volumes.error_sectors: the run would do about 8e\+09 voxels \(max_voxels = 4,000,000 x .*2000 "
     r"error_sectors measured\)\), more than the 4e\+09 a run may do \(the forest_volumes stage's limit"),
])
def test_work_past_a_stage_limit_is_refused_naming_the_key_and_the_knob(project, capsys, monkeypatch, assignments,
                                                                        pattern):
    monkeypatch.setenv("WORLDBAKE_MAX_MEMORY_GB", "16")
    sets = [a for kv in assignments for a in ("--set", kv)]
    err = refused(project, capsys, *sets, config="configs/default.toml")
    assert re.search(r"^worldbake: error: " + pattern, err), err
    assert "WORLDBAKE_MAX_WORK_SCALE raises it); lower the values named" in err, err


def test_the_work_scale_raises_every_limit(project, capsys, monkeypatch):
    bad(project, 'extends = "default.toml"\n[forest_volumes]\nerror_sectors = 2000\n')
    assert re.search(r"^worldbake: error: configs/bad.toml: forest_volumes.error_sectors: ", refused(project, capsys))
    monkeypatch.setenv("WORLDBAKE_MAX_WORK_SCALE", "0.01")  # the default world's vegetation: about 1e8 cell-steps
    err = refused(project, capsys, config="configs/default.toml")
    assert "more than the 1e+08 a run may do (the vegetation stage's limit, 1e+10 x WORLDBAKE_MAX_WORK_SCALE = 0.01" \
        in err, err
    monkeypatch.setenv("WORLDBAKE_MAX_WORK_SCALE", "-1")
    assert "WORLDBAKE_MAX_WORK_SCALE = '-1': must be a positive number" in refused(project, capsys)
    monkeypatch.setenv("WORLDBAKE_MAX_WORK_SCALE", "10")
    assert main(["--project", str(project), "plan", str(project / "configs" / "bad.toml")]) == 0
    capsys.readouterr()
