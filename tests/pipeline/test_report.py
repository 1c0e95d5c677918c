"""report.html's generic parts on a hand-made store (no bake): warnings,
the stage table and the run time against error series come from whatever
the runs' manifests hold, for any stage name."""
from __future__ import annotations

import json

import numpy as np

from pipeline import exr
from pipeline.grid import Grid
from pipeline.report import World, stage_rows, time_error_series, warnings, write_report
from pipeline.store import Store, write_json


def _run(store: Store, stage: str, key: str, metrics: dict, outputs: dict | None = None) -> None:
    folder = store.folder(stage, key)
    folder.mkdir(parents=True)
    write_json(folder / "manifest.json", {"stage": stage, "key": key, "params": {}, "inputs": {}, "files": {},
                                          "outputs": outputs or {}, "timings": {"run_s": 1.5}, "metrics": metrics})


def test_warnings_table_and_series_from_any_stage(tmp_path):
    store = Store(tmp_path / "build")
    suitability = np.zeros((4, 5, 2), np.float32)
    suitability[..., 0] = 0.5  # fern finds land, cactus none
    _run(store, "flora", "k1", {"unplaced": ["cactus"], "lod_budget_ok": False, "fit_error": 0.25,
                                "chain": [{"seconds": 0.1, "max_error": 0.3}, {"seconds": 0.4, "max_error": 0.1}]},
         {"flora.maps": {"kind": "grid", "file": "maps.exr", "channels": ["suitability.cactus", "suitability.fern"],
                         "channel_units": {}}})
    exr.write_grid(store.folder("flora", "k1") / "maps.exr",
                   Grid(suitability[..., ::-1].copy(), 10.0, ("suitability.cactus", "suitability.fern")))
    _run(store, "brandnew", "k2", {"voxels": 12})
    manifest = {"world": "w", "config": "configs/x.toml", "seed": 1, "outputs": ["brandnew"],
                "overrides": {"flora.density": 2, "ghost.param": 1}, "params": {"flora": {}, "brandnew": {}},
                "artifacts": [{"stage": "flora", "key": "k1"}, {"stage": "brandnew", "key": "k2"}],
                "steps": [{"stage": "flora", "key": "k1", "status": "ran", "seconds": 1.6},
                          {"stage": "brandnew", "key": "k2", "status": "cached", "seconds": 0.0}]}
    world = World(store, manifest)
    text = "\n".join(warnings(world))
    assert "cactus found no suitable land" in text and "fern" not in text
    assert "unplaced: cactus" in text and "lod_budget_ok is false" in text
    assert "ghost.param" in text and "flora.density" not in text
    rows = {r["stage"]: r for r in stage_rows(world)}
    assert rows["brandnew"]["status"] == "cached" and rows["brandnew"]["stats"] == {"voxels": 12}
    assert rows["flora"]["errors"] == {"fit_error": 0.25}
    (series,) = time_error_series(world)
    assert series["stage"] == "flora" and series["points"] == [(0.1, 0.3), (0.4, 0.1)]
    out = tmp_path / "page"
    out.mkdir()
    page = write_report(store, out, manifest, None).read_text()
    assert "<td>brandnew</td>" in page and "cactus found no suitable land" in page


def test_lod_counts_count_what_a_renderer_draws_on_the_composed_prototype(tmp_path):
    from pxr import Sdf, Usd, UsdGeom

    from pipeline.report import lod_counts

    path = tmp_path / "w.usda"
    stage = Usd.Stage.CreateNew(str(path))
    proto = stage.CreateClassPrim("/Protos/tree")  # abstract, like the world's prototype classes

    def quads(prim_path, n, purpose=None):
        mesh = UsdGeom.Mesh.Define(stage, prim_path)
        mesh.CreateFaceVertexCountsAttr([4] * n)
        if purpose:
            mesh.CreatePurposeAttr(purpose)
        return mesh

    vset = proto.GetVariantSets().AddVariantSet("lod")
    for name, n in (("LOD0", 10), ("LOD1", 3)):
        vset.AddVariant(name)
        vset.SetVariantSelection(name)
        with vset.GetVariantEditContext():
            quads(f"/Protos/tree/Geom_{name}", n, UsdGeom.Tokens.render)
    vset.SetVariantSelection("LOD0")
    proto.SetCustomDataByKey("worldbake:lod_switch_m", '{"ladder_m": {"LOD0": 0.0, "LOD1": 12.5}}')
    quads("/Protos/tree/Proxy", 7, UsdGeom.Tokens.proxy)  # not drawn by a final render
    quads("/Protos/tree/Off", 5).GetPrim().SetActive(False)
    quads("/Protos/tree/Hidden", 5).CreateVisibilityAttr(UsdGeom.Tokens.invisible)
    inst = UsdGeom.PointInstancer.Define(stage, "/World/Trees")
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Trees/Prototypes/tree")])
    ref = stage.DefinePrim("/World/Trees/Prototypes/tree")
    ref.GetInherits().AddInherit("/Protos/tree")
    ref.SetInstanceable(True)
    inst.CreateProtoIndicesAttr([0, 0, 0])
    stage.GetRootLayer().Save()
    instances, lods = lod_counts(path)
    assert instances == [{"prototype": "tree", "instances": 3}]
    assert lods == [{"asset": "tree", "lods": {"LOD0": 20, "LOD1": 6},  # the instance repeats no row
                     "from_m": {"LOD0": 0.0, "LOD1": 12.5}}]
