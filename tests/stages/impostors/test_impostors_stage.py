"""The impostors stage on a tiny plants layer (helpers.make_plants): what it
writes, the layer a DCC composes over the prototypes, and the forest a
viewport opens (one set of meshes per species, payload tiles)."""
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline import exr, usdio
from pipeline.config import canonical_params
from pipeline.contract import RunContext
from stages.impostors import STAGE
from stages.impostors.stage import ImpostorsParams

from .helpers import make_plants
from pipeline.opencl import get_cl

SMALL = {"frames": 6, "atlas_px": 256, "min_frame_px": 32, "small_plant_frame_px": 32, "samples": 1, "ao_rays": 1,
         "slice_px": 32, "drawn_slice_px": 32, "grass_slice_px": 32, "card_px": 32, "heldout_px": 48, "heldout_samples": 2, "heldout_stride": 54}


def _run(folder: Path, plants: Path, placed, params=SMALL, units=None):
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    folder.mkdir(parents=True, exist_ok=True)
    p = ImpostorsParams.model_validate(params)
    ctx = RunContext(cl=cl_env, stage=STAGE, key="test", out_dir=folder, seed=7,
                     provenance={"stage": "impostors", "version": 1, "key": "test", "params": canonical_params(p),
                                 "seed": 7}, project_root=Path("."), units=units)
    inputs = {"plants": plants}
    if placed is not None:
        inputs["placed"] = {"placed": placed}
    return STAGE.run(ctx, inputs, p), ctx


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    root = tmp_path_factory.mktemp("impostors")
    plants = make_plants(root / "plants")
    out, ctx = _run(root / "run", plants, ["tree", "grass"])
    return root, plants, out, ctx


def test_every_placed_species_has_its_textures(baked):
    root, plants, out, ctx = baked
    tex = root / "run" / "textures"
    assert ctx.metrics["built"] == ["grass", "tree"]
    for name in ("tree", "grass"):
        names = exr.read_attributes(tex / f"{name}_atlas.exr")
        assert (tex / f"{name}_atlas_albedo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        info = json.loads(names["worldbake:impostor"])
        assert info["layout"] == "hemi" and info["frames"] == 6
        assert info["error"]["views"] > 0 and "worst_view" in info["error"]
        assert 3 <= len(info["cutout"]["uv"]) <= 8 and 0.0 < info["cutout"]["area_fraction"] <= 1.0
        assert "slices_drawn_error" in info
        for axis in ("xpos", "xneg", "ypos", "yneg", "zpos", "zneg"):
            assert (tex / f"{name}_card_{axis}.png").is_file()
    assert (tex / "tree_slices.exr").is_file() and (tex / "tree_slices.png").is_file()
    assert (tex / "grass_tuft.png").is_file() and (tex / "grass_tuft_top.png").is_file()
    assert not (tex / "grass_slices.png").exists()


def test_unplaced_species_get_nothing(tmp_path, baked):
    root, plants, _, _ = baked
    out, ctx = _run(tmp_path / "only_grass", plants, ["grass", "oak"],
                    {**SMALL, "frames": 3, "atlas_px": 64, "min_frame_px": 8, "small_plant_frame_px": 8, "heldout_stride": 648})
    assert ctx.metrics["built"] == ["grass"]
    assert not list((tmp_path / "only_grass" / "textures").glob("tree_*"))


def test_an_unchanged_plant_is_not_baked_again(tmp_path):
    """The stage runs again when any plant changed (its key hashes the whole
    plants layer), but a species whose plant did not change has its
    impostors linked from its earlier bake: the same bytes a clean bake
    writes, not baked again; a unit with an altered file is baked again."""
    from pipeline.store import Store
    from pipeline.units import Units

    def run(folder, plants, build):
        store = Store(build)
        units = Units(store.units, store.tmp, "impostors", {"stage": "impostors", "version": 1, "seed": 7})
        _, ctx = _run(folder, plants, ["tree", "grass"], units=units)
        return ctx

    def files(folder):
        return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}

    before, after = make_plants(tmp_path / "p1"), make_plants(tmp_path / "p2", leaves=240)  # the tree changed
    reused = {n: s["reused"] for n, s in run(tmp_path / "r1", before, tmp_path / "build").metrics["species"].items()}
    assert reused == {"grass": False, "tree": False}
    ctx = run(tmp_path / "r2", after, tmp_path / "build")
    assert {n: s["reused"] for n, s in ctx.metrics["species"].items()} == {"grass": True, "tree": False}
    grass = {f: b for f, b in files(tmp_path / "r1").items() if "grass_" in f}
    assert grass and all(files(tmp_path / "r2")[f] == b for f, b in grass.items())
    clean = run(tmp_path / "clean", after, tmp_path / "clean_build")
    assert all(not s["reused"] for s in clean.metrics["species"].values())
    assert files(tmp_path / "r2") == files(tmp_path / "clean")  # layer, stats, textures: history leaves no trace

    unit = tmp_path / "build" / "units" / "impostors" / ctx.units.used["grass"]
    (unit / "grass_atlas.exr").write_bytes(b"not an exr")
    again = run(tmp_path / "r3", after, tmp_path / "build")
    assert {n: s["reused"] for n, s in again.metrics["species"].items()} == {"grass": False, "tree": True}
    assert files(tmp_path / "r3") == files(tmp_path / "clean")


