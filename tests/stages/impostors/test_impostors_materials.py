"""The materials of a small world's plants and impostors, as a DCC reads
them by the UsdPreviewSurface spec: every UsdUVTexture feeding a `normal`
input decodes a file stored 0..1 with scale (2, 2, 2, 1) and bias
(-1, -1, -1, 0); every texture names its sourceColorSpace (sRGB for 8-bit
colour, raw for data); foliage is cut out (opacityThreshold), its cards
double-sided, and carries its translucency gain on the diffuse colour."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib import materials
from worldlib.render.usd_asset import read_image

from .test_impostors_stage import SMALL as SMALL_IMPOSTORS, _run

SPECIES = ["bush", "grass"]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The plants stage (tests/stages/plants/helpers.SMALL: a shrub and
    grass) and the impostors over it, composed as the world composes them."""
    from tests.stages.plants.helpers import SMALL, run_stage

    root = tmp_path_factory.mktemp("materials")
    out, _ = run_stage(root / "plants", SMALL)
    plants = next(iter(out.values()))
    _run(root / "impostors", plants, SPECIES, SMALL_IMPOSTORS)
    top = root / "world.usda"
    top.write_text("#usda 1.0\n(\n    subLayers = [@./impostors/impostors.usda@, @./plants/plants.usda@]\n"
                   '    upAxis = "Y"\n)\n')
    return top


def _connected(shader_input):
    from pxr import UsdShade

    if not shader_input or not shader_input.HasConnectedSource():
        return None
    return UsdShade.Shader(shader_input.GetConnectedSource()[0].GetPrim())


def _vec(tex, name):
    value = tex.GetInput(name).Get() if tex.GetInput(name) else None
    return None if value is None else tuple(float(v) for v in value)


def spec_problems(stage) -> list[str]:
    """What in the stage's materials breaks the rules of the module docstring."""
    from pxr import Usd, UsdShade

    problems, normal_maps = [], set()
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        shader = UsdShade.Shader(prim)
        if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
            continue
        where = prim.GetPath()
        normal = _connected(shader.GetInput("normal"))
        if normal is not None:
            normal_maps.add(normal.GetPath())
            if _vec(normal, "scale") != materials.NORMAL_SCALE or _vec(normal, "bias") != materials.NORMAL_BIAS:
                problems.append(f"{where}: normal map scale {_vec(normal, 'scale')} bias {_vec(normal, 'bias')}")
            texels = read_image(normal.GetInput("file").Get().resolvedPath, "raw")[..., :3]
            if texels.min() < 0.0 or texels.max() > 1.0:
                problems.append(f"{where}: normal map values {texels.min():.3f}..{texels.max():.3f} outside 0..1")
            n = materials.decode_normal(texels)
            if np.linalg.norm(n, axis=-1).max() > 1.01 or n[..., 2].mean() <= 0.0:
                problems.append(f"{where}: the decoded normals are no tangent-space normals")
        opacity = _connected(shader.GetInput("opacity"))
        if opacity is not None:
            threshold = shader.GetInput("opacityThreshold")
            if not threshold or not (threshold.Get() or 0.0) > 0.0:
                problems.append(f"{where}: opacity without an opacityThreshold (alpha-blended, not cut out)")
            colour = _connected(shader.GetInput("diffuseColor"))
            if opacity.GetPath() == (colour.GetPath() if colour else None) and _vec(colour, "scale") not in (
                    None, (1.0, 1.0, 1.0, 1.0)):
                problems.append(f"{where}: opacity read from the scaled colour reader")
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        tex = UsdShade.Shader(prim)
        if not tex or tex.GetIdAttr().Get() != "UsdUVTexture":
            continue
        space = tex.GetInput("sourceColorSpace").Get() if tex.GetInput("sourceColorSpace") else None
        file = tex.GetInput("file").Get().path
        # 8-bit colour is sRGB; data (a normal map in any format, float images) raw
        want = "sRGB" if file.lower().endswith(".png") and prim.GetPath() not in normal_maps else "raw"
        if space != want:
            problems.append(f"{prim.GetPath()}: sourceColorSpace {space} for {file} (want {want})")
        gain = prim.GetCustomDataByKey(materials.TRANSLUCENCY_GAIN)
        if gain is not None and (gain < 1.0 or not np.allclose(_vec(tex, "scale") or 0.0, (gain, gain, gain, 1.0),
                                                               rtol=1e-6)):
            problems.append(f"{prim.GetPath()}: translucency gain {gain} with scale {_vec(tex, 'scale')}")
    return problems


