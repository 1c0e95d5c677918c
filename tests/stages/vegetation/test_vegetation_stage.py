"""The stage contract, params from TOML, and run() on a small world: maps,
the USD layer (valid alone and with plant assets composed over it), every
instance on the mesh and where its species may grow, density, distances,
the species report, determinism and independence."""
import json
from pathlib import Path

import numpy as np
import pydantic
import pytest
from scipy.spatial import cKDTree

from pipeline import usdio
from pipeline.contract import Params, RunContext, Stage
from pipeline.grid import Grid
from stages.vegetation import STAGE, VegetationParams
from stages.vegetation import placement as pl
from worldlib.terrain.mesh import build_terrain_mesh, height_on_mesh

from .conftest import synthetic_height
from pipeline.opencl import get_cl

DX = 8.0
N = 128
SEED = 20261123


def test_contract():
    assert isinstance(STAGE, Stage) and STAGE.name == "vegetation" and STAGE.version >= 1
    assert STAGE.uses_seed and STAGE.uses_opencl and "mesh_max_vertices" in STAGE.shared_params
    roles = {i.role: i for i in STAGE.inputs}
    assert roles["terrain"].one_of[-2:] == ("erosion.height", "heightmap.height") and not roles["terrain"].optional
    assert all(roles[r].optional for r in ("moisture", "lakes", "rivers"))
    assert roles["moisture"].one_of == ("hydrology.moisture", "erosion.moisture")
    s = STAGE.output("vegetation.splat")
    assert s.channels == ("splat.rock", "splat.scree", "splat.grass", "splat.dry_grass", "splat.mud", "splat.snow")
    assert STAGE.output("vegetation.instances").kind == "usd"
    assert STAGE.output("vegetation.instances").file == "instances.usdc"
    assert STAGE.output("vegetation.species").kind == "json"
    assert issubclass(STAGE.params, Params)
    p = VegetationParams()
    assert {"conifer", "broadleaf", "shrub", "grass"} <= set(p.species) and p.mesh_max_vertices == 1025


def test_params_from_toml():
    import tomllib

    text = """
grow = ["conifer", "shrub", "grass", "pine"]
years = 40
[species.shrub]
density_per_ha = 90.0
slope_deg = { min = 0.0, max = 35.0, edge = 5.0 }
[species.pine]
altitude_m = { min = 900.0, max = 1600.0, edge = 100.0 }
slope_deg = { min = 0.0, max = 40.0, edge = 5.0 }
moisture = { min = 0.0, max = 1.0 }
sunlight = { min = 0.0, max = 3.0 }
density_per_ha = 50.0
scale_range = [0.5, 2.0]
"""
    p = VegetationParams.model_validate(tomllib.loads(text), strict=True)
    assert p.species["shrub"].density_per_ha == 90.0 and p.species["shrub"].slope_deg.max == 35.0
    assert p.species["shrub"].radius_m == VegetationParams().species["shrub"].radius_m  # merged over the default
    assert p.plant_species() == ["conifer", "shrub", "pine"] and p.grass_species() == "grass"


@pytest.mark.parametrize("bad,where", [
    ({"grow": ["oak"]}, "grow"),
    ({"species": {"shrub": {"density_per_ha": 5000.0}}}, "species"),  # more than min_spacing allows
    ({"species": {"shrub": {"slope_deg": {"min": 10.0, "max": 5.0}}}}, "species"),
    ({"species": {"shrub": {"slope_deg": {"min": 0.0, "max": 10.0, "edge": 6.0}}}}, "species"),
    ({"species": {"shrub": {"no_such": 1}}}, "species"),
    ({"species": {"bad name": VegetationParams().species["shrub"].model_dump()}}, "species"),
    ({"snow_min_m": 2000.0, "snow_max_m": 1000.0}, "snow_max_m"),
    ({"years": -1}, "years"),
    ({"sim_cell_m": 0.0}, "sim_cell_m"),
    ({"unknown": 1}, "unknown"),
])
def test_params_rejected(bad, where):
    with pytest.raises(pydantic.ValidationError) as e:
        VegetationParams.model_validate(bad, strict=True)
    assert where in str(e.value)


