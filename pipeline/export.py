"""`worldbake export`: a baked world as a self-contained copy for handoff.

A folder export holds world.usda, the world's manifest (and report, when
there is one) and one folder per stage named after the stage (`terrain/`
would be the world stage's `world/`), with every file the stage run wrote;
a stage whose earlier run a cached step still reads (early cutoff) gets a
second folder `<stage>-<key prefix>`. Every asset path in every layer is
rewritten to point inside the copy, relative to the layer, so the copy
opens wherever it is moved and after build/ is deleted.

A .usdz is made from such a folder in a temporary place, after replacing
each EXR texture the layers reference by an 8-bit PNG (USDZ viewers such as
ARKit and Quick Look read PNG and JPEG only): colour textures are encoded
sRGB (the shader's sourceColorSpace set to sRGB); data textures (normal maps
with their scale and bias, and whatever the layer marks sourceColorSpace
raw: translucency, thickness) keep their values, linear. UDIM patterns
(`ground.<UDIM>.exr`) are converted tile by tile; USD resolves each tile.
Only what the layers reference goes into the package.

Every file the world needs goes with it: each asset path of every layer
reachable from world.usda (sublayers, references and payloads, inside every
variant, so each level of a `mip` or `lod` variant set; UDIM tiles; texture
and OpenVDB volume files). `export_problems` checks an export (folder or
.usdz) for it: a file that does not resolve, or that resolves outside the
package or export folder, is named. `worldbake export` and `worldbake
validate` fail on any.

OpenVDB files inside a .usdz: the USDZ specification lists USD layers,
PNG/JPEG/EXR/AVIF images and M4A/MP3/WAV audio, and OpenUSD's validator
reports any other file in a package (UnsupportedFileExtensionInPackage);
the package still carries the .vdb files (a volume whose grids are left out
is a world missing a part), and `export_problems` reports that validator's
finding for them as a note, not an error. Blender (5.0) imports every
Volume prim of a .usdz but no grids: its USD importer copies a packaged
file out only for textures, and gives the volume the package path
`world.usdz[x.vdb]`, which it then looks for on disk ("x.vdb] not found").
The package is a plain zip whose root is world.usda: unzipped, it is a
folder export (PNG textures) whose volumes Blender reads; the note says so.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from .errors import InputError
from .store import MANIFEST, Store

LAYER_SUFFIXES = (".usda", ".usdc", ".usd")
WORLD_FILES = ("world.usda", MANIFEST, "report.html")


def export_world(store: Store, world: str, dest: Path) -> Path:
    """Write the export; returns the root layer (folder) or the .usdz file."""
    src = store.worlds / world
    if not (src / MANIFEST).is_file():
        raise InputError(f"no baked world {world!r} in {store.worlds}")
    if not (src / "world.usda").is_file():
        raise InputError(f"world {world!r} has no world.usda (its bake did not include the world stage)")
    if dest.exists():
        raise InputError(f"{dest} exists; export writes a new folder or file")
    dest.parent.mkdir(parents=True, exist_ok=True)
    if dest.suffix == ".usdz":
        with tempfile.TemporaryDirectory(prefix="worldbake-usdz-", dir=dest.parent) as tmp:
            folder = Path(tmp) / "world"
            _copy_folder(store, world, folder)
            _textures_to_png(folder)
            _package(folder / "world.usda", dest)
        return dest
    work = dest.with_name(dest.name + f".part-{os.getpid()}")
    shutil.rmtree(work, ignore_errors=True)
    try:
        _copy_folder(store, world, work)
        os.rename(work, dest)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return dest / "world.usda"


def folder_names(store: Store, world: str) -> dict[tuple[str, str], str]:
    """(stage, key) -> its folder in the export: the stage's name for the
    run the world names, `<stage>-<key[:8]>` for earlier runs it still reads."""
    manifest = json.loads((store.worlds / world / MANIFEST).read_text())
    named = {e["stage"]: e["key"] for e in manifest["artifacts"]}
    names = {}
    for stage, key in sorted(store.closure(set(named.items()))):
        names[(stage, key)] = stage if named.get(stage) == key else f"{stage}-{key[:8]}"
    return names


def _copy_folder(store: Store, world: str, out: Path) -> None:
    src = store.worlds / world
    names = folder_names(store, world)
    where = {store.folder(s, k).resolve(): out / name for (s, k), name in names.items()}
    where[src.resolve()] = out
    out.mkdir(parents=True)
    for f in WORLD_FILES:
        if (src / f).is_file():
            shutil.copy2(src / f, out / f)
    for p in src.glob("*.png"):  # the report's pictures
        shutil.copy2(p, out / p.name)
    for (stage, key), name in names.items():
        shutil.copytree(store.folder(stage, key), out / name)
    layers = [out / "world.usda"] + [p for name in names.values() for p in sorted((out / name).rglob("*"))
                                     if p.suffix in LAYER_SUFFIXES]
    back = {v: k for k, v in where.items()}  # export folder -> the store folder it came from
    for layer_path in layers:
        origin = _origin(layer_path, out, back)
        _rewrite_layer(layer_path, origin, where)


def _origin(layer_path: Path, out: Path, back: dict[Path, Path]) -> Path:
    """Where a copied layer was in the store."""
    for folder, source in back.items():
        try:
            rel = layer_path.relative_to(folder)
        except ValueError:
            continue
        if folder == out and len(rel.parts) > 1:
            continue  # a file of a stage folder, not of the world folder
        return source / rel
    raise AssertionError(layer_path)


def _rewrite_layer(layer_path: Path, origin: Path, where: dict[Path, Path]) -> None:
    """Every asset path of the layer, which sat at `origin`, re-pointed to
    the copy of its target, relative to the layer's new place."""
    from pxr import Sdf, UsdUtils

    layer = Sdf.Layer.FindOrOpen(str(layer_path))

    def remap(path: str) -> str:
        if not path or "://" in path:
            return path
        target = Path(os.path.normpath(origin.parent / path)) if not os.path.isabs(path) else Path(path)
        for folder, copy in where.items():
            try:
                rel = target.relative_to(folder)
            except ValueError:
                continue
            new = os.path.relpath(copy / rel, layer_path.parent).replace(os.sep, "/")
            return new if new.startswith("../") else "./" + new
        raise InputError(f"{origin}: asset path {path!r} points outside the world's artifacts; cannot export it")

    UsdUtils.ModifyAssetPaths(layer, remap)
    layer.Save()


