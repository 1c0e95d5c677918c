"""The whole pipeline through the `worldbake` command, as a user runs it:
caching and re-runs, plan, kills at any moment, bad configs, determinism,
and a world.usda that validates."""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline import usdio

REPO = Path(__file__).resolve().parents[2]
# A small world: 96^2 cells, and only the grass asset (the tree presets take seconds each; tests/stages/plants covers them)
# the impostors at a few texels: these tests are about the command line
IMPOSTORS_SMALL = [a for kv in ("frames=4", "atlas_px=64", "min_frame_px=8", "small_plant_frame_px=8", "samples=1",
                                "heldout_px=24", "heldout_samples=1", "heldout_stride=108", "card_px=16",
                                "slice_px=16", "grass_slice_px=16") for a in ("--set", f"impostors.{kv}")]
SMALL = ["--set", "heightmap.resolution=96", "--set", "world.texture_size=64", "--set", "shared.mesh_max_vertices=49",
         *IMPOSTORS_SMALL, "--set", 'plants.build=["grass"]', "--set", "world.ground_texel_m=16",
         "--set", "world.ground_tile_texels=256"]


@pytest.fixture
def project(tmp_path):
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    return tmp_path


def worldbake(project: Path, *args: str, build: str = "build", check: bool = True,
              env: dict | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", build, *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=project, timeout=300,
                          env=None if env is None else {**os.environ, **env})
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr}")
    return proc


def bake_json(project, *args, build="build"):
    out = worldbake(project, "bake", "configs/default.toml", *SMALL, *args, "--json", build=build)
    return {s["stage"]: s for s in json.loads(out.stdout)[0]["steps"]}


def plan_json(project, *args):
    out = worldbake(project, "plan", "configs/default.toml", *SMALL, *args, "--json")
    return {s["stage"]: s["status"] for s in json.loads(out.stdout)[0]["steps"]}


def assert_store_whole(build: Path) -> None:
    for folder in (build / "artifacts").glob("*/*"):
        assert (folder / "manifest.json").is_file(), f"{folder} has no manifest"
        manifest = json.loads((folder / "manifest.json").read_text())
        for name in manifest["files"]:
            assert (folder / name).is_file()


def test_bake_caches_and_reruns_only_what_changed(project):
    plan = plan_json(project)  # a key hashes its inputs' content: known once they are made
    assert plan["heightmap"] == "will run" and set(plan.values()) == {"will run", "after inputs"}
    first = bake_json(project)
    stages = set(first)
    assert {"heightmap", "world"} <= stages and {v["status"] for v in first.values()} == {"ran"}
    assert set(plan_json(project).values()) == {"cached"}
    assert {v["status"] for v in bake_json(project).values()} == {"cached"}

    def expect(ran):
        return {s: ("will run" if s in ran else "cached") for s in stages}

    world_change = ["--set", "world.roughness=0.5"]
    assert plan_json(project, *world_change) == expect({"world"})
    assert {s: v["status"] for s, v in bake_json(project, *world_change, "--replace").items()} == \
        {s: "ran" if s == "world" else "cached" for s in stages}

    # everything downstream of the heightmap re-runs but the plants and what is
    # made of the plants alone: the same species are placed, so their input's
    # content is the same (early cutoff)
    hm_change = ["--set", "heightmap.relief_m=1234.0"]
    assert plan_json(project, *hm_change) == {s: "will run" if s == "heightmap" else "after inputs" for s in stages}
    statuses = {s: v["status"] for s, v in bake_json(project, *hm_change, "--replace").items()}
    of_plants_alone = {"plants", "impostors", "volumes"}
    assert statuses == {s: "cached" if s in of_plants_alone else "ran" for s in stages}

    world = project / "build" / "worlds" / "default" / "world.usda"
    assert usdio.validate(world) == []
    assert_store_whole(project / "build")