def world_inputs(with_hydrology=True):
    h = synthetic_height(N, N, DX, seed=2)
    origin = (1000.0, -500.0)
    terrain = Grid(h, DX, ("height",), origin)
    inputs = {"terrain": terrain}
    if with_hydrology:
        z, x = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
        moist = np.clip(0.5 - (h - h.mean()) / 800.0, 0, 1).astype(np.float32)
        lake = np.where((x - 30) ** 2 + (z - 90) ** 2 < 36, 2.0, 0.0).astype(np.float32)
        river = (np.abs(x - z) < 1).astype(np.float32)
        inputs["moisture"] = Grid(moist, DX, ("moisture",), origin)
        inputs["lakes"] = Grid(np.stack([lake, np.where(lake > 0, 500.0, np.nan), (lake > 0) * 1.0], -1).astype(np.float32),
                               DX, ("lake.depth", "lake.level", "lake.id"), origin)
        inputs["rivers"] = Grid(np.stack([river, river * 3.0, river], -1).astype(np.float32), DX,
                                ("river.mask", "river.width", "river.order"), origin)
    return inputs


def small_params(**over):
    base = dict(years=30, step_years=5, mesh_max_vertices=65, tile_max_instances=3000, tile_min_size_m=128.0,
                grass_max_tufts=20000,
                species={"cedar": {**VegetationParams().species["conifer"].model_dump(),
                                   "altitude_m": {"min": 5000.0, "max": 6000.0, "edge": 10.0}}},
                grow=["conifer", "broadleaf", "shrub", "grass", "cedar"])
    base.update(over)
    return VegetationParams.model_validate(base)


def run_stage(tmp: Path, params, inputs=None, seed=SEED):
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    tmp.mkdir(parents=True, exist_ok=True)
    ctx = RunContext(cl=cl_env, stage=STAGE, key="test", out_dir=tmp, seed=seed, provenance={"stage": "vegetation", "seed": seed},
                     project_root=tmp)
    return STAGE.run(ctx, inputs or world_inputs(), params), ctx


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("veg")
    params = small_params()
    out, ctx = run_stage(tmp / "a", params)
    return out, ctx, params


def instancers(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    found = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointInstancer):
            found.setdefault(prim.GetName(), []).append(UsdGeom.PointInstancer(prim))
    return stage, found


def collect(path):
    """{species: (positions, ids)} over every tile (the stage is closed after)."""
    stage, found = instancers(path)
    return {name: (np.concatenate([np.asarray(pi.GetPositionsAttr().Get()) for pi in pis]),
                   np.concatenate([np.asarray(pi.GetIdsAttr().Get()) for pi in pis])) for name, pis in found.items()}


def gather(found, name):
    return found[name]


def test_outputs_and_maps(baked):
    out, ctx, params = baked
    for name in ("vegetation.attributes", "vegetation.splat", "vegetation.grass", "vegetation.canopy"):
        g = out[name]
        assert g.channels == STAGE.output(name).channels and g.shape == (N, N) and g.data.dtype == np.float32
        assert np.isfinite(g.data).all()
    w = out["vegetation.splat"].data.astype(np.float64)
    assert w.min() >= 0 and w.max() <= 1 and np.abs(w.sum(-1) - 1).max() <= 1e-6
    gd = out["vegetation.grass"].channel("grass.density")
    assert gd.min() >= 0 and gd.max() <= 1
    maps = out["vegetation.species_maps"]
    assert set(out["vegetation.species"]["maps"]["channels"]) == set(maps.channels)
    assert out["vegetation.preview"].dtype == np.uint8 and out["vegetation.preview"].shape == (N, N, 3)
    json.dumps(out["vegetation.stats"], default=float)


