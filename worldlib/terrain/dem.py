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

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError

_ROW_CHUNK = 256  # output rows per resampling step (bounds temporary memory)
# The most pixels an input raster may declare: 16384^2 (2 GiB as float64).
# Checked from the header, before a byte of pixels is read: a small
# compressed file can declare a huge image.
MAX_PIXELS = 16384 * 16384
# The largest |height| a DEM may hold, in metres (the range of heightmap.base_m,
# dem_min_m and dem_max_m): beyond it a value is not terrain but another unit
# or a no-data marker (GeoTIFFs often use -3.4e38).
MAX_HEIGHT_M = 1.0e5
# An input raster is checked at plan time by reading it in bands of rows of at
# most this many pixels (tiled files: whole rows of tiles): every pixel is
# seen, the memory held is bounded (a band and its float64 copy, about 48 MiB)
# whatever the file's size, up to MAX_PIXELS.
SCAN_BAND_PIXELS = 1 << 22


@dataclass(frozen=True)
class RasterScan:
    """What a plan-time scan of an input raster's first channel found, in the
    file's own values (integers as they are stored)."""

    width: int
    height: int
    dtype: np.dtype
    lo: float  # smallest finite value (nan when there is none)
    hi: float  # largest finite value
    lo_at: tuple[int, int]  # (row, column) of lo
    hi_at: tuple[int, int]
    nonfinite: int  # NaN and infinite values
    first_nonfinite: tuple[int, int] | None

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    @property
    def size(self) -> int:
        return self.width * self.height


_SCANS: dict[tuple, RasterScan] = {}  # (path, size, mtime) -> scan: every variant of a config opens the same files


def _open_raster(path: Path, label: str):
    """The open ImageInput and its spec, its size checked from the header."""
    import OpenImageIO as oiio

    if not path.is_file():
        raise InputError(f"{label} {path} does not exist or is not a file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{label} {path} cannot be read as an image: {oiio.geterror() or 'unknown format'}")
    spec = inp.spec()
    try:
        if spec.width < 1 or spec.height < 1 or spec.nchannels < 1:
            raise InputError(f"{label} {path} is empty ({spec.width}x{spec.height}, {spec.nchannels} channels)")
        if spec.width * spec.height > MAX_PIXELS:
            raise InputError(f"{label} {path} declares {spec.width}x{spec.height} pixels, more than the "
                             f"{MAX_PIXELS:,} an input raster may have (16384^2); downsample it first")
    except InputError:
        inp.close()
        raise
    return inp, spec