def _decoded(build: Path) -> dict:
    """Every artifact's decoded content: pixels for images, text for USD, by key."""
    out = {}
    for folder in sorted((build / "artifacts").glob("*/*")):
        for f in sorted(folder.iterdir()):
            name = f"{folder.parent.name}/{folder.name}/{f.name}"
            if f.suffix == ".exr":
                import OpenImageIO as oiio
                out[name] = oiio.ImageBuf(str(f)).get_pixels(oiio.FLOAT).tobytes()
            elif f.suffix in (".usda", ".usdc"):
                from pxr import Sdf
                out[name] = Sdf.Layer.FindOrOpen(str(f)).ExportToString()
            elif f.suffix == ".png":
                import OpenImageIO as oiio
                out[name] = oiio.ImageBuf(str(f)).get_pixels(oiio.UINT8).tobytes()
    return out


def _files(build: Path) -> set[str]:
    return {p.relative_to(build).as_posix() for p in build.rglob("*") if p.is_file()}


def test_two_bakes_give_the_same_keys_pixels_and_usd(project):
    """Two clean bakes of a world with every stage (forest sectors and the
    report included) give the same keys, and every file of the build folder
    byte for byte but the run records the store declares."""
    import filecmp

    from pipeline.store import is_run_record

    forest = ["--set", "forest_volumes.forest_min_height_m=0.0"]  # the grass makes forest sectors

    def bake(build: str) -> dict:
        out = worldbake(project, "bake", "configs/default.toml", *SMALL, *forest, "--json", build=build,
                        env={"WORLDBAKE_REPORT": "1"})
        return {s["stage"]: s for s in json.loads(out.stdout)[0]["steps"]}

    a, b = bake("build_a"), bake("build_b")
    assert {s: v["key"] for s, v in a.items()} == {s: v["key"] for s, v in b.items()}
    assert list((project / "build_a/artifacts/forest_volumes").glob("*/q*.mip0.exr")), "no forest sector"
    da, db = _decoded(project / "build_a"), _decoded(project / "build_b")
    assert da.keys() == db.keys() and len(da) >= 5
    for name in da:
        assert da[name] == db[name], f"{name} differs between two bakes"
    wa = (project / "build_a/worlds/default/world.usda").read_text()
    assert wa == (project / "build_b/worlds/default/world.usda").read_text()
    files = _files(project / "build_a")
    assert files == _files(project / "build_b")
    records = {f for f in files if is_run_record(f)}
    assert {"worlds/default/manifest.json", "worlds/default/report.html"} <= records
    assert {f"artifacts/{s}/{v['key']}/manifest.json" for s, v in a.items()} <= records
    differ = [f for f in sorted(files - records)
              if not filecmp.cmp(project / "build_a" / f, project / "build_b" / f, shallow=False)]
    assert not differ, f"not run records, yet they differ between two clean bakes: {differ}"
    # both bakes ran in the same project: an absolute path would be the same in both, so look for it
    here = str(project.resolve()).encode()
    with_path = [f for f in sorted(files - records) if here in (project / "build_a" / f).read_bytes()]
    assert not with_path, f"content holding the project's absolute path: {with_path}"