# --------------------------------------------------------------------------- .usdz


def _texture_attributes(layer):
    """(attribute spec, its shader prim spec) for every asset-valued input
    of the layer's shaders ending in .exr."""
    from pxr import Sdf

    found = []

    def visit(path):
        if not path.IsPropertyPath():
            return
        spec = layer.GetAttributeAtPath(path)
        if spec is None or spec.typeName != Sdf.ValueTypeNames.Asset or not spec.HasDefaultValue():
            return
        value = spec.default
        if isinstance(value, Sdf.AssetPath) and value.path.lower().endswith(".exr"):
            found.append((spec, layer.GetPrimAtPath(path.GetPrimPath())))
    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found


def _normal_map_shaders(layer) -> set:
    """Prim paths of the shaders whose output feeds a surface's `inputs:normal`."""
    from pxr import Sdf

    found = set()

    def visit(path):
        if not path.IsPropertyPath() or path.name != "inputs:normal":
            return
        spec = layer.GetAttributeAtPath(path)
        if spec is not None:
            found.update(source.GetPrimPath() for source in spec.connectionPathList.GetAddedOrExplicitItems())
    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found


def _scale_and_bias(layer, shader) -> None:
    from pxr import Gf, Sdf

    for name, value in (("inputs:scale", Gf.Vec4f(2, 2, 2, 1)), ("inputs:bias", Gf.Vec4f(-1, -1, -1, 0))):
        attr = Sdf.AttributeSpec(shader, name, Sdf.ValueTypeNames.Float4)
        attr.default = value


def _exr_to_png(src: Path, dst: Path, colour: bool, signed: bool = False) -> None:
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(src))
    pixels = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
    if colour:
        from .exr import srgb8

        out = srgb8(pixels[..., :3]) if pixels.shape[-1] >= 3 else srgb8(np.repeat(pixels, 3, axis=-1))
        if pixels.shape[-1] == 4:
            out = np.concatenate([out, np.round(np.clip(pixels[..., 3:4], 0, 1) * 255).astype(np.uint8)], axis=-1)
    else:
        data = pixels * 0.5 + 0.5 if signed else pixels
        out = np.round(np.clip(data, 0.0, 1.0) * 255.0).astype(np.uint8)
    buf = oiio.ImageBuf(np.ascontiguousarray(out))
    buf.specmod().attribute("oiio:UnassociatedAlpha", 1)  # PNG alpha is straight: OIIO would divide rgb by it
    if not buf.write(str(dst), oiio.UINT8):
        raise OSError(f"cannot write {dst}: {oiio.geterror()}")


