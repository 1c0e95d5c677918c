"""The report's tables the plants stage declares: instances per prototype
and the triangles of each lod variant, read from a composed world."""
from __future__ import annotations

from stages.plants.report_tables import instance_and_lod_tables, lod_counts


def test_lod_counts_count_what_a_renderer_draws_on_the_composed_prototype(tmp_path):
    from pxr import Sdf, Usd, UsdGeom

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
    counts, distances = instance_and_lod_tables(path)
    assert counts.rows == (("tree", 3, 60),) and counts.footer == ("total", 3, "")
    assert distances.columns == ("asset", "LOD0 triangles", "LOD1 triangles")
    assert distances.rows == (("tree", (20, "from 0 m"), (6, "from 12 m")),)