def test_held_out_error_is_measured_and_plausible(baked):
    _, _, out, ctx = baked
    for name, s in ctx.metrics["species"].items():
        for which in ("error", "slices_error", "slices_drawn_error"):
            e = s[which]
            assert 0.0 <= e["alpha_iou"]["min"] <= e["alpha_iou"]["median"] <= 1.0
            assert e["psnr_db"]["median"] > 15.0, (name, which, e)
    tree = ctx.metrics["species"]["tree"]["error"]
    assert tree["alpha_iou"]["median"] > 0.6, tree  # thin grass blades at 48 px are another matter
    for s in ctx.metrics["species"].values():
        d = s["lod_switch_m"]
        assert list(d)[0] == "LOD0" and d["LOD0"] == 0.0 and list(d.values()) == sorted(d.values())
        assert {"impostor", "slices"} & set(d) and list(d.values())[-1] > 0  # the far end is an impostor


def _world(folder: Path, plants: Path, impostors: Path):
    """The world's composition: the plants and impostors referenced on the
    vegetation's prototype classes, over a vegetation layer of 2 species x
    many tiles (stages.vegetation.usd_layer) -- as stages/world does it."""
    from stages.vegetation import usd_layer as veg
    from stages.vegetation.placement import Instances
    from stages.world import impostor_layer
    from stages.world.stage import bind_plant_assets

    rng = np.random.default_rng(2)
    sets = {}
    for name, n in (("tree", 120), ("grass", 300)):
        pos = np.stack([rng.uniform(0, 100, n), np.zeros(n), rng.uniform(0, 100, n)], 1).astype(np.float32)
        q = np.tile(np.array([0, 0, 0, 1], np.float16), (n, 1))
        sets[name] = Instances(name, pos, q, np.ones((n, 3), np.float32), np.ones(n, np.float32),
                               rng.random(n).astype(np.float32), np.arange(n, dtype=np.int64), np.ones(n, np.float32))
    folder.mkdir(parents=True, exist_ok=True)
    veg.write(folder / "instances.usdc", {}, sets, {"tree": 4.0, "grass": 0.4}, {"tree": "lsystem", "grass": "grass"},
              0.0, 0.0, 100.0, 40, 5.0)
    root = folder / "world.usda"
    usdio.write_root_layer(root, {}, ["./instances.usdc"])
    placed = {"placed": ["grass", "tree"], "prototypes": {n: f"/World/Vegetation/Prototypes/{n}" for n in sets}}

    class Ctx:
        def asset_path(self, target):
            return usdio.relative_asset_path(target, root)

    bound = bind_plant_assets(root, placed, plants, Ctx())
    done = impostor_layer.bind_impostors(root, bound, placed, impostors, Ctx())
    assert done == ["grass", "tree"]
    return root