def test_every_material_of_the_world_follows_the_spec(world):
    from pxr import Usd

    stage = Usd.Stage.Open(str(world))
    assert spec_problems(stage) == []
    # and there is something to check: normal maps on plants and impostors, cut-out foliage
    normals = [p for p in stage.Traverse() if p.GetName() == "NormalTexture"]
    assert any("/Impostor/" in str(p.GetPath()) for p in normals) and any("/Looks/" in str(p.GetPath()) and
                                                                         "/Impostor/" not in str(p.GetPath())
                                                                         for p in normals)


def test_foliage_is_cut_out_double_sided_and_carries_its_gain(world):
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(world))
    for name in SPECIES:
        prim = stage.GetPrimAtPath(f"/Plants/{name}")
        vset = prim.GetVariantSets().GetVariantSet("lod")
        mesh_lods = [v for v in vset.GetVariantNames() if v.startswith("LOD")]
        for v in mesh_lods:
            vset.SetVariantSelection(v)
            for mesh in (m for m in Usd.PrimRange(stage.GetPrimAtPath(f"/Plants/{name}/Geom")) if m.IsA(UsdGeom.Mesh)):
                if mesh.GetName() == "Wood":
                    continue
                assert UsdGeom.Mesh(mesh).GetDoubleSidedAttr().Get(), f"{mesh.GetPath()} ({v}) is one-sided"
                mat, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
                surf = mat.ComputeSurfaceSource()[0]
                if surf.GetInput("opacity"):
                    assert surf.GetInput("opacityThreshold").Get() == pytest.approx(0.5)
        albedo = [p for p in Usd.PrimRange(prim) if p.GetName() == "AlbedoTexture"
                  and p.GetParent().GetName() in ("FoliageCards", "Blades", "GrassSlices", "Slices", "Tuft", "TuftTop")]
        gains = {round(float(p.GetCustomDataByKey(materials.TRANSLUCENCY_GAIN)), 4) for p in albedo}
        assert len(gains) == 1 and 1.0 < gains.pop() < 2.0, f"{name}: foliage gains {gains}"


def test_the_checker_finds_a_signed_normal_map(tmp_path):
    """The spec check can fail: a normal map stored -1..1 without scale and
    bias (what the impostors wrote before) and an alpha-blended card."""
    from pxr import Sdf, Usd

    from stages.impostors import images
    from worldlib import images as worldlib_images

    n = np.zeros((8, 8, 3), np.float32)
    n[..., 0], n[..., 2] = -0.6, 0.8
    images.write_exr(tmp_path / "n.exr", [n], ("R", "G", "B"), {})
    worldlib_images.write_png(tmp_path / "a.png", np.full((8, 8, 3), 0.3, np.float32), np.ones((8, 8), np.float32))
    stage = Usd.Stage.CreateInMemory()
    _, surf, texture = materials.textured_preview_surface(stage, "/M", 0.5)
    nmap = texture("NormalTexture", str(tmp_path / "n.exr"), "raw", "clamp")
    surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
        nmap.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    colour = texture("AlbedoTexture", str(tmp_path / "a.png"), "raw", "clamp")
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
        colour.CreateOutput("a", Sdf.ValueTypeNames.Float))
    problems = "\n".join(spec_problems(stage))
    assert "normal map scale None" in problems and "outside 0..1" in problems
    assert "opacityThreshold" in problems and "sourceColorSpace raw for" in problems


