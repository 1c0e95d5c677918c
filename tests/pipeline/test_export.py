"""`worldbake export` carries every file a world needs, and `worldbake
validate` names one an export leaves out. A toy world (two toy stages, no
OpenCL, a second to bake) holds every kind of asset path: a volume file in a
variant, a payload, UDIM texture tiles and a texture of the root stage."""
from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pipeline import usdio
from pipeline.cli import main
from pipeline.config import load_config
from pipeline.contract import Artifact, Input, Params, Stage
from pipeline.executors import bake_worlds
from pipeline.export import export_problems, export_world, missing_files
from pipeline.graph import build_graph
from pipeline.store import Store

HERE = Path(__file__).parent
TILES = (1001, 1002)


def _texture(path: Path, value: float) -> None:
    import OpenImageIO as oiio

    pixels = np.full((4, 4, 3), value, np.float32)
    assert oiio.ImageBuf(pixels).write(str(path), oiio.HALF), oiio.geterror()


def _material(stage, path: str, texture: str) -> None:
    from pxr import Sdf, UsdShade

    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    reader = UsdShade.Shader.Define(stage, f"{path}/St")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    tex = UsdShade.Shader.Define(stage, f"{path}/Albedo")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")


def run_part(ctx, inputs, params):
    """A layer whose variant `look` holds a Volume naming cloud.vdb, with a
    payload whose material reads UDIM tiles."""
    from pxr import UsdGeom, UsdVol

    layer = ctx.path("part.layer")
    folder = layer.parent
    (folder / "cloud.vdb").write_bytes(b"toy volume: export copies it, nothing here reads it")
    for i, tile in enumerate(TILES):
        _texture(folder / f"tex.{tile}.exr", 0.25 * (i + 1))
    payload, _ = usdio.create_stage(folder / "payload.usda", ctx.provenance, root="/Part")
    _material(payload, "/Part/Looks/Tiles", "./tex.<UDIM>.exr")
    payload.GetRootLayer().Save()
    stage, _ = usdio.create_stage(layer, ctx.provenance)
    part = UsdGeom.Xform.Define(stage, "/World/Part")
    part.GetPrim().GetPayloads().AddPayload("./payload.usda")
    vset = part.GetPrim().GetVariantSets().AddVariantSet("look")
    for name in ("cloudy", "clear"):
        vset.AddVariant(name)
    vset.SetVariantSelection("cloudy")
    with vset.GetVariantEditContext():
        vol = UsdVol.Volume.Define(stage, "/World/Part/Cloud")
        field = UsdVol.OpenVDBAsset.Define(stage, "/World/Part/Cloud/density")
        field.CreateFilePathAttr("./cloud.vdb")
        field.CreateFieldNameAttr("density")
        vol.CreateFieldRelationship("density", field.GetPath())
    vset.SetVariantSelection("clear")  # the file in the unselected variant must travel too
    stage.GetRootLayer().Save()
    return {"part.layer": layer}


def run_top(ctx, inputs, params):
    """The world's root layer: the part's layer as a sublayer, and a texture
    of its own."""
    layer = ctx.path("top.root")
    _texture(layer.parent / "ground.exr", 0.5)
    stage, _ = usdio.create_stage(layer, ctx.provenance)
    _material(stage, "/World/Looks/Ground", "./ground.exr")
    stage.GetRootLayer().subLayerPaths.append(ctx.asset_path(inputs["part"]))
    stage.GetRootLayer().Save()
    return {"top.root": layer}


STAGES = {
    "part": Stage("part", 1, "toy layer with a variant, a payload and UDIM tiles", (),
                  (Artifact("part.layer", "usd", "part.usda", shape="any",
                            beside=("payload.usda", "cloud.vdb", "tex.*.exr")),), Params, run_part, HERE),
    "top": Stage("top", 1, "toy world root", (Input("part", ("part.layer",)),),
                 (Artifact("top.root", "usd", "top.usda", shape="any", publish=True, beside=("ground.exr",)),),
                 Params, run_top, HERE),
}


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> tuple[Path, Path, Path]:
    """The toy world baked and exported as a folder and as a .usdz:
    (project, folder export's root layer, .usdz)."""
    project = tmp_path_factory.mktemp("export")
    (project / "configs").mkdir()
    (project / "configs" / "w.toml").write_text('name = "w"\nseed = 1\noutputs = ["top"]\n')
    config = load_config(project / "configs" / "w.toml", STAGES, project_root=project)
    store = Store(project / "build")
    bake_worlds(store, [config], build_graph(STAGES), log=open("/dev/null", "w"))
    folder = export_world(store, "w", project / "out" / "copy")
    usdz = export_world(store, "w", project / "out" / "w.usdz")
    return project, folder, usdz


def _validate(path: Path, capsys) -> tuple[int, str]:
    code = main(["validate", str(path)])
    return code, capsys.readouterr().out


def test_both_exports_carry_every_file_the_world_needs(world, capsys):
    project, folder, usdz = world
    from pxr import Sdf, UsdUtils

    _, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(folder)))
    names = {Path(a).name for a in assets}
    assert unresolved == [] and {"cloud.vdb", "tex.1001.exr", "tex.1002.exr", "ground.exr"} <= names
    assert all(Path(a).resolve().is_relative_to(folder.parent.resolve()) for a in assets)
    assert export_problems(folder, folder.parent) == ([], [])
    with zipfile.ZipFile(usdz) as z:
        packed = {Path(n).name for n in z.namelist()}
    # the variant's volume, the payload, every UDIM tile (as PNG: USDZ readers take no EXR)
    assert {"cloud.vdb", "payload.usda", "tex.1001.png", "tex.1002.png", "ground.png"} <= packed
    errors, notes = export_problems(usdz)
    assert errors == [] and len(notes) == 1 and "cloud.vdb" in notes[0]
    shutil.rmtree(project / "build")  # nothing may point back into the store
    for path in (folder, usdz):
        code, out = _validate(path, capsys)
        assert code == 0, out


