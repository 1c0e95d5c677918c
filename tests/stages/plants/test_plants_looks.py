"""Foliage cards, textures, materials and the look measures (crown opacity,
foliage vs wood area, LAI) of the plants stage."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stages.plants import cards, measure, textures
from stages.plants.mesh import Part
from stages.plants.reference import VERT
from stages.plants.stage import PRESETS
from pipeline.opencl import get_cl

TREES = ("broadleaf", "conifer")


def _rgba(res):
    return np.concatenate([res.cards.albedo, res.cards.alpha[..., None]], -1)


@pytest.fixture(scope="module")
def looks(preset_builds):
    """Crown opacity and areas of every preset at every LOD."""
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    out = {}
    for name in TREES + ("shrub",):
        res = preset_builds[name]
        cov = res.cards.coverage if res.cards is not None else None
        rgba = _rgba(res) if res.cards is not None else None
        out[name] = [{"opacity": measure.crown_opacity(cl_env, parts, PRESETS[name], rgba)["mean"],
                      "foliage": measure.foliage_area(parts, cov, measure.cards_per_cluster(PRESETS[name], cov is not None)),
                      "wood": measure.surface_area(parts.get("Wood"))}
                     for parts in res.lods]
    return out


@pytest.mark.parametrize("name", TREES)
def test_tree_crowns_are_dense_and_leafy(looks, name):
    lv = looks[name]
    assert lv[0]["opacity"] >= 0.6, f"{name}: crown opacity {lv[0]['opacity']:.3f} at LOD0"
    assert lv[0]["foliage"] >= 2.0 * lv[0]["wood"], f"{name}: foliage {lv[0]['foliage']:.1f} m2, wood {lv[0]['wood']:.1f} m2"


@pytest.mark.parametrize("name", TREES + ("shrub",))
def test_lower_lods_keep_the_crown(looks, preset_builds, name):
    lv = looks[name]
    assert len(lv) == len(preset_builds[name].lods) >= 3
    for k, e in enumerate(lv[1:], 1):
        assert abs(e["opacity"] - lv[0]["opacity"]) <= 0.1, f"{name} LOD{k}: {e['opacity']:.3f} vs {lv[0]['opacity']:.3f}"
        assert e["foliage"] > 0.0


def _square(x0, x1, y0=0.0, y1=1.0, z=0.0):
    v = np.zeros((4, VERT), np.float32)
    v[:, 0:3] = [[z, y0, x0], [z, y0, x1], [z, y1, x1], [z, y1, x0]]
    v[:, 3:6] = [1.0, 0.0, 0.0]
    v[:, 6:8] = [[0, 0], [1, 0], [1, 1], [0, 1]]
    return Part(v, np.array([[0, 1, 2], [0, 2, 3]]), np.arange(4))


def test_crown_opacity_of_two_squares_with_a_gap_is_two_thirds(cl_env):
    """Two opaque unit squares one width apart, seen face on: the hull is
    3 x 1, two thirds of it covered."""
    leaves = Part.concat([_square(0.0, 1.0), _square(2.0, 3.0)])
    parts = {"Leaves": leaves}
    spec = PRESETS["shrub"].model_copy(update={})
    opaque = np.ones((8, 8, 4), np.float32)
    co = measure.crown_opacity(cl_env, parts, spec, opaque, azimuths=1, size=240)
    assert abs(co["mean"] - 2.0 / 3.0) < 0.02
    # a texture transparent on its right half halves each square: hull 2.5 wide, 1 covered
    half = opaque.copy()
    half[:, 4:, 3] = 0.0
    co = measure.crown_opacity(cl_env, parts, spec, half, azimuths=1, size=240)
    assert abs(co["mean"] - 1.0 / 2.5) < 0.02


def test_the_opposite_azimuth_measures_what_a_render_from_there_would(cl_env):
    """crown_opacity renders half of an even number of azimuths: the other
    half (opposite views, the same lines of sight) must equal the value of
    the plant turned by 180 degrees seen from the first azimuth."""
    rng = np.random.default_rng(3)
    squares = [_square(x, x + w) for x, w in zip(rng.random(6) * 4, 0.3 + rng.random(6))]
    leaves = Part.concat(squares)
    leaves.verts[:, 0] += rng.random(len(leaves.verts)) * 0.8  # not flat: depth along the view
    leaves.verts[:, 1] += np.repeat(rng.random(len(squares)) * 2, 4)
    spec = PRESETS["shrub"].model_copy(update={})
    cut = np.ones((8, 8, 4), np.float32)
    cut[2:5, 5:, 3] = 0.0
    two = measure.crown_opacity(cl_env, {"Leaves": leaves}, spec, cut, azimuths=2, size=96)
    turned = Part(leaves.verts.copy(), leaves.tris, leaves.weld)
    turned.verts[:, [0, 2]] *= -1.0
    turned.verts[:, [3, 5]] *= -1.0
    one = measure.crown_opacity(cl_env, {"Leaves": turned}, spec, cut, azimuths=1, size=96)
    assert 0.05 < one["mean"] < 0.95
    assert two["per_azimuth"][1] == pytest.approx(one["mean"], abs=0.01)


def test_foliage_area_counts_card_coverage():
    leaves = _square(0.0, 2.0)
    assert measure.foliage_area({"Leaves": leaves}, 0.25) == pytest.approx(0.5)
    assert measure.foliage_area({"Leaves": leaves}, None) == pytest.approx(2.0)
    assert measure.foliage_area({"Leaves": leaves}, 0.25, 2) == pytest.approx(0.25)  # a crossed pair counts once


@pytest.mark.parametrize("name", ["conifer", "broadleaf", "shrub", "meadow_flower"])
def test_card_bake_is_a_textured_cluster(cl_env, name):
    b = cards.bake(cl_env, PRESETS[name], 7, size=64)
    assert 0.05 < b.coverage < 0.95
    assert b.alpha.min() == 0.0 and b.alpha.max() == 1.0
    assert np.allclose(np.linalg.norm(b.normal, axis=-1), 1.0, atol=1e-4) and (b.normal[..., 2] >= 0).all()
    green = b.albedo[b.alpha >= 0.5]
    assert np.median(green[:, 1]) > np.median(green[:, 0])  # foliage is green
    again = cards.bake(cl_env, PRESETS[name], 7, size=64)
    assert np.array_equal(b.albedo, again.albedo) and np.array_equal(b.alpha, again.alpha)
    uv = b.template.rows[:, 6:8]
    assert uv.min() == 0.0 and uv.max() == 1.0
    # thickness and translucency: only where foliage is, thicker foliage passes less light
    covered = b.alpha >= 0.5
    assert (b.thickness[b.alpha == 0] == 0).all() and (b.thickness[covered] > 0).mean() > 0.95
    assert (b.translucency >= 0).all() and b.translucency.max() <= cards.LEAF_TRANSMITTANCE[PRESETS[name].leaf.shape]
    t, tr = b.thickness[covered], b.translucency[covered]
    thick = t > np.median(t)
    assert tr[thick].mean() < tr[~thick].mean()


def test_bark_tiles_without_a_seam():
    albedo, normal = textures.bark_texture(128, (0.3, 0.25, 0.2), 3)
    lum = albedo.mean(-1)
    inner_u = np.abs(np.diff(lum, axis=1)).mean()
    seam_u = np.abs(lum[:, 0] - lum[:, -1]).mean()
    inner_v = np.abs(np.diff(lum, axis=0)).mean()
    seam_v = np.abs(lum[0] - lum[-1]).mean()
    assert seam_u < 2.0 * inner_u and seam_v < 2.0 * inner_v
    # and a copy shifted by half a period would show a seam if it were not periodic: it differs
    assert np.abs(lum - np.roll(lum, 64, 1)).mean() > inner_u
    assert np.allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-5)


def test_asset_materials_read_existing_textures(small_run):
    """Every texture a material reads exists, is a PNG (colour, sRGB) or an
    EXR (data, raw), relative, with sourceColorSpace authored."""
    from pxr import Sdf, Usd, UsdShade

    out, _ = small_run
    top = out["plants.assets"]
    stage = Usd.Stage.Open(str(top))
    seen = 0
    for prim in stage.Traverse(Usd.PrimAllPrimsPredicate):
        sh = UsdShade.Shader(prim)
        if not sh or sh.GetIdAttr().Get() != "UsdUVTexture":
            continue
        f = sh.GetInput("file").Get()
        assert isinstance(f, Sdf.AssetPath) and f.path.startswith("./")
        assert f.resolvedPath, f"{prim.GetPath()}: {f.path} does not resolve"
        cs = sh.GetInput("sourceColorSpace").Get()
        assert (f.path.endswith(".png") and cs == "sRGB") or (f.path.endswith(".exr") and cs == "raw"), (f.path, cs)
        seen += 1
    assert seen >= 4
    for name in ("bush",):
        layer = Usd.Stage.Open(str(top.parent / f"{name}.usdc"))
        data = json.loads(layer.GetDefaultPrim().GetCustomDataByKey("worldbake:measures"))
        assert data["crown_opacity"] > 0 and data["foliage_area_m2"] > 0 and len(data["levels"]) >= 2
        mat = UsdShade.Material(layer.GetPrimAtPath(f"/{name}/Looks/FoliageCards"))
        surf = UsdShade.Shader(layer.GetPrimAtPath(f"/{name}/Looks/FoliageCards/Surface"))
        assert mat and surf.GetInput("opacityThreshold").Get() == 0.5
        assert surf.GetInput("opacity").HasConnectedSource() and surf.GetInput("normal").HasConnectedSource()
        tint = UsdShade.Shader(layer.GetPrimAtPath(f"/{name}/Looks/FoliageCards/Tint"))
        assert tint.GetIdAttr().Get() == "UsdPrimvarReader_float3" and tint.GetInput("varname").Get() == "tint"
        assert "primvars:tint" in mat.GetPrim().GetCustomDataByKey("worldbake:tint")
        for key in ("Translucency", "Thickness"):
            tex = UsdShade.Shader(layer.GetPrimAtPath(f"/{name}/Looks/FoliageCards/{key}Texture"))
            assert tex.GetInput("file").Get().path.endswith(f"_foliage_{key.lower()}.exr")
            assert mat.GetPrim().GetCustomDataByKey(f"worldbake:{key.lower()}")
    grass = Usd.Stage.Open(str(top.parent / "grass.usdc"))
    vset = grass.GetDefaultPrim().GetVariantSets().GetVariantSet("lod")
    vset.SetVariantSelection(vset.GetVariantNames()[-1])
    cards_prim = grass.GetPrimAtPath("/grass/Geom/Cards")
    assert cards_prim, "the last grass LOD is the slice tuft"
    mat, _ = UsdShade.MaterialBindingAPI(cards_prim).ComputeBoundMaterial()
    assert mat.GetPrim().GetName() == "GrassSlices"


def test_grass_slice_atlas_shows_the_tuft(preset_builds):
    sl = preset_builds["grass"].slices
    assert sl.albedo.shape[1] == 4 * sl.albedo.shape[0]
    n = sl.alpha.shape[0]
    for i in range(4):  # every quarter holds a tuft: covered at the bottom, open at the top corners
        q = sl.alpha[:, i * n:(i + 1) * n]
        assert 0.1 < q.mean() < 0.9 and q[-4:].mean() > q[:4].mean()
