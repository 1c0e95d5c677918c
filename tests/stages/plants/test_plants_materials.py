"""The plant assets' foliage as a DCC renders it: leaves wound toward their
normals (so a DCC's shading normal is on the lit side), the light through
the leaves that UsdPreviewSurface cannot pass baked into the diffuse
colour as a gain measured in the renderer's own display light, and the
materials that carry it (cut-out opacity through a reader of its own)."""
from __future__ import annotations

import math
import types

import numpy as np
import pytest

from stages.plants import leaves, measure
from stages.plants.mesh import Part
from stages.plants.reference import VERT
from stages.plants.stage import PRESETS
from worldlib import materials


def _frames(n: int, seed: int = 2) -> np.ndarray:
    """(n, LEAF) leaf records with random turtle frames (U = H x L, as the
    turtle keeps them) and unit scale."""
    from stages.plants.reference import LEAF

    rng = np.random.default_rng(seed)
    rec = np.zeros((n, LEAF), np.float32)
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        h, l_ = q[:, 0], q[:, 1]
        rec[i, 0:3] = rng.normal(size=3)
        rec[i, 3:6], rec[i, 6:9], rec[i, 9:12] = h, l_, np.cross(h, l_)
        rec[i, 12] = 1.0
    return rec


def _winding_agrees(part: Part) -> np.ndarray:
    p = part.verts[:, 0:3].astype(np.float64)
    t = part.tris
    face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    return (face * part.verts[:, 3:6].astype(np.float64)[t].sum(1)).sum(1) > 0


@pytest.mark.parametrize("name", ["broadleaf", "conifer", "meadow_flower"])
def test_placed_leaves_are_wound_toward_their_normals(name):
    tmpl = leaves.make_template(PRESETS[name].leaf)
    rec = _frames(20)
    part = leaves.instance(None, tmpl, rec)
    assert _winding_agrees(part).all()
    assert _winding_agrees(leaves.instance(None, leaves.card_of(tmpl), rec)).all()
    # the mirror facing_normals undoes: the template's frame placed as it is winds every leaf backwards
    raw = Part(part.verts, (tmpl.tris[None] + (np.arange(len(rec)) * len(tmpl.rows))[:, None, None]).reshape(-1, 3),
               part.weld)
    assert not _winding_agrees(raw).any()


def _quad_part(normal_x: float) -> Part:
    """One 1 m vertical leaf quad in the y-z plane, its normal along x
    (wound toward it: the renderer turns the normal with the face)."""
    v = np.zeros((4, VERT), np.float32)
    v[:, 0:3] = [[0, 0, -0.5], [0, 0, 0.5], [0, 1, 0.5], [0, 1, -0.5]]
    v[:, 3:6] = [normal_x, 0.0, 0.0]
    return Part(v, leaves.facing_normals(v, np.array([[0, 1, 2], [0, 2, 3]])), np.arange(4))


def test_translucency_gain_of_a_lone_leaf_is_the_display_lights(cl_env):
    """Side views at 4 azimuths see a lone quad from its two faces (and
    twice edge-on): one face lit by the sun (G cos), the other passing T G
    cos of it, both under the open sky S (AO 1): gain (G cos + T G cos + 2
    S) / (G cos + 2 S)."""
    import inspect

    from worldlib.render import Image

    spec = types.SimpleNamespace(leaf_color=(0.2, 0.5, 0.1), leaf_tip_color=(0.2, 0.5, 0.1), bark_color=(0.3, 0.2, 0.1))
    sun, g, t = measure._display_light()
    assert g > 0 and 0 < t < 1
    sky = inspect.signature(Image.shaded).parameters["sky"].default
    cos = abs(float(sun[0]))
    want = (g * cos + t * g * cos + 2 * sky) / (g * cos + 2 * sky)
    got = measure.translucency_gains(cl_env, {"Leaves": _quad_part(1.0)}, spec, None)["side"]
    assert got == pytest.approx(want, rel=2e-3)
    assert measure.translucency_gains(cl_env, {"Leaves": _quad_part(-1.0)}, spec, None)["side"] == pytest.approx(want, rel=2e-3)
    # no foliage: no gain
    assert measure.translucency_gains(cl_env, {"Wood": _quad_part(1.0)}, spec, None) == {"side": 1.0, "front_lit": 1.0, "dcc": 1.0}


def test_foliage_materials_carry_the_gain_and_a_separate_cut_out(small_run):
    from pxr import Usd, UsdShade

    out, ctx = small_run
    top = out["plants.assets"]
    for name in ("bush", "grass"):
        gain = ctx.metrics["species"][name]["looks"]["translucency_gain"]
        assert 1.0 < gain < 2.0
        layer = Usd.Stage.Open(str(top.parent / f"{name}.usdc"))
        looks = [p for p in layer.GetPrimAtPath(f"/{name}/Looks").GetChildren()
                 if p.GetName() in ("FoliageCards", "Blades", "GrassSlices")]
        assert looks
        for look in looks:
            colour = UsdShade.Shader(look.GetChild("AlbedoTexture"))
            assert colour.GetPrim().GetCustomDataByKey(materials.TRANSLUCENCY_GAIN) == pytest.approx(gain)
            assert tuple(colour.GetInput("scale").Get()) == pytest.approx((gain, gain, gain, 1.0))
            surf = UsdShade.Shader(look.GetChild("Surface"))
            if surf.GetInput("opacity"):
                src = surf.GetInput("opacity").GetConnectedSource()[0].GetPrim()
                assert src.GetName() == "OpacityTexture" and not UsdShade.Shader(src).GetInput("scale")
                assert surf.GetInput("opacityThreshold").Get() == 0.5
        bark = layer.GetPrimAtPath(f"/{name}/Looks/Bark/AlbedoTexture")
        assert not bark or bark.GetCustomDataByKey(materials.TRANSLUCENCY_GAIN) is None
    assert math.isfinite(gain)