def test_validate_names_the_file_an_export_folder_leaves_out(world, tmp_path, capsys):
    _, folder, _ = world
    for gone in ("cloud.vdb", "payload.usda", "ground.exr"):
        copy = tmp_path / gone / "copy"
        shutil.copytree(folder.parent, copy)
        victim = next(copy.rglob(gone))
        victim.unlink()
        code, out = _validate(copy, capsys)
        assert code == 1 and f"missing: {victim}" in out, (gone, out)
    copy = tmp_path / "tiles" / "copy"
    shutil.copytree(folder.parent, copy)
    for p in copy.rglob("tex.*.exr"):
        p.unlink()
    assert [m for m in missing_files(copy / "world.usda") if "tex.<UDIM>.exr" in m], "a UDIM set without a tile"


def test_the_usdz_unzipped_is_a_folder_export_with_its_volumes(world, tmp_path, capsys):
    """The way the note gives to a DCC that reads no volume inside a package
    (Blender 5.0): unzip the .usdz, open world.usda."""
    _, _, usdz = world
    _, notes = export_problems(usdz)
    assert "unzip w.usdz -d DIR" in notes[0] and "DIR/world.usda" in notes[0], notes
    with zipfile.ZipFile(usdz) as z:
        assert z.namelist()[0] == "world.usda"  # the package's root layer
        z.extractall(tmp_path / "w")
    root = tmp_path / "w" / "world.usda"
    assert export_problems(root, root.parent) == ([], [])
    from pxr import Usd, UsdVol

    stage = Usd.Stage.Open(str(root))
    stage.SetEditTarget(stage.GetSessionLayer())
    stage.GetPrimAtPath("/World/Part").GetVariantSet("look").SetVariantSelection("cloudy")
    (field,) = [p for p in stage.Traverse() if p.IsA(UsdVol.OpenVDBAsset)]
    resolved = Path(field.GetAttribute("filePath").Get().resolvedPath)  # a file on disk, as a DCC's OpenVDB wants
    assert resolved.is_file() and resolved.resolve().is_relative_to(root.parent.resolve()), resolved
    assert resolved.read_bytes() == b"toy volume: export copies it, nothing here reads it"


def test_validate_names_the_file_a_usdz_leaves_out(world, tmp_path, capsys):
    _, _, usdz = world
    with zipfile.ZipFile(usdz) as z:
        members = [(i, z.read(i)) for i in z.infolist()]
    gone = next(i.filename for i, _ in members if i.filename.endswith("cloud.vdb"))
    short = tmp_path / "short.usdz"
    with zipfile.ZipFile(short, "w", zipfile.ZIP_STORED) as z:  # usdz: stored, 64-byte aligned (writestr keeps it simple)
        for info, data in members:
            if info.filename != gone:
                z.writestr(info, data)
    code, out = _validate(short, capsys)
    assert code == 1 and gone in out and "missing" in out, out


def test_a_folder_export_naming_a_file_outside_it_fails(world, tmp_path, capsys):
    """An absolute path out of the export (the store it came from) is left
    out as surely as a deleted file."""
    from pxr import Sdf

    _, folder, _ = world
    copy = tmp_path / "copy"
    shutil.copytree(folder.parent, copy)
    outside = tmp_path / "elsewhere.vdb"
    outside.write_bytes(b"x")
    layer_path = next(copy.rglob("part.usda"))
    layer = Sdf.Layer.FindOrOpen(str(layer_path))
    spec = layer.GetAttributeAtPath("/World/Part{look=cloudy}Cloud/density.filePath")
    spec.default = Sdf.AssetPath(str(outside))
    layer.Save()
    code, out = _validate(copy, capsys)
    assert code == 1 and f"outside {copy.resolve()}: {outside}" in out, out


def test_usdz_png_keeps_raw_textures_linear_and_encodes_colour_srgb(tmp_path):
    """A .usdz's PNG of a texture the shader reads raw (translucency,
    thickness) holds its linear values; a colour texture's is sRGB."""
    import OpenImageIO as oiio
    from pxr import Sdf, Usd, UsdShade

    from pipeline import export
    from pipeline.exr import srgb8

    value = np.full((4, 4, 3), 0.25, np.float32)
    for name in ("colour", "data"):
        assert oiio.ImageBuf(value).write(str(tmp_path / f"{name}.exr"), oiio.HALF)
    stage = Usd.Stage.CreateNew(str(tmp_path / "world.usda"))
    for name, space in (("colour", "sRGB"), ("data", "raw")):
        tex = UsdShade.Shader.Define(stage, f"/M/{name}")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(f"./{name}.exr")
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(space)
    stage.Save()
    export._textures_to_png(tmp_path)
    read = lambda name: np.asarray(oiio.ImageBuf(str(tmp_path / f"{name}.png")).get_pixels(oiio.UINT8))
    assert (read("data")[..., :3] == round(0.25 * 255)).all()
    assert (read("colour")[..., :3] == srgb8(value)).all()