def test_the_forest_has_one_set_of_meshes_per_species_and_payload_tiles(baked, tmp_path):
    from pxr import Usd, UsdGeom

    root, plants, out, _ = baked
    world = _world(tmp_path / "world", plants, out["impostors.layer"])
    assert usdio.validate(world) == []
    stage = Usd.Stage.Open(str(world))
    instancers = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    tiles = {p.GetParent().GetPath() for p in instancers}
    assert len(tiles) >= 4
    assert all(stage.GetPrimAtPath(t).HasAuthoredPayloads() for t in tiles)
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    for proto in stage.GetPrototypes():
        meshes += [p for p in Usd.PrimRange(proto) if p.IsA(UsdGeom.Mesh)]
    # per species its LOD0 meshes and its impostor billboards, once: tree Wood, Leaves, Slices; grass Blades, Tuft, TuftTop
    assert sorted(p.GetName() for p in meshes) == sorted(["Wood", "Leaves", "Slices", "Blades", "Tuft", "TuftTop"])
    for pi in instancers:
        proto = stage.GetPrimAtPath(UsdGeom.PointInstancer(pi).GetPrototypesRel().GetTargets()[0])
        assert proto.IsInstance()
    unloaded = Usd.Stage.Open(str(world), Usd.Stage.LoadNone)
    assert not [p for p in unloaded.Traverse() if p.IsA(UsdGeom.PointInstancer)]


def test_prototypes_gain_the_impostor_lod_purposes_and_cards(baked, tmp_path):
    from pxr import Usd, UsdGeom

    root, plants, out, _ = baked
    stage = Usd.Stage.Open(str(_world(tmp_path / "world", plants, out["impostors.layer"])))
    proto = stage.GetPrimAtPath("/World/Vegetation/Prototypes/tree")
    vset = proto.GetVariantSets().GetVariantSet("lod")
    assert vset.GetVariantNames() == ["LOD0", "LOD1", "impostor"]
    assert vset.GetVariantSelection() == "LOD0"
    geom, imp = proto.GetChild("Geom"), proto.GetChild("Impostor")
    assert UsdGeom.Imageable(geom).ComputePurpose() == UsdGeom.Tokens.render
    assert UsdGeom.Imageable(imp).ComputePurpose() == UsdGeom.Tokens.proxy
    assert UsdGeom.Imageable(geom).GetProxyPrimRel().GetTargets() == [imp.GetPath()]
    model = UsdGeom.ModelAPI(proto)
    assert model.GetModelCardGeometryAttr().Get() == "box"
    card = model.GetModelCardTextureXPosAttr().Get()
    assert card.resolvedPath and Path(card.resolvedPath).is_file()
    switch = json.loads(proto.GetCustomDataByKey("worldbake:lod_switch_m"))["ladder_m"]
    assert switch["LOD0"] == 0.0 and list(switch.values()) == sorted(switch.values())
    assert list(switch)[-1] in ("impostor", "slices")
    # for a USD consumer, only variants: the `impostor` variant (the slices) last, from the slices' own distance
    data = json.loads(proto.GetCustomDataByKey("worldbake:lod_switch_m"))
    variants = data["variant_m"]
    assert set(variants) <= set(vset.GetVariantNames()) and list(variants)[-1] == "impostor"
    assert variants["impostor"] >= data["own_distance_m"]["slices"] - 1e-3
    assert list(variants.values()) == sorted(variants.values())
    assert json.loads(proto.GetCustomDataByKey("worldbake:impostor"))["error"]["views"] > 0
    vset.SetVariantSelection("impostor")
    assert UsdGeom.Imageable(imp).ComputePurpose() == UsdGeom.Tokens.default_
    assert not [p for p in Usd.PrimRange(geom) if p.IsA(UsdGeom.Mesh)]


def test_the_lod_ladder_drops_what_a_cheaper_lod_beats():
    from stages.impostors.usd_layer import lod_ladder

    assert lod_ladder({"LOD0": 0.0, "LOD1": 5.0, "LOD2": 400.0, "impostor": 90.0, "slices": 300.0}) == \
        {"LOD0": 0.0, "LOD1": 5.0, "impostor": 90.0, "slices": 300.0}
    assert lod_ladder({"LOD0": 0.0, "LOD1": 5.0, "impostor": 2.0}) == {"LOD0": 0.0, "impostor": 2.0}