def _textures_to_png(folder: Path) -> None:
    """Each EXR texture a layer references replaced by a PNG beside it."""
    from pxr import Sdf

    for layer_path in sorted(p for p in folder.rglob("*") if p.suffix in LAYER_SUFFIXES):
        layer = Sdf.Layer.FindOrOpen(str(layer_path))
        changed = False
        normal_inputs = _normal_map_shaders(layer)
        for spec, shader in _texture_attributes(layer):
            path = spec.default.path
            scaled = "inputs:scale" in shader.attributes or "inputs:bias" in shader.attributes
            # a normal map stored -1..1 (float EXR) becomes 0..1 in 8 bits, read back with scale 2 and bias -1
            signed_normal = not scaled and shader.path in normal_inputs
            # data the shader reads as it is stored (translucency, thickness, roughness: sourceColorSpace raw) stays
            # linear in the PNG; only colour is encoded sRGB
            space = shader.attributes.get("inputs:sourceColorSpace")
            colour = not scaled and not signed_normal and (space is None or space.default != "raw")
            full = Path(os.path.normpath(layer_path.parent / path))
            pattern = re.escape(full.name).replace(re.escape("<UDIM>"), r"\d{4}")
            files = sorted(p for p in full.parent.glob("*.exr") if re.fullmatch(pattern, p.name))
            if not files:
                raise InputError(f"{layer_path}: texture {path} not found in the export")
            for f in files:
                png = f.with_suffix(".png")
                if not png.exists():
                    _exr_to_png(f, png, colour, signed=signed_normal)
            spec.default = Sdf.AssetPath(path[: -len(".exr")] + ".png")
            if signed_normal:
                _scale_and_bias(layer, shader)
            if colour and space is not None:
                space.default = "sRGB"
            changed = True
        if changed:
            layer.Save()


def _package(root_layer: Path, dest: Path) -> None:
    from pxr import Sdf, UsdUtils

    work = dest.with_name(dest.name + f".part-{os.getpid()}.usdz")
    try:
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(root_layer)), str(work)):
            raise OSError(f"cannot write {dest}")
        os.rename(work, dest)
    finally:
        work.unlink(missing_ok=True)


# --------------------------------------------------------------------------- completeness

PACKAGED_VOLUME_SUFFIXES = (".vdb",)  # carried inside a .usdz although the USDZ spec's file list does not name them


def missing_files(root: Path, within: Path | None = None) -> list[str]:
    """Every file the world at `root` (a root layer or a .usdz) needs and
    does not hold: an asset path of a layer reachable from it (sublayers,
    references, payloads, in every variant; a UDIM pattern needs a tile)
    that does not resolve; in a .usdz one that resolves outside the
    package; with `within`, one that resolves outside that folder. Each
    entry names the file."""
    from pxr import Sdf, UsdUtils

    root = Path(root).resolve()
    layers, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(root)))  # USD warns per miss too
    problems = [f"missing: {p}" for p in sorted(unresolved)]
    found = sorted({layer.realPath or layer.identifier for layer in layers} | set(assets))
    if root.suffix == ".usdz":
        package = f"{root}["
        problems += [f"outside the package: {p}" for p in found if not p.startswith(package) and p != str(root)]
    elif within is not None:
        folder = Path(within).resolve()
        problems += [f"outside {folder}: {p}" for p in found if not Path(p).resolve().is_relative_to(folder)]
    return problems


def export_problems(root: Path, within: Path | None = None) -> tuple[list[str], list[str]]:
    """(errors, notes) of the world at `root`: every pxr.UsdValidation error
    and every missing file (missing_files); OpenVDB files inside a .usdz are
    notes (module docstring), not errors."""
    from . import usdio

    errors, volumes = [], []
    for e in usdio.validate(root):
        if e.startswith("UnsupportedFileExtensionInPackage") and any(f"{s}'" in e for s in PACKAGED_VOLUME_SUFFIXES):
            volumes.append(e)
        else:
            errors.append(e)
    notes = [f"the package carries {len(volumes)} OpenVDB volume files ({', '.join(PACKAGED_VOLUME_SUFFIXES)}), "
             f"which the USDZ specification's file list does not name (OpenUSD's validator: {volumes[0]}); "
             f"Blender 5.0 reads no volume grids inside a .usdz: unzip it (`unzip {Path(root).name} -d DIR`) and "
             "import DIR/world.usda, or export a folder"] if volumes else []
    return errors + missing_files(root, within), notes