def test_sigkill_at_any_moment_leaves_no_half_artifact(project):
    reference = _decoded_after_bake(project, "build_ref")
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", "build_kill", "bake", "configs/default.toml", *SMALL]
    # Kill at spread-out moments: during start-up, while heightmap runs, while files are written.
    for delay in (0.3, 0.9, 1.5, 2.2, 3.0, 4.0):
        proc = subprocess.Popen(cmd, cwd=project, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert_store_whole(project / "build_kill")
        shutil.rmtree(project / "build_kill" / "artifacts" / "world", ignore_errors=True)  # make later kills hit world again
    worldbake(project, "bake", "configs/default.toml", *SMALL, build="build_kill")
    assert_store_whole(project / "build_kill")
    assert not any((project / "build_kill" / "tmp").iterdir())
    assert _decoded(project / "build_kill") == reference


def _decoded_after_bake(project, build):
    worldbake(project, "bake", "configs/default.toml", *SMALL, build=build)
    return _decoded(project / build)


@pytest.mark.parametrize("extra, pattern", [
    ('[heightmap]\nbogus_key = 3\n', r"bad.toml: heightmap.bogus_key: unknown key"),
    ('[heightmap]\noctaves = "many"\n', r"bad.toml: heightmap.octaves: .*valid integer"),
    ('[heightmap]\noctaves = 99\n', r"bad.toml: heightmap.octaves: .*less than or equal"),
    ('[heightmap]\ngenerator = "dem"\ndem_path = "../../../etc/hostname"\n', r"bad.toml: heightmap.dem_path: .*leaves the project"),
    ('[world]\nroughness = 2.0\n', r"bad.toml: world.roughness"),
])
def test_bad_config_exits_2_names_file_and_key_and_writes_nothing(project, extra, pattern):
    import re
    (project / "configs" / "bad.toml").write_text('extends = "default.toml"\n' + extra)
    proc = worldbake(project, "bake", "configs/bad.toml", check=False)
    assert proc.returncode == 2, proc.stderr
    assert re.search(pattern, proc.stderr), proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1  # one clear message, no traceback
    assert not (project / "build").exists()


def test_unknown_config_file_and_variant(project):
    proc = worldbake(project, "bake", "configs/nope.toml", check=False)
    assert proc.returncode == 2 and "nope.toml: config file not found" in proc.stderr
    proc = worldbake(project, "bake", "configs/default.toml", "--variant", "zzz", check=False)
    assert proc.returncode == 2 and "no variant 'zzz'" in proc.stderr


def test_variants_share_upstream_work(project):
    (project / "configs" / "wedge.toml").write_text(
        'extends = "default.toml"\nname = "wedge"\n[variants.matte]\nworld.roughness = 1.0\n')
    out = worldbake(project, "bake", "configs/wedge.toml", *SMALL, "--all-variants", "--json")
    worlds = {w["world"]: {s["stage"]: s for s in w["steps"]} for w in json.loads(out.stdout)}
    assert set(worlds) == {"wedge", "wedge-matte"}
    assert worlds["wedge-matte"]["heightmap"]["status"] == "cached"
    assert worlds["wedge-matte"]["world"]["status"] == "ran"
    for w in worlds:
        assert usdio.validate(project / "build" / "worlds" / w / "world.usda") == []


def test_gc_removes_only_unreferenced(project):
    bake_json(project)
    bake_json(project, "--set", "world.roughness=0.3", "--replace")
    out = worldbake(project, "gc")
    assert "1 unreferenced artifact folders and 0 unused units removed" in out.stdout  # the ground unit serves both
    assert set(plan_json(project, "--set", "world.roughness=0.3").values()) == {"cached"}


def test_a_list_valued_key_from_toml_and_from_set(project):
    plan_json(project, "--set", "heightmap.window=[0, 0, 32, 16]")
    proc = worldbake(project, "plan", "configs/default.toml", "--set", "heightmap.window=[0, 0, 32]", check=False)
    assert proc.returncode == 2 and "heightmap.window" in proc.stderr


def test_corrupt_dem_exits_2_and_leaves_no_artifact(project):
    (project / "data").mkdir()
    (project / "data" / "dem.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    (project / "configs" / "dem.toml").write_text(
        'extends = "default.toml"\n[heightmap]\ngenerator = "dem"\ndem_path = "data/dem.png"\n')
    proc = worldbake(project, "bake", "configs/dem.toml", *SMALL, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "dem.png" in proc.stderr.strip().splitlines()[-1] and "Traceback" not in proc.stderr
    assert not list((project / "build" / "artifacts").glob("*/*")) if (project / "build" / "artifacts").exists() else True
    assert not (project / "build" / "worlds").exists()


def test_a_rectangular_dem_stating_its_cell_size_bakes_a_rectangular_world(project):
    """A 50 x 40 DEM whose EXR header says 40 m cells: every stage runs on
    its 40 rows x 50 columns at 40 m, the height is the DEM's, and the world
    is 2 km x 1.6 km."""
    import OpenImageIO as oiio
    from pxr import Usd, UsdGeom

    from pipeline.exr import read_grid
    (project / "data").mkdir()
    r, c = np.mgrid[0:40, 0:50].astype(np.float64)
    dem = (400.0 + 600.0 * np.exp(-((c - 30) ** 2 + (r - 18) ** 2) / 300.0) + 2.0 * c).astype(np.float32)
    out = oiio.ImageOutput.create(str(project / "data" / "dem.exr"))
    spec = oiio.ImageSpec(50, 40, 1, "float")
    spec.attribute("worldbake:cell_size_m", 40.0)
    assert out.open(str(project / "data" / "dem.exr"), spec) and out.write_image(dem[:, :, None])
    out.close()
    (project / "configs" / "dem.toml").write_text(
        'extends = "default.toml"\nname = "demworld"\n[heightmap]\ngenerator = "dem"\ndem_path = "data/dem.exr"\n')
    steps = json.loads(worldbake(project, "bake", "configs/dem.toml", *SMALL, "--set", 'outputs=["world", "landscape"]',
                                 "--set", "landscape.components_per_tile=1", "--json").stdout)[0]["steps"]
    from pipeline.registry import all_stages
    assert {s["stage"] for s in steps} == set(all_stages())  # every stage runs on the rectangular world
    for s in steps:
        run = json.loads((project / "build" / "artifacts" / s["stage"] / s["key"] / "manifest.json").read_text())
        for name, meta in run["outputs"].items():
            if meta["kind"] == "grid" and not meta.get("absent"):
                assert meta["shape"] == [40, 50] and meta["cell_size_m"] == 40.0, name
        if s["stage"] == "heightmap":
            np.testing.assert_array_equal(read_grid(project / "build" / "artifacts" / "heightmap" / s["key"]
                                                    / "height.exr").data, dem)
    world = project / "build" / "worlds" / "demworld" / "world.usda"
    assert usdio.validate(world) == []
    stage = Usd.Stage.Open(str(world))
    r = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default"]).ComputeWorldBound(
        stage.GetPrimAtPath("/World/Terrain/Ground")).ComputeAlignedRange()  # the terrain tiles' extents
    lo, hi = r.GetMin(), r.GetMax()
    assert (round(hi[0] - lo[0] + 40), round(hi[2] - lo[2] + 40)) == (2000, 1600)  # vertex span + a cell


def _devices():
    from tests.conftest import device_id, working_devices

    return pytest.mark.parametrize("device", working_devices(), ids=device_id)


@_devices()
def test_dask_bake_gives_the_same_keys_and_pixels_as_local(project, device):
    """On every working runtime; Intel's used to abort at worker exit beside pymeshlab."""
    env = {"WORLDBAKE_CL_DEVICE": device.index}
    out = worldbake(project, "bake", "configs/default.toml", *SMALL, "--json", build="build_local", env=env)
    local = {s["stage"]: s for s in json.loads(out.stdout)[0]["steps"]}
    proc = worldbake(project, "bake", "configs/default.toml", *SMALL, "--json", "--executor", "dask",
                     build="build_dask", env=env)
    assert proc.returncode == 0
    # distributed logs (with a traceback) a worker heartbeat that finds the scheduler already closed, a race of
    # the cluster's shutdown on a loaded machine after every result is in: not the native crash looked for here
    records = re.split(r"(?m)^(?=\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ - )", proc.stderr)
    stderr = "".join(r for r in records if "Failed to communicate with scheduler during heartbeat" not in r)
    for text in ("malloc", "PLEASE submit a bug report", "Traceback"):
        assert text not in stderr, stderr[-3000:]
    dask = {s["stage"]: s for s in json.loads(proc.stdout)[0]["steps"]}
    assert {s: v["key"] for s, v in local.items()} == {s: v["key"] for s, v in dask.items()}
    assert {v["status"] for v in dask.values()} == {"ran"}
    assert _decoded(project / "build_local") == _decoded(project / "build_dask")
    assert usdio.validate(project / "build_dask" / "worlds" / "default" / "world.usda") == []


def test_world_instancers_use_the_plant_assets(project):
    from pxr import Usd, UsdGeom
    bake_json(project, "--set", 'plants.build=["grass", "shrub"]', "--set", "heightmap.resolution=128")
    stage = Usd.Stage.Open(str(project / "build" / "worlds" / "default" / "world.usda"))
    placed = json.loads(next((project / "build" / "artifacts" / "vegetation").glob("*/species.json")).read_text())["placed"]
    assert {"grass", "shrub"} & set(placed)
    seen = set()
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointInstancer):
            proto = stage.GetPrimAtPath(UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets()[0])
            species = proto.GetName()
            has_asset = proto.GetVariantSets().HasVariantSet("lod")
            assert has_asset == (species in ("grass", "shrub")), species
            seen.add(species)
    assert seen == set(placed)
    assert usdio.validate(project / "build" / "worlds" / "default" / "world.usda") == []


