"""The plants stage end to end: USD assets that validate, the presets'
measured LODs, determinism per seed, params and config handling."""
import hashlib
import json
from pathlib import Path

import numpy as np
import pydantic
import pytest

from pipeline import usdio
from pipeline.config import canonical_params, load_config
from pipeline.contract import RunContext
from pipeline.errors import InputError
from pipeline.registry import all_stages
from stages.plants import STAGE
from stages.plants.stage import PRESETS, PlantsParams


from tests.stages.plants.helpers import SMALL, run_stage


def test_four_presets_load_and_are_the_defaults():
    assert {"conifer", "broadleaf", "shrub", "grass"} <= set(PRESETS)
    p = PlantsParams()
    assert sorted(p.build) == sorted(PRESETS) and p.species == PRESETS


def test_assets_validate_and_have_the_promised_structure(small_run):
    from pxr import Kind, Usd, UsdGeom, UsdShade

    out, ctx = small_run
    top = out["plants.assets"]
    assert top == ctx.path("plants.assets") and top.name == "plants.usda"
    assert usdio.validate(top) == []
    stage = Usd.Stage.Open(str(top))
    assert stage.GetDefaultPrim().GetPath() == "/Plants"
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert Usd.ModelAPI(stage.GetDefaultPrim()).GetKind() == Kind.Tokens.group
    assert sorted(c.GetName() for c in stage.GetDefaultPrim().GetChildren()) == ["bush", "grass"]
    assert (top.parent / "bush.usdc").is_file() and (top.parent / "grass.usdc").is_file()
    assert not (top.parent / "conifer.usdc").exists()  # not in build: not built
    for name in ("bush", "grass"):
        prim = stage.GetPrimAtPath(f"/Plants/{name}")
        assert Usd.ModelAPI(prim).GetKind() == Kind.Tokens.component
        refs = prim.GetPrimStack()[0].referenceList.prependedItems
        assert refs[0].assetPath == f"./{name}.usdc"
        vset = prim.GetVariantSets().GetVariantSet("lod")
        names = vset.GetVariantNames()
        assert names == [f"LOD{k}" for k in range(4)] and vset.GetVariantSelection() == "LOD0"
        lods = json.loads(prim.GetCustomDataByKey("worldbake:lods"))
        assert [e["level"] for e in lods] == [0, 1, 2, 3]
        tris = []
        for k, v in enumerate(names):
            vset.SetVariantSelection(v)
            hint = UsdGeom.ModelAPI(prim).GetExtentsHint()
            assert len(hint) == 2 and hint[1][1] > hint[0][1]
            n = 0
            for mp in Usd.PrimRange(prim):
                if not mp.IsA(UsdGeom.Mesh):
                    continue
                m = UsdGeom.Mesh(mp)
                assert m.GetSubdivisionSchemeAttr().Get() == "none"
                pv = UsdGeom.PrimvarsAPI(m)
                for pname in ("normals", "st", "wind:branchWeight", "wind:flutterWeight", "wind:phase", "wind:pivot", "displayColor"):
                    assert pv.GetPrimvar(pname).IsDefined(), (name, v, mp.GetPath(), pname)
                npts = len(m.GetPointsAttr().Get())
                for pname in ("wind:branchWeight", "wind:flutterWeight", "wind:phase", "wind:pivot"):
                    assert len(pv.GetPrimvar(pname).Get()) == npts
                mat, _ = UsdShade.MaterialBindingAPI(mp).ComputeBoundMaterial()
                assert mat and mat.GetSurfaceOutput().HasConnectedSource()
                ext = m.GetExtentAttr().Get()
                assert ext is not None and len(ext) == 2
                n += len(m.GetFaceVertexCountsAttr().Get())
            tris.append(n)
            assert n == lods[k]["triangles"]
        vset.SetVariantSelection("LOD0")
        assert all(b <= 0.5 * a for a, b in zip(tris, tris[1:]))


def test_metrics_are_json_and_complete(small_run):
    _, ctx = small_run
    m = json.loads(json.dumps(ctx.metrics))
    assert m["built"] == ["grass", "bush"]
    bush = m["species"]["bush"]
    for key in ("modules", "segments", "leaves", "seconds_total", "wood_check", "lods", "lod_budget_ok", "lod_halving_ok"):
        assert key in bush
    assert bush["wood_check"]["watertight"] and bush["lod_halving_ok"]


def test_same_seed_same_bytes_other_seed_other_plant(tmp_path, small_run):
    out1, _ = small_run
    out2, _ = run_stage(tmp_path / "a", SMALL, seed=1)
    out3, _ = run_stage(tmp_path / "b", SMALL, seed=2)

    def digests(top):
        return {p.relative_to(top.parent).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(top.parent.rglob("*")) if p.is_file()}

    d1, d2, d3 = digests(out1["plants.assets"]), digests(out2["plants.assets"]), digests(out3["plants.assets"])
    assert d1 == d2
    assert d1["bush.usdc"] != d3["bush.usdc"] and d1["grass.usdc"] != d3["grass.usdc"]


