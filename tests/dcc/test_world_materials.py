"""Every normal map of the exported world as the UsdPreviewSurface spec
has it (issue 30): each UsdUVTexture that feeds a `normal` input (of a
UsdPreviewSurface, or through a NodeGraph output a DCC wires into one: the
ground's detail layer) authors scale (2, 2, 2, 1) and bias (-1, -1, -1, 0),
and its file's values lie in 0..1. Over the small default world the other
tests here bake (no Blender needed): plants, impostors, the ground."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np


def _normal_sources(stage) -> set[str]:
    """The paths of the prims whose outputs connect to an input or NodeGraph
    output named `normal` (or `..._normal`: the detail layer's)."""
    from pxr import Usd, UsdShade

    found = set()
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        connectable = UsdShade.ConnectableAPI(prim)
        if not connectable:
            continue
        ports = list(connectable.GetInputs()) + (list(UsdShade.NodeGraph(prim).GetOutputs())
                                                 if prim.IsA(UsdShade.NodeGraph) else [])
        for port in ports:
            if port.GetBaseName() == "normal" or port.GetBaseName().endswith("_normal"):
                found.update(str(s.source.GetPrim().GetPath()) for s in port.GetConnectedSources()[0])
    return found


def _files(asset) -> list[Path]:
    """The file(s) of an asset path, its UDIM tiles expanded."""
    path = Path(asset.resolvedPath or asset.path)
    if "<UDIM>" not in path.name:
        return [path]
    pattern = re.escape(path.name).replace(re.escape("<UDIM>"), r"\d{4}")
    return sorted(p for p in path.parent.glob("*") if re.fullmatch(pattern, p.name))


def test_every_normal_map_of_the_world_is_stored_0_1_with_scale_and_bias(small_world):
    import OpenImageIO as oiio
    from pxr import Usd, UsdShade

    from worldlib import materials

    stage = Usd.Stage.Open(str(small_world["folder"]))
    checked, problems = [], []
    textures = [UsdShade.Shader(p) for p in stage.Traverse(Usd.TraverseInstanceProxies())
                if UsdShade.Shader(p) and UsdShade.Shader(p).GetIdAttr().Get() == "UsdUVTexture"]
    normal_sources = _normal_sources(stage)
    for tex in textures:
        if str(tex.GetPath()) not in normal_sources:
            continue
        where = tex.GetPath()
        get = lambda name: tuple(float(v) for v in tex.GetInput(name).Get()) if tex.GetInput(name) else None
        if get("scale") != materials.NORMAL_SCALE or get("bias") != materials.NORMAL_BIAS:
            problems.append(f"{where}: scale {get('scale')} bias {get('bias')}")
        files = _files(tex.GetInput("file").Get())
        if not files or not all(f.is_file() for f in files):
            problems.append(f"{where}: file {tex.GetInput('file').Get()} not found")
            continue
        for f in files:
            px = np.asarray(oiio.ImageBuf(str(f)).get_pixels(oiio.FLOAT), np.float32)[..., :3]
            if px.min() < 0.0 or px.max() > 1.0:
                problems.append(f"{where}: {f.name} holds {px.min():.3f}..{px.max():.3f}, outside 0..1")
        checked.append(str(where))
    assert not problems, "\n".join(problems[:20])
    # something of each kind was checked: plant leaves and bark, impostor slices, the ground's detail
    assert any("/Prototypes/" in w or "Plants" in w for w in checked), checked[:10]
    assert any("Impostor" in w for w in checked), checked[:10]
    assert any("/Terrain/" in w for w in checked), checked[:10]