def test_with_only_heightmap_and_world_a_heightmap_change_reruns_just_those(project):
    only = ["--set", "erosion.enabled=false", "--set", "hydrology.enabled=false",
            "--set", "vegetation.enabled=false", "--set", "plants.enabled=false", "--set", "impostors.enabled=false",
            "--set", "volumes.enabled=false", "--set", "forest_volumes.enabled=false"]
    first = bake_json(project, *only)
    assert set(first) == {"heightmap", "world"}
    assert plan_json(project, *only, "--set", "heightmap.octaves=6") == {"heightmap": "will run", "world": "after inputs"}
    assert plan_json(project, *only, "--set", "world.roughness=0.2") == {"heightmap": "cached", "world": "will run"}
    assert usdio.validate(project / "build" / "worlds" / "default" / "world.usda") == []


def test_unknown_opencl_device_is_a_clear_error(project):
    cmd = [sys.executable, "-m", "pipeline.cli", "plan", "configs/default.toml"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=project, timeout=120,
                          env={**os.environ, "WORLDBAKE_CL_DEVICE": "no-such-gpu"})
    assert proc.returncode == 3 and "WORLDBAKE_CL_DEVICE='no-such-gpu' matches no device" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_two_worlds_placing_the_same_species_share_the_plant_meshes(project):
    """Early cutoff: world b differs from a in vegetation params only, and
    places the same species with the same plant params: the plants stage
    reads only which species were placed, so b's bake builds no plant mesh."""
    (project / "configs" / "a.toml").write_text('extends = "default.toml"\nname = "a"\n')
    (project / "configs" / "b.toml").write_text('extends = "default.toml"\nname = "b"\n[vegetation]\nlatitude_deg = 20.0\n')
    small = [*SMALL[:-1], 'plants.build=["grass", "shrub"]']
    a = worldbake(project, "bake", "configs/a.toml", *small, "--json")
    plan = worldbake(project, "plan", "configs/b.toml", *small, "--json")
    b = worldbake(project, "bake", "configs/b.toml", *small, "--json")
    steps_a = {s["stage"]: s for s in json.loads(a.stdout)[0]["steps"]}
    steps_b = {s["stage"]: s for s in json.loads(b.stdout)[0]["steps"]}
    planned_b = {s["stage"]: s["status"] for s in json.loads(plan.stdout)[0]["steps"]}
    assert planned_b["vegetation"] == "will run" and planned_b["plants"] == "after inputs"
    assert steps_b["vegetation"]["status"] == "ran" and steps_b["vegetation"]["key"] != steps_a["vegetation"]["key"]
    assert steps_b["plants"]["status"] == "cached" and steps_b["plants"]["key"] == steps_a["plants"]["key"]
    # nor voxelizes a plant again (the volumes' key hashes the assets' content); its forest sectors follow the new instances
    assert steps_b["volumes"]["status"] == "cached" and steps_b["forest_volumes"]["status"] == "ran"
    # and `plan` now says so
    again = {s["stage"]: s["status"] for s in json.loads(worldbake(project, "plan", "configs/b.toml", *small,
                                                                   "--json").stdout)[0]["steps"]}
    assert set(again.values()) == {"cached"}
    for world in ("a", "b"):
        assert usdio.validate(project / "build" / "worlds" / world / "world.usda") == []