def test_species_built_in_two_processes_give_the_same_bytes(tmp_path, small_run, monkeypatch):
    """The worker process (started when the work is large) changes nothing."""
    from stages.plants import stage as plants_stage

    monkeypatch.setattr(plants_stage, "PARALLEL_MIN_MODULES", 0)
    calls = []
    real = plants_stage._run_jobs
    monkeypatch.setattr(plants_stage, "_run_jobs", lambda *a: calls.append(a[0]) or real(*a))
    out1, m1 = small_run
    out2, m2 = run_stage(tmp_path / "p", SMALL)
    assert len(calls[0]) >= 2 and plants_stage._parallel_ok()

    def digests(top):
        return {p.relative_to(top.parent).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(top.parent.rglob("*")) if p.is_file()}

    assert digests(out1["plants.assets"]) == digests(out2["plants.assets"])
    assert list(m1.metrics["species"]) == list(m2.metrics["species"])


def test_an_error_in_the_worker_process_fails_the_stage_with_its_message(tmp_path, monkeypatch):
    from stages.plants import stage as plants_stage

    monkeypatch.setattr(plants_stage, "PARALLEL_MIN_MODULES", 0)
    # 128 modules that draw nothing: the largest, so the worker builds it (grass: 48 blades)
    params = {"build": ["grass", "void"],
              "species": {"void": {"kind": "lsystem", "lsystem": {"axiom": "A", "rules": ["A=AA"], "iterations": 7}}}}
    with pytest.raises(InputError, match="produced no geometry"):
        run_stage(tmp_path, params)


def test_an_empty_build_writes_an_empty_valid_layer(tmp_path):
    out, ctx = run_stage(tmp_path, {"build": []})
    assert usdio.validate(out["plants.assets"]) == [] and ctx.metrics["built"] == []


def test_config_names_presets_and_overrides_them(tmp_path):
    cfg = tmp_path / "w.toml"
    cfg.write_text('seed = 3\n[plants]\nbuild = ["tallpine"]\n[plants.species.tallpine]\npreset = "conifer"\n'
                   'lsystem.iterations = 5\nleaf.needles = 6\n')
    config = load_config(cfg, all_stages(), project_root=tmp_path)
    p = config.params["plants"]
    assert p.build == ["tallpine"]
    assert p.species["tallpine"].lsystem.iterations == 5 and p.species["tallpine"].leaf.shape == "needles"
    assert p.species["tallpine"].lsystem.axiom == PRESETS["conifer"].lsystem.axiom
    assert PlantsParams.model_validate(json.loads(canonical_params(p))) == p
    cfg.write_text('[plants]\nbuild = ["oak"]\n')
    with pytest.raises(InputError, match="oak"):
        load_config(cfg, all_stages(), project_root=tmp_path)


@pytest.mark.parametrize("bad, words", [
    ({"species": {"x y": {"preset": "shrub"}}}, "prim name"),
    ({"species": {"a": {"preset": "nope"}}}, "preset 'nope' not found"),
    ({"species": {"a": {"kind": "grass"}}}, "needs a [grass] table"),
    ({"lod_ratio": 0.7}, "less than or equal"),
    ({"build": ["grass", "grass"]}, "twice"),
])
def test_bad_params_are_rejected(bad, words):
    with pytest.raises(pydantic.ValidationError, match=words.replace("[", r"\[").replace("]", r"\]")):
        PlantsParams.model_validate(bad, strict=True)


def test_an_exploding_lsystem_fails_the_stage_with_its_size(tmp_path):
    params = {"build": ["boom"], "max_modules": 20000,
              "species": {"boom": {"kind": "lsystem", "lsystem": {"axiom": "A", "rules": ["A=F[+A][-A]A"], "iterations": 30}}}}
    with pytest.raises(InputError, match="max_modules = 20,000"):
        run_stage(tmp_path, params)


# ------------------------------------------------------------------ the presets at full size


@pytest.mark.parametrize("name", ["conifer", "broadleaf", "shrub"])
def test_preset_wood_is_one_watertight_manifold_solid(preset_builds, name):
    m = preset_builds[name].metrics
    c = m["wood_check"]
    assert c["watertight"] and c["manifold"] and c["winding_consistent"]  # trimesh and manifold3d agree
    assert c["degenerate"] == 0 and c["min_area"] > 0 and c["normals_agree"] == 1.0
    assert c["manifold_volume"] == pytest.approx(c["volume"], rel=1e-6) and c["volume"] > 0
    for chk in m["wood_lod_checks"]:
        assert chk["watertight"] and chk["manifold"] and chk["degenerate"] == 0


@pytest.mark.parametrize("name", ["conifer", "broadleaf", "shrub", "grass"])
def test_preset_lod_errors_and_triangle_counts(preset_builds, name):
    info = preset_builds[name].lod_info
    assert len(info) == 4
    assert info[1]["hausdorff_fraction"] <= 0.01, info
    assert info[2]["hausdorff_fraction"] <= 0.03, info
    for a, b in zip(info, info[1:]):
        assert b["triangles"] <= 0.5 * a["triangles"]
        assert b["hausdorff_fraction"] > 0


def test_presets_are_plants_of_plausible_size(preset_builds):
    heights = {}
    for name, res in preset_builds.items():
        pos = np.concatenate([p.welded()[0] for p in res.lods[0].values() if p.n_tris])
        heights[name] = pos[:, 1].max() - pos[:, 1].min()
        assert pos[:, 1].min() > -0.3  # grows up from the origin
    assert 4 < heights["conifer"] < 9 and 4 < heights["broadleaf"] < 9
    assert 0.6 < heights["shrub"] < 2.5 and 0.15 < heights["grass"] < 0.6
