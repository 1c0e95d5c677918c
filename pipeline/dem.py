"""Import an existing DEM (EXR, TIFF, 16-bit PNG, anything OpenImageIO reads).

The first channel is taken. Values become metres:
- float files (half/float EXR or TIFF) are metres as they are, unless both
  dem_min_m and dem_max_m are given: then the values are taken as normalised
  (0..1) and mapped linearly onto [dem_min_m, dem_max_m];
- integer files (8/16/32-bit, signed or not) need dem_min_m and dem_max_m:
  the full range of the type (0..65535 for 16-bit PNG) maps linearly onto them.

The DEM covers the whole square world; it is resampled to the world grid by
bilinear interpolation between pixel centres (pixel-is-area on both sides,
clamped at the borders), so a linear ramp stays the same ramp. Each cell is
computed independently from the same formula, so a window is bit-identical
to the same crop of the whole map. Downsampling by more than 2x aliases
(no prefilter).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import InputError

_ROW_CHUNK = 256  # output rows per resampling step (bounds temporary memory)
# The most pixels an input raster may declare: 16384^2 (2 GiB as float64).
# Checked from the header, before a byte of pixels is read: a small
# compressed file can declare a huge image.
MAX_PIXELS = 16384 * 16384


def read_dem(path: str | Path, dem_min_m: float | None = None, dem_max_m: float | None = None,
             label: str = "DEM file") -> np.ndarray:
    """The DEM's first channel in metres, float64 (height, width). `label`
    names the file in errors (other rasters read with it: "rain map")."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{label} {path} does not exist or is not a file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{label} {path} cannot be read as an image: {oiio.geterror() or 'unknown format'}")
    try:
        spec = inp.spec()
        if spec.width < 1 or spec.height < 1 or spec.nchannels < 1:
            raise InputError(f"{label} {path} is empty ({spec.width}x{spec.height}, {spec.nchannels} channels)")
        if spec.width * spec.height > MAX_PIXELS:
            raise InputError(f"{label} {path} declares {spec.width}x{spec.height} pixels, more than the "
                             f"{MAX_PIXELS:,} an input raster may have (16384^2); downsample it first")
        raw = inp.read_image(0, 0, 0, 1, spec.format)  # first channel, in the file's own pixel type
        if raw is None or inp.has_error:
            raise InputError(f"{label} {path} is corrupt: {inp.geterror() or oiio.geterror() or 'read failed'}")
    finally:
        inp.close()
    raw = np.asarray(raw).reshape(spec.height, spec.width)
    scaled = dem_min_m is not None and dem_max_m is not None
    if np.issubdtype(raw.dtype, np.integer):
        if not scaled:
            hint = ("set dem_min_m and dem_max_m (the heights in metres of the smallest and largest "
                    f"{raw.dtype} values)") if label == "DEM file" else "save it with float values"
            raise InputError(f"{label} {path} holds {raw.dtype} integers: {hint}")
        info = np.iinfo(raw.dtype)
        t = (raw.astype(np.float64) - float(info.min)) / (float(info.max) - float(info.min))
        return dem_min_m + t * (dem_max_m - dem_min_m)
    values = raw.astype(np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(
            f"{label} {path} contains {int(bad.sum())} NaN or infinite value(s), the first at row {r}, column {c}"
        )
    if scaled:
        values = dem_min_m + values * (dem_max_m - dem_min_m)
    return values


def _taps(n_out: int, n_src: int, first: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices and weight for output cells [first, first+count) of n_out
    cells spanning the same extent as n_src source pixels (centre to centre)."""
    idx = np.arange(first, first + count, dtype=np.float64)
    s = (idx + 0.5) * (n_src / n_out) - 0.5
    s = np.clip(s, 0.0, n_src - 1)
    i0 = np.floor(s).astype(np.int64)
    i1 = np.minimum(i0 + 1, n_src - 1)
    return i0, i1, s - i0


def resample(src: np.ndarray, resolution: int | tuple[int, int], window: tuple[int, int, int, int]) -> np.ndarray:
    """Bilinear, cell-centred resampling of src (h, w) onto the cells
    window = (col0, row0, cols, rows) of a resolution x resolution grid (or
    of a (grid rows, grid cols) grid)."""
    col0, row0, cols, rows = window
    res_r, res_c = (resolution, resolution) if isinstance(resolution, int) else resolution
    h, w = src.shape
    x0, x1, wx = _taps(res_c, w, col0, cols)
    out = np.empty((rows, cols), np.float32)
    for r in range(0, rows, _ROW_CHUNK):
        n = min(_ROW_CHUNK, rows - r)
        z0, z1, wz = _taps(res_r, h, row0 + r, n)
        wz = wz[:, None]
        top = src[z0][:, x0] * (1.0 - wx) + src[z0][:, x1] * wx
        bottom = src[z1][:, x0] * (1.0 - wx) + src[z1][:, x1] * wx
        out[r:r + n] = top * (1.0 - wz) + bottom * wz
    return out


def load_dem(
    path: str | Path, resolution: int, window: tuple[int, int, int, int],
    dem_min_m: float | None = None, dem_max_m: float | None = None, max_aspect_error: float = 0.01,
) -> np.ndarray:
    """Read, check and resample a DEM onto a window of the square world grid."""
    src = read_dem(path, dem_min_m, dem_max_m)
    h, w = src.shape
    if abs(w / h - 1.0) > max_aspect_error:
        raise InputError(
            f"DEM file {path} is {w}x{h} pixels but the world is square: crop or pad it to a square first"
        )
    return resample(src, resolution, window)
