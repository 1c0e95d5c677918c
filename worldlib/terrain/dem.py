"""Import an existing DEM (EXR, TIFF, 16-bit PNG, anything OpenImageIO reads).

The first channel is taken. Values become metres:
- float files (half/float EXR or TIFF) are metres as they are, unless both
  dem_min_m and dem_max_m are given: then the values are taken as normalised
  (0..1) and mapped linearly onto [dem_min_m, dem_max_m];
- integer files (8/16/32-bit, signed or not) need dem_min_m and dem_max_m:
  the full range of the type (0..65535 for 16-bit PNG) maps linearly onto them.

A DEM whose file states its cell size (GeoTIFF pixel scale, EXR attribute
worldbake:cell_size_m), or given one by the config, is used at its own cells:
the world is its rows x cols (rectangular when the DEM is). Otherwise the
DEM covers the whole square world; it is resampled to the world grid by
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


# GeoTIFF ModelPixelScaleTag: (x, y, z) size of a pixel in the model's units (metres for projected DEMs)
GEOTIFF_PIXEL_SCALE = 33550
CELL_SIZE_ATTRIBUTES = ("worldbake:cell_size_m", "cell_size_m")  # EXR header attributes read as the cell size


def _tiff_pixel_scale(path: Path) -> tuple[float, float] | None:
    """The GeoTIFF pixel scale (x, y) of a TIFF's first image, from its tag
    directory (OpenImageIO does not report GeoTIFF tags); None without one."""
    import struct

    with open(path, "rb") as f:
        head = f.read(16)
        if len(head) < 8 or head[:2] not in (b"II", b"MM"):
            return None
        e = "<" if head[:2] == b"II" else ">"
        magic = struct.unpack(e + "H", head[2:4])[0]
        big = magic == 43
        if magic not in (42, 43):
            return None
        offset = struct.unpack(e + "Q", head[8:16])[0] if big else struct.unpack(e + "I", head[4:8])[0]
        f.seek(offset)
        count_fmt, entry_size = (e + "Q", 20) if big else (e + "H", 12)
        raw = f.read(8 if big else 2)
        if len(raw) < (8 if big else 2):
            return None
        n = struct.unpack(count_fmt, raw)[0]
        entries = f.read(min(n, 4096) * entry_size)
        for i in range(len(entries) // entry_size):
            entry = entries[i * entry_size:(i + 1) * entry_size]
            tag, kind = struct.unpack(e + "HH", entry[:4])
            if tag != GEOTIFF_PIXEL_SCALE or kind != 12:  # 12: DOUBLE
                continue
            count = struct.unpack(e + "Q", entry[4:12])[0] if big else struct.unpack(e + "I", entry[4:8])[0]
            if count < 2:
                return None
            where = struct.unpack(e + "Q", entry[12:20])[0] if big else struct.unpack(e + "I", entry[8:12])[0]
            f.seek(where)
            data = f.read(16)
            return struct.unpack(e + "dd", data) if len(data) == 16 else None
    return None


def dem_cell_size(path: str | Path, label: str = "DEM file") -> float | None:
    """The cell size in metres a DEM file states: the GeoTIFF pixel scale of
    a TIFF, or an EXR header attribute worldbake:cell_size_m (or cell_size_m);
    None when it states none. Cells that are not square are refused."""
    import OpenImageIO as oiio

    path = Path(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        scale = _tiff_pixel_scale(path)
        if scale is None:
            return None
        sx, sy = (abs(float(v)) for v in scale)
        if not (np.isfinite(sx) and sx > 0 and np.isfinite(sy) and sy > 0):
            raise InputError(f"{label} {path}: GeoTIFF pixel scale {scale} is not a positive size")
        if abs(sx - sy) > 1e-6 * max(sx, sy):
            raise InputError(f"{label} {path}: its pixels are {sx:g} x {sy:g} (GeoTIFF pixel scale), not square; "
                             f"resample it to square cells first")
        return sx
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return None
    try:
        spec = inp.spec()
        for name in CELL_SIZE_ATTRIBUTES:
            value = spec.getattribute(name)
            if value is not None:
                try:
                    cell = float(value)
                except (TypeError, ValueError):
                    raise InputError(f"{label} {path}: attribute {name} = {value!r} is not a number") from None
                if not (np.isfinite(cell) and cell > 0):
                    raise InputError(f"{label} {path}: attribute {name} = {cell!r} is not a positive size")
                return cell
    finally:
        inp.close()
    return None


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
            f"DEM file {path} is {w}x{h} pixels but the world is square: crop or pad it to a square, or give "
            f"its cell size (heightmap.dem_cell_size_m, or in the file: GeoTIFF pixel scale, EXR attribute "
            f"worldbake:cell_size_m) to bake it at its own cells"
        )
    return resample(src, resolution, window)
