"""The volumes and forest_volumes stages on one small plant asset (a
3-iteration shrub built by the plants stage): only placed species get
volumes, the atlases load back into the same grids, the mips keep the mean
coverage, the error views and the woody solid are measured, and sectors
splat the species volumes at each instance keeping their projected area."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline import usdio
from worldlib.volumes import dense as volume
from pipeline.config import canonical_params
from pipeline.contract import RunContext
from stages.forest_volumes import STAGE as FOREST
from stages.forest_volumes import reference, splat
from stages.forest_volumes.stage import ForestVolumesParams, _rotations, occupied_box, read_species_volumes, read_tiles
from stages.volumes import STAGE
from stages.volumes.stage import VolumesParams

from tests.stages.plants.helpers import run_stage as run_plants
from pipeline.opencl import get_cl

BUSH = {"build": ["bush"], "hausdorff_samples": 1000, "lod_count": 1,
        "species": {"bush": {"preset": "shrub", "lsystem": {"iterations": 3}}}}


def _run(stage, params, inputs, out: Path, units=None):
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    out.mkdir(parents=True, exist_ok=True)
    ctx = RunContext(cl=cl_env, stage=stage, key="test", out_dir=out, seed=1,
                     provenance={"stage": stage.name, "version": stage.version, "key": "test",
                                 "params": canonical_params(params), "seed": "none"}, project_root=Path("."),
                     units=units)
    return stage.run(ctx, inputs, params), ctx


@pytest.fixture(scope="module")
def plants(tmp_path_factory):
    out, _ = run_plants(tmp_path_factory.mktemp("plants"), BUSH)
    return out["plants.assets"]


@pytest.fixture(scope="module")
def volumes(plants, tmp_path_factory):
    params = VolumesParams(voxels=32, mip_levels=3, error_view_pixels=64, vdb=False)
    out, ctx = _run(STAGE, params, {"plants": plants, "placed": {"placed": ["bush", "oak"]}},
                    tmp_path_factory.mktemp("volumes"))
    return out, ctx


def test_an_unchanged_asset_is_not_voxelized_again(plants, tmp_path):
    """A later run (another species changed) links the volumes of an asset
    that did not change: the same bytes a clean run writes."""
    from pipeline.store import Store
    from pipeline.units import Units

    params = VolumesParams(voxels=16, mip_levels=2, error_view_pixels=32, vdb=False)
    inputs = {"plants": plants, "placed": {"placed": ["bush"]}}

    def run(out, build):
        store = Store(build)
        return _run(STAGE, params, inputs, out, Units(store.units, store.tmp, "volumes", {"stage": "volumes"}))

    def files(folder):
        return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}

    (first, first_ctx), (second, second_ctx) = run(tmp_path / "a", tmp_path / "build"), run(tmp_path / "b", tmp_path / "build")
    assert not first_ctx.metrics["species"]["bush"]["reused"]
    assert second_ctx.metrics["species"]["bush"]["reused"]
    assert second_ctx.metrics["species"]["bush"]["seconds"] == first_ctx.metrics["species"]["bush"]["seconds"]
    assert first["volumes.stats"] == second["volumes.stats"]  # content: no run times, no reuse
    assert files(tmp_path / "a") == files(tmp_path / "b")


def test_only_placed_species_with_an_asset_get_volumes(plants, volumes, tmp_path):
    out, _ = volumes
    stats = out["volumes.stats"]
    assert stats["voxelized"] == ["bush"] and stats["not_voxelized"] == ["oak"]
    assert sorted(p.name for p in out["volumes.assets"].parent.glob("*.exr")) == [f"bush.mip{k}.exr" for k in range(3)]
    none, _ = _run(STAGE, VolumesParams(voxels=16, mip_levels=2, error_view_pixels=0, vdb=False),
                   {"plants": plants, "placed": {"placed": ["grass"]}}, tmp_path / "none")
    assert none["volumes.stats"]["voxelized"] == [] and not list((tmp_path / "none").glob("*.exr"))
    assert usdio.validate(none["volumes.assets"]) == []


def test_the_layer_validates_and_holds_a_volume_per_mip(volumes):
    from pxr import Usd, UsdVol

    out, _ = volumes
    layer = out["volumes.assets"]
    assert usdio.validate(layer) == []
    stage = Usd.Stage.Open(str(layer))
    prim = stage.GetPrimAtPath("/Volumes/bush")
    vset = prim.GetVariantSets().GetVariantSet("mip")
    assert vset.GetVariantNames() == ["mip0", "mip1", "mip2"]
    vol = UsdVol.Volume(stage.GetPrimAtPath("/Volumes/bush/Volume"))
    assert set(vol.GetFieldPaths()) == {"density", "albedo", "normal"}
    assert vol.GetPrim().GetCustomDataByKey("worldbake:atlas")["file"] == "./bush.mip0.exr"


def test_atlases_reassemble_into_the_grids_and_the_mips_keep_coverage(volumes):
    out, _ = volumes
    folder = out["volumes.assets"].parent
    levels = [volume.read_atlas(folder / f"bush.mip{k}.exr") for k in range(3)]
    for k, lv in enumerate(levels):
        assert lv.attributes["volume_mip"] == k
        assert tuple(lv.attributes["volume_grid"]) == lv.shape_xyz
        assert np.array_equal(volume.to_atlas(lv), volume.to_atlas(volume.from_atlas(
            volume.to_atlas(lv), lv.shape_xyz, lv.origin, lv.voxel_m)))
        assert abs(lv.mean_density() - levels[0].mean_density()) <= 1e-6 * levels[0].mean_density()
        assert (lv.albedo <= lv.density[..., None] * (1 + 1e-6) + 1e-9).all() and (lv.albedo >= 0).all()
        assert (np.linalg.norm(lv.normal, axis=-1) <= 1 + 1e-6).all()
    # the written mip 1 is the mip of the written finest level
    again = volume.downsample(levels[0])
    for name in ("density", "albedo", "normal", "surface"):
        np.testing.assert_allclose(getattr(again, name), getattr(levels[1], name), rtol=1e-6, atol=1e-7)
    assert max(levels[0].shape_xyz) == 32 and levels[1].voxel_m == pytest.approx(2 * levels[0].voxel_m)


def test_errors_and_the_woody_solid_are_measured(volumes):
    out, _ = volumes
    rep = out["volumes.stats"]["species"]["bush"]
    # occupied voxels vs manifold3d's volume of the Wood mesh: branches 1-2 voxels thick at 32 voxels
    assert abs(rep["wood"]["relative_error"]) < 0.1
    for e in rep["levels"]:
        assert 0.0 <= e["alpha_iou_min"] <= 1.0 and e["psnr_db_min"] > 20 and len(e["views"]) == 2
        assert e["bytes"] == 32 * np.prod(e["grid"])
    assert rep["levels"][0]["alpha_iou_min"] > 0.4  # a sparse 3-iteration shrub at 32 voxels
    attrs = volume.read_atlas(out["volumes.assets"].parent / "bush.mip0.exr").attributes
    assert attrs["volume_errors"]["alpha_iou_min"] == rep["levels"][0]["alpha_iou_min"]


def test_a_splat_keeps_the_projected_area_of_every_instance(volumes):
    out, _ = volumes
    src = read_species_volumes(out["volumes.assets"])["bush"].level(0)
    shape, origin, voxel = (32, 16, 32), (-4.0, -2.0, -4.0), 0.25
    acc = np.zeros((8, 32 * 16 * 32), np.int64)
    q = np.array([[1.0, 0, 0, 0], [np.cos(0.3), 0, np.sin(0.3), 0]])
    reference.splat(shape, origin, voxel, src, np.array([[0.0, 0, 0], [1.0, 0.5, 1.0]]), _rotations(q),
                    np.array([1.0, 2.0]), acc)
    per_instance = src.density.astype(np.float64).sum() * src.voxel_m ** 3
    assert acc[0].sum() / splat.FIXED * voxel ** 3 == pytest.approx(per_instance * (1 + 2 ** 2), rel=1e-9)


@pytest.fixture(scope="module")
def forest(volumes, tmp_path_factory):
    """A two-tile instances layer as vegetation writes it (30 turned bushes
    in one tile, 30 grass tufts in the other) and its forest volumes."""
    from stages.vegetation import usd_layer
    from stages.vegetation.placement import Instances

    tmp_path = tmp_path_factory.mktemp("forest")
    rng = np.random.default_rng(3)

    def inst(name, n, x0):
        pos = np.stack([x0 + 10 * rng.random(n), np.zeros(n), 10 * rng.random(n)], 1).astype(np.float32)
        quat = np.zeros((n, 4), np.float16)  # (i, j, k, real): a quarter turn about +y
        quat[:, 1] = quat[:, 3] = np.sqrt(0.5)
        return Instances(name, pos, quat, np.ones((n, 3), np.float32), np.ones(n, np.float32), rng.random(n).astype(np.float32),
                         np.arange(n, dtype=np.int64), np.ones(n, np.float32))

    sets = {"bush": inst("bush", 30, 0.0), "grass": inst("grass", 30, 20.0)}
    layer = tmp_path / "instances.usdc"
    usd_layer.write(layer, {"stage": "vegetation"}, sets, {"bush": 0.6, "grass": 0.3}, {"bush": "plant", "grass": "grass"},
                    0.0, 0.0, 32.0, 40, 8.0)
    out, _ = volumes
    params = ForestVolumesParams(voxel_m=0.5, mip_levels=2, forest_min_height_m=0.1, vdb=False)
    res, _ = _run(FOREST, params, {"volumes": out["volumes.assets"], "instances": layer}, tmp_path / "out")
    return layer, res, tmp_path / "out"


def test_forest_tiles_get_sector_volumes(volumes, forest):
    """The tile with the shrubs gets a sector volume over it, the tile of
    grass none."""
    from pxr import Usd, UsdGeom

    from worldlib.volumes import sparse as sparse_volume

    layer, res, folder = forest
    tiles = read_tiles(layer)
    assert sum(len(t.species.get("bush", ([],))[0]) for t in tiles) == 30
    rot = next(t.species["bush"][1] for t in tiles if "bush" in t.species)
    np.testing.assert_allclose(rot[0] @ [1.0, 0, 0], [0, 0, -1.0], atol=1e-3)  # x turns to -z about +y
    out, _ = volumes
    sectors = res["forest_volumes.stats"]["sectors"]
    assert len(sectors) == 1 and list(sectors.values())[0]["instances"] == {"bush": 30}
    path = next(iter(sectors))
    assert usdio.validate(res["forest_volumes.sectors"]) == []
    world = Usd.Stage.Open(str(res["forest_volumes.sectors"]))
    far = world.GetPrimAtPath(f"{path}/FarVolume")
    assert UsdGeom.Imageable(far).GetPurposeAttr().Get() == UsdGeom.Tokens.proxy
    lv = sparse_volume.read_level(folder / f"{path.rsplit('/', 1)[-1]}.mip0.exr")
    src = read_species_volumes(out["volumes.assets"])["bush"].level(0)
    expect = 30 * src.density.astype(np.float64).sum() * src.voxel_m ** 3
    assert lv.density.astype(np.float64).sum() * lv.voxel_m ** 3 == pytest.approx(expect, rel=1e-3)
    assert lv.attributes["volume_pixel_type"] == "half (density float)"
    info = list(sectors.values())[0]
    assert all(a <= b for a, b in zip(info["grid"], info["grid_before_clip"]))
    assert (lv.density[0] > 0).any() or (lv.density[:, 0] > 0).any() or (lv.density[..., 0] > 0).any()
    assert json.loads(far.GetCustomDataByKey("worldbake:volume"))["instances"] == {"bush": 30}


def test_stored_sector_levels_are_column_runs_that_keep_the_mean_coverage(forest):
    from worldlib.volumes import sparse as sparse_volume

    _, res, folder = forest
    path, info = next(iter(res["forest_volumes.stats"]["sectors"].items()))
    stem = path.rsplit("/", 1)[-1]
    levels = [sparse_volume.read_runs(folder / f"{stem}.mip{k}.exr") for k in range(2)]
    for k, lv in enumerate(levels):
        assert lv.attributes["volume_layout"] == "column runs" and len(lv.index) == info["levels"][k]["occupied_voxels"]
        # the runs hold no more than the occupied voxels and the gaps inside their columns
        assert len(lv.index) <= lv.attributes["volume_runs_voxels"] < 2 * len(lv.index)
        # the finest level's density is rounded to pxr24's 24 bits before the mips are made: what is read back
        # is what was computed, and the stored mips keep the stored finest level's mean coverage
        assert abs(lv.mean_density() / levels[0].mean_density() - 1) <= 1e-7
        assert lv.mean_density() == pytest.approx(info["levels"][k]["mean_density"], rel=1e-12)
    assert np.array_equal(levels[0].density, sparse_volume.round_to_pxr24(levels[0].density))
    dense = levels[0].to_dense()
    again = sparse_volume.downsample(sparse_volume.from_dense(dense)).to_dense()
    np.testing.assert_allclose(again.density, levels[1].to_dense().density, rtol=2e-5, atol=1e-9)


def test_the_sector_is_measured_against_its_instances(forest, volumes):
    """column_errors: the baked sector keeps its instances' extinction and
    lies close to them column by column; a sector moved by three voxels, or
    with half its density, is caught."""
    from worldlib.volumes import sparse as sparse_volume
    from stages.forest_volumes.stage import column_errors

    layer, res, folder = forest
    path, info = next(iter(res["forest_volumes.stats"]["sectors"].items()))
    err = info["error"]
    assert abs(err["extinction_relative"]) < 1e-6 and abs(err["side_extinction_relative"]) < 1e-6
    assert err["column_relative_l1_32m"] < 0.05 and err["column_relative_l1"] < 0.5 and err["cover_mae"] < 0.1
    assert res["forest_volumes.stats"]["error"]["sectors"] == 1
    level = sparse_volume.read_runs(folder / f"{path.rsplit('/', 1)[-1]}.mip0.exr")
    tile = next(t for t in read_tiles(layer) if t.path == path)
    species = read_species_volumes(volumes[0]["volumes.assets"])
    again = column_errors(level, tile, species)
    assert again["column_relative_l1"] == pytest.approx(err["column_relative_l1"], abs=1e-3)
    level.origin = level.origin + [3 * level.voxel_m, 0.0, 0.0]
    moved = column_errors(level, tile, species)
    assert moved["column_relative_l1"] > 2 * err["column_relative_l1"] + 0.3
    assert moved["side_column_relative_l1"] < 0.5 * moved["column_relative_l1"]  # along x: the side sees no move
    level.origin = level.origin - [3 * level.voxel_m, 0.0, 0.0]
    level.density = level.density / 2
    assert column_errors(level, tile, species)["extinction_relative"] == pytest.approx(-0.5, abs=1e-3)


def test_vdb_levels_read_back_with_the_same_values(plants, tmp_path):
    """With vdb = true (the default) every level is also an OpenVDB file
    (Debian's python3-openvdb through worldlib/volumes/vdb.py) whose grids
    density and albedo, read by OpenVDB itself, equal the atlas's (albedo as
    the plain colour, albedo / density), whose voxel (0, 0, 0) sits where the atlas puts it,
    and which the Volume's fields name and resolve to."""
    from pxr import Usd, UsdVol

    from worldlib.volumes import vdb

    if vdb.available() is not None:
        pytest.skip(f"no OpenVDB writer here: {vdb.available()}")
    params = VolumesParams(voxels=16, mip_levels=2, error_view_pixels=0)
    assert params.vdb
    out, _ = _run(STAGE, params, {"plants": plants, "placed": {"placed": ["bush"]}}, tmp_path)
    assert usdio.validate(out["volumes.assets"]) == []
    for k in range(2):
        lv = volume.read_atlas(tmp_path / f"bush.mip{k}.exr")
        grids = vdb.read_vdb(tmp_path / f"bush.mip{k}.vdb", lv.shape_xyz)
        assert set(grids) >= {"density", "albedo"} and "normal" not in grids  # what a DCC's volume shader reads
        assert np.array_equal(grids["density"], lv.density)
        occupied = lv.density > 0
        # the albedo grid is saved as half floats (the EXR form's precision)
        np.testing.assert_allclose(grids["albedo"][occupied], lv.albedo[occupied] / lv.density[occupied][:, None],
                                   rtol=1e-3)
        assert not grids["albedo"][~occupied].any() and str(grids["density_class"]) == "fog volume"
        np.testing.assert_allclose(grids["density_voxel"], lv.voxel_m, rtol=1e-12)
        np.testing.assert_allclose(grids["density_world0"], lv.origin + lv.voxel_m / 2, rtol=0, atol=1e-9)
    stage = Usd.Stage.Open(str(out["volumes.assets"]))
    vol = UsdVol.Volume(stage.GetPrimAtPath("/Volumes/bush/Volume"))
    assert set(vol.GetFieldPaths()) == {"density", "albedo"}
    for name, path in vol.GetFieldPaths().items():
        field = UsdVol.OpenVDBAsset(stage.GetPrimAtPath(path))
        asset = field.GetFilePathAttr().Get()
        assert asset.path == "./bush.mip0.vdb" and field.GetFieldNameAttr().Get() == name
        assert Path(asset.resolvedPath) == tmp_path / "bush.mip0.vdb"
    assert UsdVol.OpenVDBAsset(stage.GetPrimAtPath("/Volumes/bush/Volume/albedo")).GetVectorDataRoleHintAttr().Get() \
        == "Color"