def test_slice_quads_are_cut_to_their_covered_texels(cl_env):
    """A quad spans its tile's covered texels and one more around them, its
    uv cut alike, so the billboards draw what the whole tile's quad drew
    with fewer empty layers for a DCC's rays to cross."""
    from dataclasses import replace

    from stages.impostors import slices
    from worldlib.render import Camera, Settings, render

    t = 16
    sheet = slices._sheet("slices", 1, 1, t)
    rgba = np.zeros((t, t, 4), np.float32)
    rgba[4:10, 6:12] = (0.2, 0.6, 0.1, 1.0)  # rows 4..9 (from the top), columns 6..11
    normal = np.zeros((t, t, 3), np.float32)
    normal[..., 2] = 1.0
    right, up, view = np.eye(3)
    corners = slices._quad(0.0, view, right, up, -1.0, 1.0, -1.0, 1.0)
    slices._place(sheet, 0, 0, rgba, normal, corners, right, up, view)
    q, uv = sheet.positions[0], sheet.uvs[0]
    assert np.allclose(q[:, 0].min(), -1 + 2 * 5 / 16) and np.allclose(q[:, 0].max(), -1 + 2 * 13 / 16)
    assert np.allclose(q[:, 1].min(), 1 - 2 * 11 / 16) and np.allclose(q[:, 1].max(), 1 - 2 * 3 / 16)
    assert np.allclose(uv.min(0), [5 / 16, 5 / 16]) and np.allclose(uv.max(0), [13 / 16, 13 / 16])
    whole = replace(sheet, positions=[corners], uvs=[np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])])
    cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), ortho_height_m=2.0)
    cut, full = (render(cl_env, slices.sheet_scene([s]), cam, Settings(64, 64, samples=2)) for s in (sheet, whole))
    assert full.alpha.sum() > 0
    assert np.array_equal(cut.alpha, full.alpha) and np.allclose(cut.albedo, full.albedo)


def test_a_slice_texel_keeps_one_of_its_samples_normals_so_a_crown_shades_as_its_needles():
    """Needles facing every way into the viewer's hemisphere, 3 x 3 samples
    per texel: each texel's normal is one of its covered samples' (the
    centre one when covered), and the mean Lambert term of the texels under a
    sun is the samples' own, where the texels' renormalized mean normals
    shade brighter."""
    from stages.impostors.slices import _one_sample_normal

    rng = np.random.default_rng(5)
    tile, s = 48, 3
    n = rng.normal(size=(tile * s, tile * s, 3))
    n[..., 2] = np.abs(n[..., 2])  # toward the viewer (+z), as a two-sided needle's shading normal faces it
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    keep = (rng.random((tile * s, tile * s)) < 0.4).astype(np.float32)
    picked = _one_sample_normal(n, keep, tile, s)

    blocks = n.reshape(tile, s, tile, s, 3).transpose(0, 2, 1, 3, 4).reshape(tile, tile, s * s, 3)
    kept = keep.reshape(tile, s, tile, s).transpose(0, 2, 1, 3).reshape(tile, tile, s * s) > 0
    covered = kept.any(-1)
    assert not picked[~covered].any()
    match = (np.abs(blocks - picked[:, :, None]).max(-1) == 0) & kept
    assert match.any(-1)[covered].all()  # one of its own covered samples, bit for bit
    centre = kept[..., s * s // 2]
    assert (picked[centre] == blocks[..., s * s // 2, :][centre]).all()

    sun = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])
    samples = float(np.clip(n[keep > 0] @ sun, 0, None).mean())
    ones = float(np.clip(picked[covered] @ sun, 0, None).mean())
    mean = (blocks * kept[..., None]).sum(2)[covered]
    mean /= np.linalg.norm(mean, axis=-1, keepdims=True)
    smooth = float(np.clip(mean @ sun, 0, None).mean())
    assert abs(ones / samples - 1) < 0.03, (ones, samples)
    assert smooth / samples - 1 > 0.08, (smooth, samples)  # what a mean normal did: a smooth, brighter crown