def test_bad_sizes_are_refused_before_any_work():
    import pydantic

    from pipeline.contract import CheckContext, ParamError
    from stages.impostors.stage import check

    with pytest.raises(pydantic.ValidationError, match="power of two"):
        ImpostorsParams(atlas_px=1000)
    with pytest.raises(ParamError, match="texels per frame"):
        check(ImpostorsParams(frames=64, atlas_px=128), CheckContext(seed=1, project_root=Path("."), inputs={}))


def test_the_impostor_prim_draws_thin_slabs_and_the_blend_sheet_lies_beside(baked):
    """A USD viewer draws the drawn_slice_slabs sheet (every quad of it); the
    slice_slabs sheet an engine blends is written beside and named in the
    impostor's customData."""
    from pxr import Usd, UsdGeom

    root, _, out, _ = baked
    params = ImpostorsParams.model_validate(SMALL)
    assert params.drawn_slice_slabs != params.slice_slabs  # the defaults, or this test checks nothing
    tex = root / "run" / "textures"
    tiles = {name: json.loads(exr.read_attributes(tex / f"tree_{name}.exr")["worldbake:tiles"])
             for name in ("slices", "blend_slices")}
    assert tiles["slices"]["cols"] == params.drawn_slice_slabs and tiles["blend_slices"]["cols"] == params.slice_slabs
    assert tiles["slices"]["rows"] == tiles["blend_slices"]["rows"] == 8
    stage = Usd.Stage.Open(str(out["impostors.layer"]))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Plants/tree/Impostor/Slices"))
    # 4 slicings x front/back x slabs, each quad two triangles
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == 2 * 4 * 2 * params.drawn_slice_slabs
    info = json.loads(stage.GetPrimAtPath("/Plants/tree").GetCustomDataByKey("worldbake:impostor"))
    assert info["slices"]["slabs"] == params.slice_slabs and info["slices"]["drawn_slabs"] == params.drawn_slice_slabs
    # the drawn sheet's tiles: twice the frame side, at most drawn_slice_px; the blended one's half the frame side
    assert tiles["slices"]["tile_px"] == min(params.drawn_slice_px, 2 * info["frame_px"]) > info["slice_px"]
    assert tiles["blend_slices"]["tile_px"] == info["slice_px"] == min(params.slice_px, info["frame_px"] // 2)
    assert info["slice_files"]["blend_slices"]["albedo"] == "./textures/tree_blend_slices.png"
    assert not (tex / "grass_blend_slices.png").exists()


def test_thin_slabs_drawn_at_once_stay_nearer_the_mesh_from_between_the_slicings(cl_env, tmp_path):
    """Seen between two slicings (30 deg from each), every slab shows its
    content shifted by up to half its thickness x tan 30 deg: 8 slabs per
    orientation, drawn all at once as a DCC draws them, cover a sparse
    crown's mesh (the tiny tree with 150 leaves, where a gap moved is a
    pixel lost) better than 3 do."""
    from stages.impostors import measure, slices
    from worldlib.render import Prepared, Settings
    from worldlib.render.usd_asset import load_plant

    ps = load_plant(make_plants(tmp_path / "plants", leaves=150), "/Plants/tree")
    prepared = Prepared(cl_env, ps.scene)
    views = [(az, el) for az in (30.0, 90.0, 150.0, 210.0) for el in (0.0, 20.0)]
    refs = measure.References(prepared, ps, views, 64, 3)
    iou = {}
    for slabs in (3, 8):
        drawn = Prepared(cl_env, slices.sheet_scene([slices.tree_slices(prepared, slabs, 64, 2)]))
        errors = refs.measure(measure.drawn_view(drawn, ps, Settings(64, 64, samples=3)))
        iou[slabs] = float(np.mean([e.iou for e in errors]))
    assert iou[8] > iou[3] + 0.02, iou