def test_species_report(baked):
    out, ctx, params = baked
    rep = out["vegetation.species"]
    assert set(rep["placed"]) == {"conifer", "broadleaf", "shrub", "grass"}
    assert rep["unplaced"] == ["cedar"]  # nowhere at 5000 m: reported, not in the layer
    assert rep["species"]["cedar"]["instances"] == 0
    assert rep["prototypes"]["conifer"] == "/World/Vegetation/Prototypes/conifer"


def test_usd_layer_is_valid_and_tiled(baked):
    from pxr import Usd, UsdGeom

    out, ctx, params = baked
    path = out["vegetation.instances"]
    assert usdio.validate(path) == []
    stage, found = instancers(path)
    assert set(found) == {"conifer", "broadleaf", "shrub", "grass"}
    assert stage.GetPrimAtPath("/World/Vegetation/Prototypes/cedar").IsValid() is False
    leaves = {pi.GetPrim().GetParent().GetPath() for v in found.values() for pi in v}
    assert len(leaves) >= 4  # the quadtree split
    for name, pis in found.items():
        for pi in pis:
            protos = pi.GetPrototypesRel().GetTargets()
            assert [str(t).rsplit("/", 2)[-2:] for t in protos] == [["Prototypes", name]]
            proto = stage.GetPrimAtPath(protos[0])
            assert Usd.ModelAPI(proto).GetKind() == "component"
            assert proto.GetChild("Placeholder").IsA(UsdGeom.Cone)
            n = len(pi.GetPositionsAttr().Get())
            assert n <= params.tile_max_instances
            assert len(pi.GetOrientationsAttr().Get()) == len(pi.GetScalesAttr().Get()) == n
            pv = UsdGeom.PrimvarsAPI(pi)
            assert len(pv.GetPrimvar("age").Get()) == len(pv.GetPrimvar("random").Get()) == n
            tint = pv.GetPrimvar("tint")
            assert tint.GetInterpolation() == UsdGeom.Tokens.vertex  # one value per instance
            assert tint.GetTypeName() == "color3f[]" and len(tint.Get()) == n
    counts = out["vegetation.stats"]["instances"]
    for name, pis in found.items():
        assert sum(len(pi.GetPositionsAttr().Get()) for pi in pis) == counts[name]


def test_world_composes_plant_assets_over_the_placeholders(baked, tmp_path):
    """What the world stage does: a stronger layer references the plant asset
    on /World/Vegetation/Prototypes/<species> and deactivates the
    placeholder; every tile's prototype follows; still zero errors."""
    from pxr import Kind, Usd, UsdGeom

    out, ctx, params = baked
    assets = Usd.Stage.CreateNew(str(tmp_path / "plants.usda"))
    root = UsdGeom.Xform.Define(assets, "/Plants")
    assets.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root).SetKind(Kind.Tokens.group)
    over = Usd.Stage.CreateNew(str(tmp_path / "over.usda"))
    names = out["vegetation.species"]["placed"]
    for name in names:
        x = UsdGeom.Xform.Define(assets, f"/Plants/{name}")
        Usd.ModelAPI(x).SetKind(Kind.Tokens.component)
        UsdGeom.Cube.Define(assets, f"/Plants/{name}/Mesh").CreateExtentAttr([(-1, -1, -1), (1, 1, 1)])
        prim = over.OverridePrim(out["vegetation.species"]["prototypes"][name])
        prim.GetReferences().AddReference("./plants.usda", f"/Plants/{name}")
        over.OverridePrim(out["vegetation.species"]["prototypes"][name] + "/Placeholder").SetActive(False)
    assets.GetRootLayer().Save()
    over.GetRootLayer().Save()
    world, _ = usdio.create_stage(tmp_path / "world.usda", {})
    world.GetRootLayer().subLayerPaths.append("./over.usda")
    world.GetRootLayer().subLayerPaths.append(usdio.relative_asset_path(out["vegetation.instances"], tmp_path / "world.usda"))
    world.GetRootLayer().Save()
    assert usdio.validate(tmp_path / "world.usda") == []
    stage, found = instancers(tmp_path / "world.usda")
    for name, pis in found.items():
        proto = stage.GetPrimAtPath(pis[0].GetPrototypesRel().GetTargets()[0])
        assert proto.GetChild("Mesh").IsValid() and not proto.GetChild("Placeholder").IsActive()


