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
    rgb = np.asarray(rgb, np.float32)
    with MipmappedWriter(path, rgb.shape[0], rgb.shape[1], rgb.shape[2], provenance, compression) as out:
        out.write_rows(rgb)


MIP_TILE = 64  # texels per side of a texture file's tiles


class MipmappedWriter:
    """write_mipmapped_texture's file written band by band of whole rows
    (north to south, each a whole number of MIP_TILE rows but the last), so a
    texture larger than memory allows is never whole: level 0 goes to the
    file as it comes, level 1 (a quarter of the texels) is kept and the
    levels below it made from it at the end. The bytes are those of
    write_mipmapped_texture of the whole image."""

    def __init__(self, path: Path | str, rows: int, cols: int, channels: int,
                 provenance: dict[str, Any] | None = None, compression: str = "zips"):
        oiio = _oiio()
        self.path, self.rows, self.cols, self.channels = Path(path), int(rows), int(cols), int(channels)
        self.compression, self.next_row = compression, 0
        self.out = oiio.ImageOutput.create(str(path))
        if self.out is None:
            raise OSError(f"cannot write texture {path}: {oiio.geterror()}")
        spec = self._spec(self.rows, self.cols)
        spec.attribute("openexr:levelmode", 1)  # MIPMAP_LEVELS
        spec.attribute("textureformat", "Plain Texture")
        spec.attribute("wrapmodes", "clamp,clamp")
        spec.attribute("DateTime", "")
        for k, v in (provenance or {}).items():
            spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
        self._check(self.out.open(str(path), spec, "Create"))
        below = (max(self.rows // 2, 1), max(self.cols // 2, 1), self.channels)
        self.level1 = np.empty(below, np.float32) if self.rows > 1 or self.cols > 1 else None

    def _spec(self, rows: int, cols: int):
        oiio = _oiio()
        spec = oiio.ImageSpec(cols, rows, self.channels, oiio.HALF)
        spec.tile_width = spec.tile_height = MIP_TILE
        spec.attribute("compression", self.compression)
        return spec

    def _check(self, ok: bool) -> None:
        if not ok:
            err = self.out.geterror()
            self._release()
            raise OSError(f"cannot write texture {self.path}: {err}")

    def write_rows(self, band: np.ndarray) -> None:
        """The next rows of level 0 (rows x cols x channels)."""
        band = np.asarray(band, np.float32)
        r0, n = self.next_row, band.shape[0]
        if band.shape[1:] != (self.cols, self.channels) or r0 + n > self.rows:
            raise ValueError(f"{self.path}: a band of {band.shape} at row {r0} does not fit the texture's "
                             f"{self.rows} x {self.cols} x {self.channels}")
        if r0 + n < self.rows and n % MIP_TILE:
            raise ValueError(f"{self.path}: a band of {n} rows; all but the last must be whole {MIP_TILE}-row tiles")
        self._check(self.out.write_tiles(0, self.cols, r0, r0 + n, 0, 1, np.ascontiguousarray(band, np.float16)))
        self.next_row = r0 + n
        if self.level1 is not None:  # box_mip_chain's first step on these rows (even, so a band halves alone)
            a = band[:n - 1] if (r0 + n == self.rows and n % 2 and self.rows > 1) else band
            if self.cols % 2 and self.cols > 1:
                a = a[:, :-1]
            r = a if self.rows == 1 else 0.5 * (a[0::2] + a[1::2])
            self.level1[r0 // 2:r0 // 2 + r.shape[0]] = r if r.shape[1] == 1 else 0.5 * (r[:, 0::2] + r[:, 1::2])

    def close(self) -> None:
        if self.next_row != self.rows:
            self._release()
            raise OSError(f"{self.path}: {self.next_row} of {self.rows} rows written")
        if self.level1 is not None:
            for level in box_mip_chain(self.level1):
                rows, cols = level.shape[:2]
                self._check(self.out.open(str(self.path), self._spec(rows, cols), "AppendMIPLevel")
                            and self.out.write_image(np.ascontiguousarray(level, np.float16)))
        self._release()

    def _release(self) -> None:
        # OpenEXR writes a tiled file's offset table when its writer is destroyed, not at close():
        # the file is whole only once nothing holds the ImageOutput
        self.out.close()
        self.out = None

    def __enter__(self) -> "MipmappedWriter":
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        elif self.out is not None:
            self._release()
