"""Texture files for materials: half-float EXR, tiled and mip-mapped.

The textures a stage writes for its USD materials (ground, bark, foliage
cards); the engine's own grids and preview pictures are pipeline.exr's.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def _oiio():
    import OpenImageIO as oiio

    return oiio



def write_png(path: Path | str, rgb_linear: np.ndarray, alpha: np.ndarray | None = None, srgb: bool = True) -> None:
    """An 8-bit PNG texture (what a DCC's UsdUVTexture reads): colour through
    the sRGB curve (srgb) or stored as it is (data: normal maps, 0..1);
    alpha linear and straight, as PNG defines it (OpenImageIO takes pixels
    as premultiplied and would divide the colour by alpha on writing, which
    every other reader then sees too bright); no timestamp, so a rebake
    writes the same bytes."""
    from pipeline.exr import srgb8

    oiio = _oiio()
    a = np.asarray(rgb_linear, np.float32)
    data = srgb8(a) if srgb else np.round(np.clip(a, 0, 1) * 255).astype(np.uint8)
    if alpha is not None:
        data = np.concatenate([data, np.round(np.clip(alpha, 0, 1) * 255).astype(np.uint8)[..., None]], -1)
    buf = oiio.ImageBuf(np.ascontiguousarray(data))
    buf.specmod().attribute("DateTime", "")
    buf.specmod().attribute("oiio:UnassociatedAlpha", 1)
    if not buf.write(str(path), oiio.UINT8):
        raise OSError(f"cannot write {path}: {buf.geterror()}")


def write_texture(path: Path | str, rgb: np.ndarray, provenance: dict[str, Any] | None = None) -> None:
    """A colour texture for a material: half-float RGB EXR, tiled and
    mip-mapped (ImageBufAlgo.make_texture), zip compressed."""
    oiio = _oiio()
    src = oiio.ImageBuf(np.ascontiguousarray(rgb, dtype=np.float32))
    config = oiio.ImageSpec()
    config.attribute("compression", "zip")
    config.attribute("maketx:filtername", "lanczos3")
    config.attribute("DateTime", "")
    for k, v in (provenance or {}).items():
        config.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
    config.set_format(oiio.HALF)
    if not oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, src, str(path), config):
        raise OSError(f"cannot write texture {path}: {oiio.geterror()}")


def box_mip_chain(rgb: np.ndarray) -> list[np.ndarray]:
    """MIP levels of an image down to 1x1, each the 2x2 mean of the one
    above, in OpenEXR's round-down sizes (the odd last row or column of a
    level is left out of the next)."""
    levels = [np.asarray(rgb, np.float32)]
    a = levels[0]
    while a.shape[0] > 1 or a.shape[1] > 1:
        if a.shape[0] % 2 and a.shape[0] > 1:
            a = a[:-1]
        if a.shape[1] % 2 and a.shape[1] > 1:
            a = a[:, :-1]
        r = a if a.shape[0] == 1 else 0.5 * (a[0::2] + a[1::2])
        a = r if r.shape[1] == 1 else 0.5 * (r[:, 0::2] + r[:, 1::2])
        levels.append(a)
    return levels


def write_mipmapped_texture(path: Path | str, rgb: np.ndarray, provenance: dict[str, Any] | None = None,
                            compression: str = "zips") -> None:
    """A colour texture like write_texture (half-float RGB EXR, 64^2 tiles,
    MIP-mapped, clamped) with box-filtered MIP levels computed here, for
    large textures: make_texture's lanczos3 resampling costs about ten times
    the write."""
    oiio = _oiio()
    levels = box_mip_chain(rgb)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot write texture {path}: {oiio.geterror()}")
    for i, level in enumerate(levels):
        rows, cols = level.shape[:2]
        spec = oiio.ImageSpec(cols, rows, level.shape[2], oiio.HALF)
        spec.tile_width = spec.tile_height = 64
        spec.attribute("compression", compression)
        if i == 0:
            spec.attribute("openexr:levelmode", 1)  # MIPMAP_LEVELS
            spec.attribute("textureformat", "Plain Texture")
            spec.attribute("wrapmodes", "clamp,clamp")
            spec.attribute("DateTime", "")
            for k, v in (provenance or {}).items():
                spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
        ok = out.open(str(path), spec, "Create" if i == 0 else "AppendMIPLevel")
        ok = ok and out.write_image(np.ascontiguousarray(level, np.float16))
        if not ok:
            err = out.geterror()
            out.close()
            raise OSError(f"cannot write texture {path}: {err}")
    out.close()