def test_instances_on_the_mesh_and_where_they_may_grow(baked):
    out, ctx, params = baked
    terrain = world_inputs()["terrain"]
    mesh = build_terrain_mesh(terrain, params.mesh_max_vertices)
    dom = pl.Domain(N, N, DX, terrain.origin_m)
    attrs = out["vegetation.attributes"]
    maps = out["vegetation.species_maps"]
    water = (world_inputs()["lakes"].channel("lake.depth") > 0) | (world_inputs()["rivers"].channel("river.mask") > 0.5)
    found = collect(out["vegetation.instances"])
    h = terrain.data
    for name in found:
        pos, ids = gather(found, name)
        p64 = pos.astype(np.float64)
        assert np.abs(p64[:, 1] - height_on_mesh(mesh, p64[:, 0], p64[:, 2])).max() <= 1e-3, name
        assert len(np.unique(ids)) == len(ids)
        tr, tc = dom.world_cell(pos)
        assert (maps.channel(f"suitability.{name}")[tr, tc] > 0).all(), name
        assert not water[tr, tc].any(), name
        e = params.species[name]
        assert (attrs.channel("attr.slope")[tr, tc] < e.slope_deg.max).all(), name
        alt = out["vegetation.sites"].channel("altitude.effective")  # the altitude shifted by aspect
        assert ((alt[tr, tc] > e.altitude_m.min) & (alt[tr, tc] < e.altitude_m.max)).all(), name
        assert np.abs(alt - h).max() <= 0.5 * params.treeline_aspect_shift_m + 1e-3
        # inside the mesh footprint: first to last cell centre
        assert (pos[:, 0] >= dom.x0).all() and (pos[:, 0] <= dom.x0 + dom.width).all()


def test_density_and_distances(baked):
    out, ctx, params = baked
    terrain = world_inputs()["terrain"]
    dom = pl.Domain(N, N, DX, terrain.origin_m)
    maps = out["vegetation.species_maps"]
    found = collect(out["vegetation.instances"])
    judged = 0
    pts = {}
    for name in params.plant_species():
        if name not in found:
            continue
        pos, _ = gather(found, name)
        target = maps.channel(f"density.{name}").astype(np.float64) / 1e4
        err = pl.density_error(pos[:, 0] - dom.x0, pos[:, 2] - dom.z0, target, dom)
        judged += err["windows"]
        assert err["max_relative_error"] <= 0.05, (name, err)
        xy = pos[:, [0, 2]].astype(np.float64)
        d, _ = cKDTree(xy).query(xy, k=2)
        assert d[:, 1].min() >= params.species[name].min_spacing_m, name
        pts[name] = xy
    assert judged >= 4
    names = list(pts)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d, _ = cKDTree(pts[a]).query(pts[b], k=1)
            assert d.min() >= params.species[a].collision_radius_m + params.species[b].collision_radius_m