def scan_raster(path: str | Path, label: str = "DEM file") -> RasterScan:
    """Check an input raster before any stage runs without holding it: its
    header (size, at most MAX_PIXELS), then its first channel in bands of
    rows (SCAN_BAND_PIXELS), for the range of its values and its NaN and
    infinities. A file that cannot be decoded to its last row is corrupt."""
    import OpenImageIO as oiio

    path = Path(path)
    stat = path.stat() if path.is_file() else None
    memo = (str(path.resolve()), stat.st_size, stat.st_mtime_ns) if stat else None
    if memo in _SCANS:
        return _SCANS[memo]
    inp, spec = _open_raster(path, label)
    try:
        w, h = spec.width, spec.height
        step = max(1, SCAN_BAND_PIXELS // w)
        if spec.tile_width:  # whole rows of tiles
            step = max(spec.tile_height, step - step % max(spec.tile_height, 1))
        lo, hi, lo_at, hi_at, bad, first_bad, dtype = math.inf, -math.inf, (0, 0), (0, 0), 0, None, None
        for r0 in range(0, h, step):
            r1 = min(h, r0 + step)
            if spec.tile_width:
                band = inp.read_tiles(0, 0, spec.x, spec.x + w, spec.y + r0, spec.y + r1, spec.z, spec.z + 1, 0, 1,
                                      spec.format)
            else:
                band = inp.read_scanlines(0, 0, spec.y + r0, spec.y + r1, spec.z, 0, 1, spec.format)
            if band is None or inp.has_error:
                raise InputError(f"{label} {path} is corrupt: {inp.geterror() or oiio.geterror() or 'read failed'} "
                                 f"(rows {r0} .. {r1 - 1})")
            band = np.asarray(band).reshape(r1 - r0, w)
            dtype = band.dtype
            if not np.issubdtype(band.dtype, np.integer):
                finite = np.isfinite(band)
                if not finite.all():
                    if first_bad is None:
                        r, c = np.argwhere(~finite)[0]
                        first_bad = (r0 + int(r), int(c))
                    bad += int(band.size - finite.sum())
                    if not finite.any():
                        continue
                    band = np.where(finite, band, band[finite][0])
            i_lo, i_hi = int(np.argmin(band)), int(np.argmax(band))
            if float(band.flat[i_lo]) < lo:
                lo, lo_at = float(band.flat[i_lo]), (r0 + i_lo // w, i_lo % w)
            if float(band.flat[i_hi]) > hi:
                hi, hi_at = float(band.flat[i_hi]), (r0 + i_hi // w, i_hi % w)
    finally:
        inp.close()
    if lo > hi:  # no finite value at all
        lo = hi = math.nan
    scan = RasterScan(w, h, np.dtype(dtype), lo, hi, lo_at, hi_at, bad, first_bad)
    if memo is not None:
        _SCANS[memo] = scan
    return scan


def nonfinite_error(label: str, path, count: int, at: tuple[int, int]) -> InputError:
    return InputError(f"{label} {path} contains {count} NaN or infinite value(s), the first at row {at[0]}, "
                      f"column {at[1]}")


def integer_hint(label: str, dtype) -> str:
    return (("set dem_min_m and dem_max_m (the heights in metres of the smallest and largest "
             f"{dtype} values)") if label == "DEM file" else "save it with float values")


def height_range_error(label: str, path, value: float, at: tuple[int, int]) -> InputError:
    """A height beyond +-MAX_HEIGHT_M: another unit, or a no-data marker."""
    return InputError(f"{label} {path} holds a height of {value:.4g} m (row {at[0]}, column {at[1]}), beyond the "
                      f"+-{MAX_HEIGHT_M:,.0f} m a terrain may have: wrong units, or a no-data value (fill it first)")


def check_dem(path: str | Path, dem_min_m: float | None = None, dem_max_m: float | None = None,
              label: str = "DEM file") -> RasterScan:
    """Everything read_dem would refuse, found by scan_raster (bounded memory):
    size, corrupt data, integers without a range, NaN or infinity, heights
    beyond +-MAX_HEIGHT_M (after dem_min_m / dem_max_m scaling)."""
    scan = scan_raster(path, label)
    scaled = dem_min_m is not None and dem_max_m is not None
    if np.issubdtype(scan.dtype, np.integer):
        if not scaled:
            raise InputError(f"{label} {path} holds {scan.dtype} integers: {integer_hint(label, scan.dtype)}")
        return scan  # the type's range maps onto [dem_min_m, dem_max_m], inside the params' range
    if scan.nonfinite:
        raise nonfinite_error(label, path, scan.nonfinite, scan.first_nonfinite)
    for value, at in ((scan.lo, scan.lo_at), (scan.hi, scan.hi_at)):
        metres = dem_min_m + value * (dem_max_m - dem_min_m) if scaled else value
        if not abs(metres) <= MAX_HEIGHT_M:
            raise height_range_error(label, path, metres, at)
    return scan


def check_rain_map(path: str | Path, max_mm_per_year: float, label: str = "rain map") -> RasterScan:
    """A rain map (mm/year, float) checked by scan_raster: float values,
    finite, not negative, at most max_mm_per_year."""
    scan = scan_raster(path, label)
    if np.issubdtype(scan.dtype, np.integer):
        raise InputError(f"{label} {path} holds {scan.dtype} integers: {integer_hint(label, scan.dtype)}")
    if scan.nonfinite:
        raise nonfinite_error(label, path, scan.nonfinite, scan.first_nonfinite)
    if scan.lo < 0:
        raise InputError(f"{label} {path} has negative rain ({scan.lo:g} mm/year at row {scan.lo_at[0]}, "
                         f"column {scan.lo_at[1]})")
    if scan.hi > max_mm_per_year:
        raise InputError(f"{label} {path} has {scan.hi:.4g} mm/year of rain (row {scan.hi_at[0]}, column "
                         f"{scan.hi_at[1]}), more than {max_mm_per_year:g} mm/year (wrong units?)")
    return scan


def read_dem(path: str | Path, dem_min_m: float | None = None, dem_max_m: float | None = None,
             label: str = "DEM file", max_abs_m: float | None = None) -> np.ndarray:
    """The DEM's first channel in metres, float64 (height, width). `label`
    names the file in errors (other rasters read with it: "rain map");
    values beyond +-max_abs_m (heights: MAX_HEIGHT_M) are refused."""
    import OpenImageIO as oiio

    path = Path(path)
    inp, spec = _open_raster(path, label)
    try:
        raw = inp.read_image(0, 0, 0, 1, spec.format)  # first channel, in the file's own pixel type
        if raw is None or inp.has_error:
            raise InputError(f"{label} {path} is corrupt: {inp.geterror() or oiio.geterror() or 'read failed'}")
    finally:
        inp.close()
    raw = np.asarray(raw).reshape(spec.height, spec.width)
    scaled = dem_min_m is not None and dem_max_m is not None
    if np.issubdtype(raw.dtype, np.integer):
        if not scaled:
            raise InputError(f"{label} {path} holds {raw.dtype} integers: {integer_hint(label, raw.dtype)}")
        info = np.iinfo(raw.dtype)
        t = (raw.astype(np.float64) - float(info.min)) / (float(info.max) - float(info.min))
        return dem_min_m + t * (dem_max_m - dem_min_m)
    values = raw.astype(np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise nonfinite_error(label, path, int(bad.sum()), (int(r), int(c)))
    if scaled:
        values = dem_min_m + values * (dem_max_m - dem_min_m)
    if max_abs_m is not None:
        beyond = np.abs(values) > max_abs_m
        if beyond.any():
            r, c = np.argwhere(beyond)[0]
            raise height_range_error(label, path, float(values[r, c]), (int(r), int(c)))
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


# The cell sizes a DEM file may state, in metres: the range of heightmap.dem_cell_size_m, and at least 1 cm
# (a geographic DEM states its pixels in degrees: 1 arc-second is 0.000278).
MIN_CELL_M, MAX_CELL_M = 0.01, 1.0e5


def _stated_cell(label: str, path, what: str, cell: float) -> float:
    if not MIN_CELL_M <= cell <= MAX_CELL_M:
        raise InputError(f"{label} {path}: its {what} states cells of {cell:g} m, outside {MIN_CELL_M:g} .. "
                         f"{MAX_CELL_M:g} m (degrees of a geographic DEM? reproject it to metres); or set "
                         f"heightmap.dem_cell_size_m")
    return cell


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
        return _stated_cell(label, path, "GeoTIFF pixel scale", sx)
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
                return _stated_cell(label, path, f"attribute {name}", cell)
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
    src = read_dem(path, dem_min_m, dem_max_m, max_abs_m=MAX_HEIGHT_M)
    check_shape(path, src.shape[1], src.shape[0], own_cells=False, max_aspect_error=max_aspect_error)
    return resample(src, resolution, window)


MIN_SIDE = 3  # pixels on each side of a DEM: a terrain's slopes and flow need a cell's 8 neighbours


def check_shape(path, width: int, height: int, own_cells: bool, max_aspect_error: float = 0.01) -> None:
    """A DEM's size: at least MIN_SIDE pixels a side; square (within
    max_aspect_error) when it is stretched over the square world."""
    if min(width, height) < MIN_SIDE:
        raise InputError(f"DEM file {path} is {width}x{height} pixels: a DEM needs at least {MIN_SIDE} pixels on "
                         f"each side")
    if not own_cells and abs(width / height - 1.0) > max_aspect_error:
        raise InputError(
            f"DEM file {path} is {width}x{height} pixels but the world is square: crop or pad it to a square, or give "
            f"its cell size (heightmap.dem_cell_size_m, or in the file: GeoTIFF pixel scale, EXR attribute "
            f"worldbake:cell_size_m) to bake it at its own cells"
        )