def test_forest_sectors_are_openvdb_volumes_too(forest, volumes, tmp_path):
    """With vdb = true (the default) every sector level is also a .vdb: the
    occupied voxels of its column runs, at the EXR's place, named by the
    Volume's OpenVDBAsset fields density and albedo; all levels of the bake
    in one run of the writer."""
    from pxr import Usd, UsdVol

    from worldlib.volumes import sparse as sparse_volume, vdb

    if vdb.available() is not None:
        pytest.skip(f"no OpenVDB writer here: {vdb.available()}")
    layer, _, _ = forest
    params = ForestVolumesParams(voxel_m=0.5, mip_levels=2, forest_min_height_m=0.1, error_sectors=0)
    res, ctx = _run(FOREST, params, {"volumes": volumes[0]["volumes.assets"], "instances": layer}, tmp_path)
    path = next(iter(res["forest_volumes.stats"]["sectors"]))
    stem = path.rsplit("/", 1)[-1]
    for k in range(2):
        runs = sparse_volume.read_runs(tmp_path / f"{stem}.mip{k}.exr")
        grids = vdb.read_vdb(tmp_path / f"{stem}.mip{k}.vdb", runs.shape_xyz)
        lv = runs.to_dense()
        assert np.array_equal(grids["density"], lv.density)
        occupied = lv.density > 0
        # the EXR holds albedo in half floats, the .vdb the float32 the stage computed
        np.testing.assert_allclose(grids["albedo"][occupied], lv.albedo[occupied] / lv.density[occupied][:, None],
                                   rtol=2e-3)
        np.testing.assert_allclose(grids["density_world0"], runs.origin + runs.voxel_m / 2, atol=1e-9)
        lo, hi = grids["density_active"]
        z, y, x = np.nonzero(occupied)
        assert list(lo) == [x.min(), y.min(), z.min()] and list(hi) == [x.max(), y.max(), z.max()]
    stage = Usd.Stage.Open(str(res["forest_volumes.sectors"]))
    vol = UsdVol.Volume(stage.GetPrimAtPath(f"{path}/FarVolume/Volume"))
    for name in ("density", "albedo"):
        field = UsdVol.OpenVDBAsset(stage.GetPrimAtPath(vol.GetFieldPath(name)))
        assert field.GetFieldNameAttr().Get() == name
        assert Path(field.GetFilePathAttr().Get().resolvedPath) == tmp_path / f"{stem}.mip0.vdb"
    assert ctx.metrics["phases_seconds"]["vdb"] > 0
    assert usdio.validate(res["forest_volumes.sectors"]) == []


def test_a_sector_is_clipped_to_its_occupied_voxels_in_whole_mips():
    occ = np.zeros((16, 8, 16), bool)
    occ[3, 5, 9] = occ[6, 6, 10] = True
    assert occupied_box(occ, 4) == (slice(3, 7), slice(4, 8), slice(9, 13))
    assert occupied_box(np.zeros((4, 4, 4), bool), 2) is None
