"""EXR and preview image I/O through OpenImageIO.

Grids are written as float32 scanline EXR with zip compression (lossless) and
named channels ("height", "flow.accumulation"); the grid geometry and the
provenance travel in header attributes prefixed "worldbake:".
"""
from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .grid import Grid


def _oiio():
    import OpenImageIO as oiio

    return oiio


def write_grid(path: Path | str, grid: Grid, provenance: dict[str, Any] | None = None) -> None:
    oiio = _oiio()
    data = np.ascontiguousarray(grid.data, dtype=np.float32)
    rows, cols = grid.shape
    nchan = len(grid.channels)
    spec = oiio.ImageSpec(cols, rows, nchan, oiio.FLOAT)
    spec.channelnames = tuple(grid.channels)
    spec.attribute("compression", "zip")
    spec.attribute("worldbake:cell_size_m", float(grid.cell_size_m))
    spec.attribute("worldbake:origin_m", json.dumps(list(grid.origin_m)))
    # OpenImageIO stamps the current time otherwise; a fixed value keeps
    # repeated bakes byte-identical as well as pixel-identical.
    spec.attribute("DateTime", "")
    for k, v in (provenance or {}).items():
        spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(data.reshape(rows, cols, nchan))
    ok = out.close() and ok
    if not ok:
        raise OSError(f"cannot write {path}: {out.geterror()}")


@contextlib.contextmanager
def _image_input(path: Path | str):
    """An open OpenImageIO ImageInput; a file it cannot open is an InputError naming it."""
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read: {oiio.geterror()}")
    try:
        yield inp
    finally:
        inp.close()


def read_grid(path: Path | str) -> Grid:
    """A grid written by write_grid. A file that is missing, corrupt or not a
    worldbake grid raises InputError naming it."""
    oiio = _oiio()
    with _image_input(path) as inp:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if pixels is None:
            raise InputError(f"{path}: cannot decode pixels: {inp.geterror()}")
        cell = spec.getattribute("worldbake:cell_size_m")
        if cell is None:
            raise InputError(f"{path}: no worldbake:cell_size_m attribute; not a worldbake grid")
        origin = tuple(json.loads(spec.getattribute("worldbake:origin_m") or "[0, 0]"))
        names = tuple(spec.channelnames)
    data = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if spec.nchannels == 1:
        data = data[:, :, 0]
    return Grid(np.ascontiguousarray(data), float(cell), names, origin)


def channel_names(path: Path | str) -> list[str]:
    """The channel names of an image in the order the file stores them
    (OpenEXR sorts them by name: lake.depth, lake.id, lake.level whatever
    order they were written in); read a channel by its name, not its place."""
    with _image_input(path) as inp:
        return list(inp.spec().channelnames)


def read_attributes(path: Path | str) -> dict[str, Any]:
    """The header attributes of an image, as a dict."""
    with _image_input(path) as inp:
        return {a.name: a.value for a in inp.spec().extra_attribs}


def write_png(path: Path | str, rgb: np.ndarray) -> None:
    """A uint8 RGB(A) preview picture."""
    oiio = _oiio()
    rgb = np.ascontiguousarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] not in (3, 4):
        raise ValueError(f"a preview must be uint8 (rows, cols, 3|4), got {rgb.dtype} {rgb.shape}")
    buf = oiio.ImageBuf(rgb)
    if not buf.write(str(path), oiio.UINT8):
        raise OSError(f"cannot write {path}: {buf.geterror()}")


def linear_from_srgb(srgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] colour to linear (the standard piecewise curve), in the input's precision."""
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def srgb8(linear_rgb: np.ndarray) -> np.ndarray:
    """Linear [0, 1] colour to 8-bit sRGB (the standard piecewise curve)."""
    x = np.clip(np.asarray(linear_rgb, np.float64), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)
