"""Writing the impostor textures: multi-layer EXR (`layer.channel` names,
half for colours, normals and occlusion, float for depth, zip, tiled, with
the mip levels we built per frame); the 8-bit sRGB PNG copies of albedo
that DCC materials read are worldlib.images.write_png's."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

TILE = 64


def _attributes(spec, attributes: dict) -> None:
    spec.attribute("compression", "zip")
    spec.attribute("DateTime", "")  # repeated bakes stay byte-identical
    for k, v in attributes.items():
        spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))


def write_exr(path: Path, levels: list[np.ndarray], channels: tuple[str, ...], attributes: dict,
              float_channels: tuple[str, ...] = ()) -> None:
    """levels[0] (h, w, c) and, when there are more, its mip levels
    (each half the size), written as one tiled mip-mapped EXR."""
    import OpenImageIO as oiio

    formats = tuple(oiio.FLOAT if c in float_channels else oiio.HALF for c in channels)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    for level, img in enumerate(levels):
        h, w, c = img.shape
        spec = oiio.ImageSpec(w, h, c, oiio.HALF)
        spec.channelnames = tuple(channels)
        spec.channelformats = formats
        if len(levels) > 1:
            spec.tile_width = spec.tile_height = TILE
            spec.attribute("textureformat", "Plain Texture")  # a MIP-mapped EXR
        _attributes(spec, attributes if level == 0 else {})
        mode = "Create" if level == 0 else "AppendMIPLevel"
        if not out.open(str(path), spec, mode):
            raise OSError(f"cannot write {path} level {level}: {out.geterror()}")
        if not out.write_image(np.ascontiguousarray(img, np.float32)):
            raise OSError(f"cannot write {path} level {level}: {out.geterror()}")
    if not out.close():
        raise OSError(f"cannot write {path}: {out.geterror()}")


def read_exr_levels(path: Path) -> tuple[list[np.ndarray], tuple[str, ...], dict]:
    """Every mip level (as float32), the channel names and the worldbake attributes."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    levels, names, attrs = [], (), {}
    level = 0
    while inp.seek_subimage(0, level):
        spec = inp.spec()
        if level == 0:
            names = tuple(spec.channelnames)
            attrs = {a.name: a.value for a in spec.extra_attribs if a.name.startswith("worldbake:")}
        levels.append(np.asarray(inp.read_image(0, level, 0, spec.nchannels, oiio.FLOAT), np.float32)
                      .reshape(spec.height, spec.width, -1))
        level += 1
    inp.close()
    return levels, names, attrs
