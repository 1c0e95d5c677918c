"""The tile files: names and writers (OpenImageIO).

Unreal's tiled import (LandscapeImportHelper::ExtractCoordinates) takes the
text after the last "_x" and the last "_y" of a file's base name as the
tile's column and row, and collects every file of the chosen folder, its
subfolders included, whose name before "_x" matches, whatever its extension.
So the name ends in _x<col>_y<row>, a weightmap puts its ground type before
that suffix, and the files Unreal imports (PNG) sit in a folder of their own,
apart from the float EXRs and JSON sidecars of the same names.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline import exr
from pipeline.grid import Grid

UNREAL_DIR = "unreal"  # what Unreal imports: 16-bit heightmaps and 8-bit weightmaps
DATA_DIR = "data"  # float heights and the JSON sidecars


def tile_name(prefix: str, col: int, row: int, ground: str | None = None) -> str:
    """<prefix>_x<col>_y<row> for a heightmap, <prefix>_<ground>_x<col>_y<row> for a weightmap."""
    return f"{prefix}_{ground}_x{col}_y{row}" if ground else f"{prefix}_x{col}_y{row}"


def _write_png(path: Path, pixels: np.ndarray, pixel_type, text: dict[str, str]) -> None:
    """One-channel PNG; `text` goes into tEXt chunks. Colour space "raw": no
    sRGB, gAMA or cHRM chunk, the values are data."""
    import OpenImageIO as oiio

    rows, cols = pixels.shape
    spec = oiio.ImageSpec(cols, rows, 1, pixel_type)
    spec.attribute("oiio:ColorSpace", "raw")
    spec.attribute("DateTime", "")  # no time stamp: a re-bake writes the same bytes
    for k, v in text.items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(np.ascontiguousarray(pixels).reshape(rows, cols, 1))
    ok = out.close() and ok
    if not ok:
        raise OSError(f"cannot write {path}: {out.geterror()}")


def write_height_png(path: Path, values: np.ndarray, text: dict[str, str]) -> None:
    import OpenImageIO as oiio

    _write_png(path, values.astype(np.uint16, copy=False), oiio.UINT16, text)


def write_weight_png(path: Path, values: np.ndarray, text: dict[str, str]) -> None:
    import OpenImageIO as oiio

    _write_png(path, values.astype(np.uint8, copy=False), oiio.UINT8, text)


def write_height_exr(path: Path, heights: np.ndarray, cell_m: float, first_vertex_m: tuple[float, float],
                     provenance: dict) -> None:
    """Float32 metres, channel "height"; as a worldbake grid whose cell
    centres are the vertices (origin half a cell before the first)."""
    origin = (first_vertex_m[0] - 0.5 * cell_m, first_vertex_m[1] - 0.5 * cell_m)
    exr.write_grid(path, Grid(heights.astype(np.float32), cell_m, ("height",), origin), provenance)


def read_png(path: Path) -> tuple[np.ndarray, dict[str, str]]:
    """A one-channel PNG's values (in its own integer type) and its text attributes."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, 1, spec.format)
        attrs = {a.name: a.value for a in spec.extra_attribs}
    finally:
        inp.close()
    return np.asarray(pixels).reshape(spec.height, spec.width), attrs


def write_sidecar(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
