"""EXR and preview image I/O through OpenImageIO.

Grids are written as float32 tiled EXR (TILE x TILE file tiles, zip
compression per tile, lossless) with named channels ("height",
"flow.accumulation"); the grid geometry and the provenance travel in header
attributes prefixed "worldbake:". A grid is written window by window
(GridWriter) in any order, or whole (write_grid, the same bytes), and read
whole (read_grid) or by window (read_window, only the file tiles it needs).
Grids from before tiling (scanline EXR) read as they did.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import tempfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .errors import InputError
from .grid import Grid


def _oiio():
    import OpenImageIO as oiio

    return oiio


# The file tile size of a grid EXR. Fixed: a file's bytes depend on it, and
# world tiles (multiples of it) map onto whole file tiles.
TILE = 256


class GridInfo(NamedTuple):
    """A grid file's header: its geometry without its pixels."""

    shape: tuple[int, int]
    channels: tuple[str, ...]  # in the file's order, not always the writer's: read channels by name
    cell_size_m: float
    origin_m: tuple[float, float]
    tile: int  # file tile size; 0 for a scanline file (written before grids were tiled)


def _grid_spec(shape: tuple[int, int], channels: tuple[str, ...], cell_size_m: float,
               origin_m: tuple[float, float], provenance: dict[str, Any] | None, tile: int):
    oiio = _oiio()
    rows, cols = shape
    spec = oiio.ImageSpec(cols, rows, len(channels), oiio.FLOAT)
    spec.channelnames = tuple(channels)
    spec.tile_width = spec.tile_height = tile
    spec.attribute("compression", "zip")
    # Tiles in row-major order in the file whatever order they are written in
    # (OpenEXR's INCREASING_Y for tiled files); GridWriter hands them over in
    # that order, so OpenEXR never holds tiles back in memory.
    spec.attribute("openexr:lineOrder", "increasingY")
    spec.attribute("worldbake:cell_size_m", float(cell_size_m))
    spec.attribute("worldbake:origin_m", json.dumps(list(origin_m)))
    # OpenImageIO stamps the current time otherwise; a fixed value keeps
    # repeated bakes byte-identical as well as pixel-identical.
    spec.attribute("DateTime", "")
    for k, v in (provenance or {}).items():
        spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
    return spec