def test_deterministic_seeded_and_independent(baked, tmp_path):
    out, ctx, params = baked
    again, _ = run_stage(tmp_path / "b", params)
    f1 = collect(out["vegetation.instances"])
    f2 = collect(again["vegetation.instances"])
    for name in f1:
        np.testing.assert_array_equal(gather(f1, name)[0], gather(f2, name)[0])
    np.testing.assert_array_equal(out["vegetation.splat"].data, again["vegetation.splat"].data)
    other, _ = run_stage(tmp_path / "c", params, seed=SEED + 1)
    f3 = collect(other["vegetation.instances"])
    assert not np.array_equal(gather(f1, "conifer")[0][:50], gather(f3, "conifer")[0][:50])
    # the shrub's density enters neither the simulation nor any species placed before it (its heights
    # would: they decide who shades whom; grass is shaded by the canopy of every plant species, shrubs
    # included: it moves)
    sp = params.species["shrub"].model_dump()
    sp.update(density_per_ha=60.0)
    changed = small_params(species={**{k: v.model_dump() for k, v in params.species.items()}, "shrub": sp})
    moved, _ = run_stage(tmp_path / "d", changed)
    f4 = collect(moved["vegetation.instances"])
    for name in ("conifer", "broadleaf"):  # the same instances (the tiles they fall in may differ)
        (p1, i1), (p4, i4) = gather(f1, name), gather(f4, name)
        np.testing.assert_array_equal(np.sort(i1), np.sort(i4))
        np.testing.assert_array_equal(p1[np.argsort(i1)], p4[np.argsort(i4)])
    assert len(gather(f4, "shrub")[0]) < 0.7 * len(gather(f1, "shrub")[0])


def test_without_hydrology(tmp_path):
    out, _ = run_stage(tmp_path, small_params(years=10), inputs=world_inputs(with_hydrology=False))
    assert out["vegetation.stats"]["moisture_source"] == "topographic position"
    assert usdio.validate(out["vegetation.instances"]) == []
    assert out["vegetation.species"]["placed"]


def test_nothing_grows_and_no_data(tmp_path):
    """A species that fits nowhere, no grass, no years, a hole of no-data in
    the terrain: an empty but valid layer, the species reported unplaced."""
    inputs = world_inputs(with_hydrology=False)
    h = inputs["terrain"].data.copy()
    h[10:20, 10:20] = np.nan
    inputs["terrain"] = Grid(h, DX, ("height",), inputs["terrain"].origin_m)
    p = small_params(years=0, grow=["cedar"])
    out, _ = run_stage(tmp_path, p, inputs=inputs)
    assert out["vegetation.species"]["placed"] == [] and out["vegetation.species"]["unplaced"] == ["cedar"]
    assert usdio.validate(out["vegetation.instances"]) == []
    for name in ("vegetation.attributes", "vegetation.splat", "vegetation.grass", "vegetation.canopy"):
        assert np.isfinite(out[name].data).all()
    w = out["vegetation.splat"].data.astype(np.float64)
    assert np.abs(w.sum(-1) - 1).max() <= 1e-6


def test_instance_tints_vary_by_instance_site_and_age(baked):
    """The per-instance tint: near 1 on average, varied between instances,
    the same for an instance id in every call, olive on dry ground, lighter
    for young plants, and all 1 when the variation is 0."""
    from stages.vegetation import tint

    out, ctx, params = baked
    stats = out["vegetation.stats"]["tint"]
    for name, t in stats.items():
        assert all(0.8 < m < 1.2 for m in t["mean"]), (name, t)
        assert all(s > 0.03 for s in t["std"]), (name, t)
    ids = np.arange(2000, dtype=np.int64) + (np.int64(7) << 32)
    half = np.full(len(ids), 0.5)
    a = tint.instance_tints(SEED, "conifer", ids, half, np.full(len(ids), 100.0), 40.0, 0.15)
    assert np.array_equal(a, tint.instance_tints(SEED, "conifer", ids, half, np.full(len(ids), 100.0), 40.0, 0.15))
    assert not np.array_equal(a, tint.instance_tints(SEED, "shrub", ids, half, np.full(len(ids), 100.0), 40.0, 0.15))
    dry = tint.instance_tints(SEED, "conifer", ids, np.zeros(len(ids)), np.full(len(ids), 100.0), 40.0, 0.15)
    assert (dry[:, 0] / dry[:, 2]).mean() > 1.2 * (a[:, 0] / a[:, 2]).mean()  # drier: redder than bluer
    young = tint.instance_tints(SEED, "conifer", ids, half, np.zeros(len(ids)), 40.0, 0.15)
    assert young[:, 1].mean() > a[:, 1].mean()
    assert np.all(tint.instance_tints(SEED, "conifer", ids, half, half, 40.0, 0.0) == 1.0)
