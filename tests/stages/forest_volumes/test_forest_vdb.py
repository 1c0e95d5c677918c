"""Sector volumes as OpenVDB (worldlib.volumes.vdb): a sparse level and its
mip written in one batch and read back by OpenVDB itself hold the column
runs' voxels at the EXR's place; the Volume prims name them; and a bake
asking for .vdb files where no writer runs is refused at plan time."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.contract import CheckContext, ParamError
from worldlib.volumes import dense, sparse, vdb


def _sector() -> sparse.SparseLevel:
    """A 16 x 8 x 12 grid at 2 m voxels with a canopy of random voxels in
    a band (about 8 % occupied), off the origin as a sector is."""
    rng = np.random.default_rng(5)
    lv = dense.empty_level((16, 8, 12), (-310.0, 42.0, 1024.0), 2.0)
    band = np.zeros(lv.density.shape, bool)
    band[:, 3:6] = rng.random((12, 3, 16)) < 0.3
    lv.density[band] = rng.random(band.sum()) * 0.2 + 0.01
    lv.albedo[band] = lv.density[band][:, None] * rng.random((band.sum(), 3)) * [0.3, 0.5, 0.2]
    lv.surface[band] = 3 * lv.density[band]
    return sparse.from_dense(lv)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    if vdb.available() is not None:
        pytest.skip(f"no OpenVDB writer here (python3-openvdb): {vdb.available()}")
    tmp = tmp_path_factory.mktemp("vdb")
    chain = sparse.mip_chain(_sector(), 2)
    vdb.write_vdbs([(tmp / f"q.mip{k}.vdb", lv) for k, lv in enumerate(chain)])  # one run of the writer
    for k, lv in enumerate(chain):
        sparse.write_runs(tmp / f"q.mip{k}.exr", lv, k)
    return tmp, chain


def test_a_sector_level_round_trips_through_openvdb(written):
    tmp, chain = written
    for k, level in enumerate(chain):
        runs = sparse.read_runs(tmp / f"q.mip{k}.exr")
        grids = vdb.read_vdb(tmp / f"q.mip{k}.vdb", level.shape_xyz)
        full = level.to_dense()
        assert np.array_equal(grids["density"], full.density)
        occupied = full.density > 0
        np.testing.assert_allclose(grids["albedo"][occupied], full.albedo[occupied] / full.density[occupied][:, None],
                                   rtol=1e-3, atol=1e-6)
        assert not grids["albedo"][~occupied].any() and not grids["density"][~occupied].any()
        # the same place as the EXR: voxel (i, j, k)'s centre at volume_bbox_min + (i, j, k) h + h / 2
        np.testing.assert_allclose(grids["density_voxel"], runs.attributes["volume_voxel_m"], rtol=1e-12)
        np.testing.assert_allclose(grids["density_world0"], np.add(runs.attributes["volume_bbox_min"],
                                                                   runs.voxel_m / 2), rtol=0, atol=1e-9)
        z, y, x = np.nonzero(occupied)
        lo, hi = grids["density_active"]  # only the occupied voxels are active
        assert list(lo) == [x.min(), y.min(), z.min()] and list(hi) == [x.max(), y.max(), z.max()]


def test_a_level_written_twice_gives_the_same_bytes(written, tmp_path):
    """OpenVDB's random header UUID is replaced by one made from the
    content: a bake writes the same files every time."""
    tmp, chain = written
    vdb.write_vdb(tmp_path / "again.vdb", chain[0])
    assert (tmp_path / "again.vdb").read_bytes() == (tmp / "q.mip0.vdb").read_bytes()
    other = sparse.SparseLevel(chain[0].index, chain[0].density * 2, chain[0].albedo, chain[0].normal,
                               chain[0].surface, chain[0].shape_xyz, chain[0].origin, chain[0].voxel_m)
    vdb.write_vdb(tmp_path / "other.vdb", other)
    assert (tmp_path / "other.vdb").read_bytes()[vdb.UUID_AT] != (tmp / "q.mip0.vdb").read_bytes()[vdb.UUID_AT]


def test_the_volume_prims_name_the_vdb_grids(written):
    from pxr import Usd, UsdGeom, UsdVol

    tmp, chain = written
    stage = Usd.Stage.CreateNew(str(tmp / "sectors.usda"))
    UsdGeom.Xform.Define(stage, "/World/q0/FarVolume")
    dense.define_mip_volumes(stage, "/World/q0/FarVolume", chain, [f"./q.mip{k}.exr" for k in range(2)],
                             vdb_files=[f"./q.mip{k}.vdb" for k in range(2)])
    stage.GetRootLayer().Save()
    prim = stage.GetPrimAtPath("/World/q0/FarVolume")
    for k in range(2):
        prim.GetVariantSets().GetVariantSet("mip").SetVariantSelection(f"mip{k}")
        vol = UsdVol.Volume(stage.GetPrimAtPath("/World/q0/FarVolume/Volume"))
        assert set(vol.GetFieldPaths()) == {"density", "albedo"}
        for name, path in vol.GetFieldPaths().items():
            field = UsdVol.OpenVDBAsset(stage.GetPrimAtPath(path))
            assert field.GetFieldNameAttr().Get() == name
            assert Path(field.GetFilePathAttr().Get().resolvedPath) == tmp / f"q.mip{k}.vdb"
        lo, hi = vol.GetExtentAttr().Get()
        np.testing.assert_allclose([lo, hi], [chain[k].origin, chain[k].bbox_max], atol=1e-3)


def test_asking_for_vdb_without_a_writer_is_refused_at_plan_time(monkeypatch):
    """One rule: vdb = true needs the writer; without it the check (plan
    time, before any stage runs) names the key, never a bake without .vdb."""
    from stages.forest_volumes.stage import ForestVolumesParams, check

    monkeypatch.setenv("WORLDBAKE_VDB_PYTHON", sys.executable)  # the project's Python: no pyopenvdb
    vdb.available.cache_clear()
    try:
        with pytest.raises(ParamError, match="python3-openvdb") as e:
            check(ForestVolumesParams(), CheckContext(1, Path("."), {}))
        assert e.value.key == "vdb"
        check(ForestVolumesParams(vdb=False), CheckContext(1, Path("."), {}))
    finally:
        monkeypatch.undo()
        vdb.available.cache_clear()