class GridWriter:
    """A grid EXR written window by window, in any order, holding at most one
    row of file tiles in memory (besides the window being handed in).

    A window is a rectangle of whole file tiles: row0 and col0 multiples of
    the tile size, its rows and cols multiples of it or reaching the map's
    last row or column (one file tile, a world tile of k x k file tiles, a
    row of file tiles, the whole map). Tiles go to the file in one fixed
    order (row by row, west to east), so its bytes do not depend on the order
    the windows came in: a window below the row of tiles being assembled
    waits in an anonymous spool file beside the target, on disk. Each cell is
    written exactly once; close() checks that every tile came.

        with GridWriter(path, (rows, cols), ("height",), 8.0) as w:
            for row0, col0, block in windows:
                w.write_window(row0, col0, block)
    """

    def __init__(self, path: Path | str, shape: tuple[int, int], channels: tuple[str, ...] | list[str],
                 cell_size_m: float, origin_m: tuple[float, float] = (0.0, 0.0),
                 provenance: dict[str, Any] | None = None, *, tile: int = TILE) -> None:
        oiio = _oiio()
        self.path, self.shape, self.channels, self.tile = Path(path), (int(shape[0]), int(shape[1])), \
            tuple(channels), int(tile)
        if min(self.shape) < 1 or not self.channels or self.tile < 1 or not cell_size_m > 0:
            raise ValueError(f"{path}: cannot write a grid of shape {shape}, channels {channels}, "
                             f"cell {cell_size_m} m in tiles of {tile}")
        self._done = np.zeros((-(-self.shape[0] // self.tile), -(-self.shape[1] // self.tile)), bool)
        self._row = 0  # the tile row being assembled; every row above it is in the file
        self._band: np.ndarray | None = None
        self._spool = None
        self._spooled: dict[int, list[tuple[int, int, int]]] = {}  # tile row -> [(col0, cols, byte offset)]
        # Grid.content_hash of the whole map, fed row by row as the rows reach the file (their bytes in
        # row-major order are the map's), so a tiled write knows it without holding the map
        self._hash = hashlib.sha256(json.dumps([list(self.channels), list(self.shape if len(self.channels) == 1
                                                                          else (*self.shape, len(self.channels))),
                                                np.dtype(np.float32).str, cell_size_m, list(origin_m)]).encode())
        spec = _grid_spec(self.shape, self.channels, cell_size_m, origin_m, provenance, self.tile)
        self._out = oiio.ImageOutput.create(str(self.path))
        if self._out is None or not self._out.open(str(self.path), spec):
            raise OSError(f"cannot write {path}: {self._out.geterror() if self._out else oiio.geterror()}")

    def __enter__(self) -> GridWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        else:
            self._abort()

    def write_window(self, row0: int, col0: int, data: np.ndarray) -> None:
        """Cells [row0, row0 + rows) x [col0, col0 + cols) of the map, from an
        array (rows, cols) for one channel or (rows, cols, channels) in the
        writer's channel order."""
        row0, col0 = int(row0), int(col0)
        block, rows_t, cols_t = self._check_window(row0, col0, data)
        t = self.tile
        for r in range(rows_t.start, rows_t.stop):
            piece = block[r * t - row0:(r + 1) * t - row0]
            self._done[r, cols_t] = True
            if r != self._row:
                self._spill(r, col0, piece)
                continue
            if piece.shape[1] == self.shape[1]:  # a whole row of tiles: straight to the file
                self._write_row(piece)
            else:
                band = self._band_rows()
                band[:, col0:col0 + piece.shape[1]] = piece
                if not self._done[r].all():
                    continue
                self._write_row(band)
            self._row += 1
            self._pull()

    def close(self) -> None:
        """Finish the file; a tile never written is a ValueError (and no file)."""
        if self._out is None:
            return
        if not self._done.all():
            missing = np.argwhere(~self._done)
            self._abort()
            r, c = (int(v) * self.tile for v in missing[0])
            raise ValueError(f"{self.path}: {len(missing)} of {self._done.size} file tiles never written, "
                             f"the first at row {r}, col {c}")
        out, self._out = self._out, None
        ok = out.close()
        self._close_spool()
        if not ok:
            raise OSError(f"cannot write {self.path}: {out.geterror()}")

    def content_hash(self) -> str:
        """After close(): what Grid.content_hash gives for the whole map as float32."""
        if self._out is not None or not self._done.all():
            raise ValueError(f"{self.path}: content_hash before the grid is closed whole")
        return self._hash.hexdigest()

    def _check_window(self, row0: int, col0: int, data: np.ndarray) -> tuple[np.ndarray, slice, slice]:
        if self._out is None:
            raise ValueError(f"{self.path}: a window written after close()")
        block = np.asarray(data, dtype=np.float32)
        if block.ndim == 2 and len(self.channels) == 1:
            block = block[:, :, None]
        if block.ndim != 3 or block.shape[2] != len(self.channels):
            raise ValueError(f"{self.path}: a window of shape {np.shape(data)} does not match channels "
                             f"{self.channels}")
        (rows, cols), (n_rows, n_cols), t = block.shape[:2], self.shape, self.tile
        whole = (row0 % t == 0 and col0 % t == 0 and (rows % t == 0 or row0 + rows == n_rows)
                 and (cols % t == 0 or col0 + cols == n_cols))
        if not (whole and row0 >= 0 and col0 >= 0 and rows >= 1 and cols >= 1 and row0 + rows <= n_rows
                and col0 + cols <= n_cols):
            raise ValueError(f"{self.path}: window rows {row0}..{row0 + rows - 1}, cols {col0}..{col0 + cols - 1} "
                             f"is not a rectangle of whole {t}x{t} file tiles inside the {n_rows} x {n_cols} map")
        rows_t, cols_t = slice(row0 // t, -(-(row0 + rows) // t)), slice(col0 // t, -(-(col0 + cols) // t))
        if self._done[rows_t, cols_t].any():
            raise ValueError(f"{self.path}: window rows {row0}..{row0 + rows - 1}, cols {col0}..{col0 + cols - 1} "
                             f"overlaps cells already written")
        return block, rows_t, cols_t

    def _band_rows(self) -> np.ndarray:
        """The buffer of the row of tiles being assembled (one, reused)."""
        if self._band is None:
            self._band = np.empty((min(self.tile, self.shape[0]), self.shape[1], len(self.channels)), np.float32)
        return self._band[:min(self.shape[0], (self._row + 1) * self.tile) - self._row * self.tile]

    def _write_row(self, pixels: np.ndarray) -> None:
        y0, pixels = self._row * self.tile, np.ascontiguousarray(pixels)
        if not self._out.write_tiles(0, self.shape[1], y0, y0 + pixels.shape[0], 0, 1, pixels):
            raise OSError(f"cannot write {self.path}: {self._out.geterror()}")
        self._hash.update(pixels.data)

    def _spill(self, r: int, col0: int, piece: np.ndarray) -> None:
        """Keep a window's part in a later row of tiles on disk until its row comes."""
        if self._spool is None:
            self._spool = tempfile.TemporaryFile(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".spool")
        offset = self._spool.seek(0, 2)
        self._spool.write(np.ascontiguousarray(piece).tobytes())
        self._spooled.setdefault(r, []).append((col0, piece.shape[1], offset))

    def _pull(self) -> None:
        """Move the spooled windows of the new current row into the buffer,
        and write each row they complete."""
        while self._row < self._done.shape[0] and self._row in self._spooled:
            band = self._band_rows()
            for col0, cols, offset in self._spooled.pop(self._row):
                self._spool.seek(offset)
                raw = self._spool.read(band.shape[0] * cols * band.shape[2] * 4)
                band[:, col0:col0 + cols] = np.frombuffer(raw, np.float32).reshape(band.shape[0], cols, -1)
            if not self._done[self._row].all():
                return
            self._write_row(band)
            self._row += 1

    def _close_spool(self) -> None:
        if self._spool is not None:
            self._spool.close()
            self._spool = None

    def _abort(self) -> None:
        """No file rather than a partial one."""
        if self._out is not None:
            self._out.close()
            self._out = None
        self._close_spool()
        self.path.unlink(missing_ok=True)


def write_grid(path: Path | str, grid: Grid, provenance: dict[str, Any] | None = None) -> None:
    """A whole grid: the same bytes as any GridWriter of its windows."""
    with GridWriter(path, grid.shape, grid.channels, grid.cell_size_m, grid.origin_m, provenance) as out:
        out.write_window(0, 0, grid.data)


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


def _grid_info(inp, path: Path | str) -> GridInfo:
    spec = inp.spec()
    cell = spec.getattribute("worldbake:cell_size_m")
    if cell is None:
        raise InputError(f"{path}: no worldbake:cell_size_m attribute; not a worldbake grid")
    origin = tuple(json.loads(spec.getattribute("worldbake:origin_m") or "[0, 0]"))
    return GridInfo((spec.height, spec.width), tuple(spec.channelnames), float(cell), origin, spec.tile_width)


def grid_info(path: Path | str) -> GridInfo:
    """A grid file's shape, channels, geometry and file tile size, from its header alone."""
    with _image_input(path) as inp:
        return _grid_info(inp, path)


def _as_grid(pixels: Any, rows: int, cols: int, info: GridInfo, origin: tuple[float, float]) -> Grid:
    data = np.asarray(pixels, dtype=np.float32).reshape(rows, cols, len(info.channels))
    if len(info.channels) == 1:
        data = data[:, :, 0]
    return Grid(np.ascontiguousarray(data), info.cell_size_m, info.channels, origin)


def read_grid(path: Path | str) -> Grid:
    """A grid written by write_grid or GridWriter (tiled), or by the scanline
    writer before them. A file that is missing, corrupt or not a worldbake
    grid raises InputError naming it."""
    oiio = _oiio()
    with _image_input(path) as inp:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if pixels is None:
            raise InputError(f"{path}: cannot decode pixels: {inp.geterror()}")
        info = _grid_info(inp, path)
    return _as_grid(pixels, *info.shape, info, info.origin_m)


def read_window(path: Path | str, row0: int, col0: int, rows: int, cols: int) -> Grid:
    """Cells [row0, row0 + rows) x [col0, col0 + cols) of a grid file, with
    the window's own origin; only the file tiles (or, in a scanline file, the
    rows) the window touches are decoded. A window outside the map is an
    InputError naming the file."""
    oiio = _oiio()
    row0, col0, rows, cols = int(row0), int(col0), int(rows), int(cols)
    with _image_input(path) as inp:
        info, spec = _grid_info(inp, path), inp.spec()
        (n_rows, n_cols), n = info.shape, spec.nchannels
        if not (row0 >= 0 and col0 >= 0 and rows >= 1 and cols >= 1 and row0 + rows <= n_rows
                and col0 + cols <= n_cols):
            raise InputError(f"{path}: window rows {row0}..{row0 + rows - 1}, cols {col0}..{col0 + cols - 1} "
                             f"is outside the map's {n_rows} x {n_cols} cells")
        if spec.tile_width:  # the whole file tiles the window touches
            tw, th = spec.tile_width, spec.tile_height
            x0, y0 = col0 // tw * tw, row0 // th * th
            x1, y1 = min(n_cols, -(-(col0 + cols) // tw) * tw), min(n_rows, -(-(row0 + rows) // th) * th)
            pixels = inp.read_tiles(0, 0, spec.x + x0, spec.x + x1, spec.y + y0, spec.y + y1, spec.z, spec.z + 1,
                                    0, n, oiio.FLOAT)
        else:
            x0, y0, x1, y1 = 0, row0, n_cols, row0 + rows
            pixels = inp.read_scanlines(0, 0, spec.y + y0, spec.y + y1, spec.z, 0, n, oiio.FLOAT)
        if pixels is None or inp.has_error:
            raise InputError(f"{path}: cannot decode rows {y0}..{y1 - 1}: {inp.geterror()}")
    block = np.asarray(pixels, np.float32).reshape(y1 - y0, x1 - x0, n)
    block = block[row0 - y0:row0 - y0 + rows, col0 - x0:col0 - x0 + cols]
    origin = (info.origin_m[0] + col0 * info.cell_size_m, info.origin_m[1] + row0 * info.cell_size_m)
    return _as_grid(block, rows, cols, info, origin)


def channel_names(path: Path | str) -> list[str]:
    """The channel names of an image in the order the file stores them
    (not the order written: OpenEXR sorts them by name and OpenImageIO puts
    names without a dot first); read a channel by its name, not its place."""
    with _image_input(path) as inp:
        return list(inp.spec().channelnames)


def read_attributes(path: Path | str) -> dict[str, Any]:
    """The header attributes of an image, as a dict."""
    with _image_input(path) as inp:
        return {a.name: a.value for a in inp.spec().extra_attribs}


PNG_COMPRESSION = 1  # zlib level of the previews: a third of the default 6's time for a tenth more bytes


def write_png(path: Path | str, rgb: np.ndarray) -> None:
    """A uint8 RGB(A) preview picture."""
    rgb = np.ascontiguousarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] not in (3, 4):
        raise ValueError(f"a preview must be uint8 (rows, cols, 3|4), got {rgb.dtype} {rgb.shape}")
    write_png_rows(path, rgb.shape[:2], [rgb])


def write_png_rows(path: Path | str, shape: tuple[int, int], bands) -> None:
    """A uint8 RGB(A) preview written band by band (`bands`: arrays of whole
    rows, north to south, covering `shape`): the bytes of write_png of the
    whole picture, without holding it."""
    oiio = _oiio()
    out, y = None, 0
    try:
        for band in bands:
            band = np.ascontiguousarray(band)
            if band.dtype != np.uint8 or band.ndim != 3 or band.shape[2] not in (3, 4) or band.shape[1] != shape[1]:
                raise ValueError(f"a preview band must be uint8 (rows, {shape[1]}, 3|4), got {band.dtype} {band.shape}")
            if out is None:
                spec = oiio.ImageSpec(int(shape[1]), int(shape[0]), band.shape[2], oiio.UINT8)
                spec.attribute("png:compressionLevel", PNG_COMPRESSION)
                out = oiio.ImageOutput.create(str(path))
                if out is None or not out.open(str(path), spec):
                    raise OSError(f"cannot write {path}: {out.geterror() if out else oiio.geterror()}")
            if not out.write_scanlines(y, y + band.shape[0], 0, band):
                raise OSError(f"cannot write {path}: {out.geterror()}")
            y += band.shape[0]
        if y != shape[0]:
            raise ValueError(f"{path}: the bands cover {y} of {shape[0]} rows")
    except BaseException:
        if out is not None:
            out.close()
        Path(path).unlink(missing_ok=True)
        raise
    if not out.close():
        raise OSError(f"cannot write {path}: {out.geterror()}")


def linear_from_srgb(srgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] colour to linear (the standard piecewise curve), in the input's precision."""
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def srgb8(linear_rgb: np.ndarray) -> np.ndarray:
    """Linear [0, 1] colour to 8-bit sRGB (the standard piecewise curve)."""
    x = np.clip(np.asarray(linear_rgb, np.float64), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)
