"""Sparse voxel volumes: a level as its occupied voxels only, its mips, and
the EXR "column runs" file it is stored in.

A forest sector is mostly air: a canopy a few voxels thick over sloping
ground fills a few percent of its clipped box, a few voxels per occupied
(x, z) column. A SparseLevel holds the occupied voxels of a grid (density
or surface above 0): their flat indices (z * ny + y) * nx + x, ascending,
and their channels, with the grid's shape, origin and voxel edge; the
channels and units are those of worldlib.volumes.dense.VolumeLevel, and
to_dense() gives that level back.

Column runs (the file): every (x, z) column of the grid holds its occupied
voxels in one run along y, from its lowest to its highest occupied voxel
(an empty voxel between them is stored as zeros). Two EXR parts:

    part 0 "voxels"   the runs one after the other, columns in z-then-x
                      order, each from its bottom up, pixels row-major in
                      an image RUNS_WIDTH wide; channels as the Z-slice
                      atlas (worldlib.volumes.dense.CHANNELS; density float32,
                      the others half floats); the header as the atlas's
                      (volume_grid, volume_bbox_min/_max, volume_voxel_m,
                      volume_mip, ...) with volume_layout "column runs".
    part 1 "columns"  nx x nz pixels (image row z, column x), uint
                      channels run.y0 (lowest y), run.length (0: an empty
                      column) and run.offset (the run's first pixel of
                      part 0, counted row-major).

Voxel (x, y, z) is pixel run.offset + y - run.y0 of part 0 where
run.y0 <= y < run.y0 + run.length, and air elsewhere: one 2-D texture fetch
and one buffer fetch, as a shader reads a height-field volume. Unlike
8^3 or 4^3 bricks (OpenVDB leaves) it stores only the canopy's own voxels,
not the air that shares a brick with them.

Mips sum each 2 x 2 x 2 block of occupied voxels (np.bincount in voxel
order: deterministic), as worldlib.volumes.dense.downsample does on a dense grid.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import InputError

from .dense import CHANNEL_UNITS, CHANNELS, HALF_MAX, VolumeLevel, header_attributes, read_atlas, read_channels

RUNS_WIDTH = 256  # pixels a row of the voxels part
RUN_CHANNELS = ("run.y0", "run.length", "run.offset")


@dataclass
class SparseLevel:
    index: np.ndarray  # (n,) int64 flat voxel index (z * ny + y) * nx + x, ascending
    density: np.ndarray  # (n,) float32, 1/m
    albedo: np.ndarray  # (n, 3) float32, density-premultiplied
    normal: np.ndarray  # (n, 3) float32, length <= 1
    surface: np.ndarray  # (n,) float32, m^2/m^3
    shape_xyz: tuple[int, int, int]
    origin: np.ndarray  # (3,) float64 min corner (x, y, z), m
    voxel_m: float
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        nx, ny, nz = self.shape_xyz
        return nx * ny * nz

    @property
    def bbox_max(self) -> np.ndarray:
        return self.origin + np.array(self.shape_xyz, np.float64) * self.voxel_m

    @property
    def nbytes(self) -> int:
        """Memory of the level as a dense grid of 8 float32 channels."""
        return int(self.size * len(CHANNELS) * 4)

    def mean_density(self) -> float:
        """The dense grid's mean (air counts as 0)."""
        return float(np.sum(self.density, dtype=np.float64) / self.size)

    def check_finite(self, what: str) -> None:
        for name in ("density", "albedo", "normal", "surface"):
            if not np.isfinite(getattr(self, name)).all():
                raise FloatingPointError(f"{what}: the volume's {name} holds NaN or Inf")

    def atlas_info(self) -> dict[str, Any]:
        return {"layout": "column runs"}

    def to_dense(self) -> VolumeLevel:
        nx, ny, nz = self.shape_xyz
        out = VolumeLevel(np.zeros(self.size, np.float32), np.zeros((self.size, 3), np.float32),
                          np.zeros((self.size, 3), np.float32), np.zeros(self.size, np.float32),
                          np.asarray(self.origin, np.float64).copy(), float(self.voxel_m), dict(self.attributes))
        out.density[self.index], out.albedo[self.index] = self.density, self.albedo
        out.normal[self.index], out.surface[self.index] = self.normal, self.surface
        out.density, out.surface = out.density.reshape(nz, ny, nx), out.surface.reshape(nz, ny, nx)
        out.albedo, out.normal = out.albedo.reshape(nz, ny, nx, 3), out.normal.reshape(nz, ny, nx, 3)
        return out


def from_dense(level: VolumeLevel) -> SparseLevel:
    """The occupied voxels of a dense level."""
    d, s = level.density.ravel(), level.surface.ravel()
    index = np.flatnonzero((d > 0) | (s > 0))
    return SparseLevel(index, d[index], level.albedo.reshape(-1, 3)[index], level.normal.reshape(-1, 3)[index],
                       s[index], level.shape_xyz, np.asarray(level.origin, np.float64).copy(), float(level.voxel_m))


def normals_from_sums(weighted: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """Surface-weighted mean normals (float32), 0 without surface, never longer than 1."""
    out = np.zeros(weighted.shape, np.float32)
    where = surface > 0
    mean = weighted[where] / surface[where][:, None]
    length = np.linalg.norm(mean, axis=-1, keepdims=True)
    out[where] = np.where(length > 1.0, mean / np.maximum(length, 1e-30), mean)
    return out


def downsample(level: SparseLevel) -> SparseLevel:
    """The next mip: voxels twice the edge, density, albedo and surface the
    mean of 2 x 2 x 2 voxels, normals the surface-weighted mean."""
    nx, ny, nz = level.shape_xyz
    if nx % 2 or ny % 2 or nz % 2:
        raise ValueError(f"a volume of {level.shape_xyz} voxels has no exact mip")
    z, rest = np.divmod(level.index, nx * ny)
    y, x = np.divmod(rest, nx)
    parent = ((z // 2) * (ny // 2) + y // 2) * (nx // 2) + x // 2
    index, owner = np.unique(parent, return_inverse=True)
    m = len(index)
    add = lambda w: np.bincount(owner, w, m)  # noqa: E731  (float64 sums in voxel order)
    surf = add(level.surface.astype(np.float64))
    weighted = np.stack([add(level.normal[:, c].astype(np.float64) * level.surface) for c in range(3)], 1)
    albedo = np.stack([add(level.albedo[:, c].astype(np.float64)) for c in range(3)], 1)
    return SparseLevel(index, (add(level.density.astype(np.float64)) / 8).astype(np.float32),
                       (albedo / 8).astype(np.float32), normals_from_sums(weighted, surf), (surf / 8).astype(np.float32),
                       (nx // 2, ny // 2, nz // 2), level.origin.copy(), 2 * level.voxel_m)


def round_to_pxr24(a: np.ndarray) -> np.ndarray:
    """float32 values as OpenEXR's pxr24 compression stores them (the
    significand rounded to 15 bits, ImfPxr24Compressor floatToFloat24), so
    that what is computed from them is what is read back."""
    u = np.ascontiguousarray(a, np.float32).view(np.uint32)
    em = u & np.uint32(0x7FFFFFFF)
    r = ((em + (u & np.uint32(0x80))) >> np.uint32(8)) << np.uint32(8)
    r = np.where((em >= np.uint32(0x7F800000)) | (r >= np.uint32(0x7F800000)), (em >> np.uint32(8)) << np.uint32(8), r)
    return ((u & np.uint32(0x80000000)) | r).view(np.float32)


def mip_chain(level: SparseLevel, count: int) -> list[SparseLevel]:
    out = [level]
    for _ in range(count - 1):
        out.append(downsample(out[-1]))
    return out


# --------------------------------------------------------------------------- the column runs file


def column_runs(level: SparseLevel) -> tuple[np.ndarray, np.ndarray]:
    """((nz, nx, 3) uint32 run.y0, run.length, run.offset per column; (n,)
    int64 pixel of each occupied voxel in the voxels part)."""
    nx, ny, nz = level.shape_xyz
    z, rest = np.divmod(level.index, nx * ny)
    y, x = np.divmod(rest, nx)
    col = z * nx + x
    columns = np.zeros((nz * nx, 3), np.int64)
    if len(col):
        order = np.lexsort((y, col))
        cs, ys = col[order], y[order]
        starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
        last = np.r_[starts[1:], len(cs)] - 1
        columns[cs[starts], 0] = ys[starts]
        columns[cs[starts], 1] = ys[last] - ys[starts] + 1
    columns[:, 2] = np.cumsum(columns[:, 1]) - columns[:, 1]
    pixel = columns[col, 2] + y - columns[col, 0]
    if columns[-1, 2] + columns[-1, 1] >= 2 ** 32:
        raise ValueError(f"a volume of {level.shape_xyz} voxels holds too many runs for uint32 offsets")
    return columns.reshape(nz, nx, 3).astype(np.uint32), pixel


def _header(spec, attrs: dict[str, Any]) -> None:
    for k, v in attrs.items():
        spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))


def write_runs(path: Path | str, level: SparseLevel, mip: int, provenance: dict[str, Any] | None = None,
               stats: dict[str, Any] | None = None, compression: str = "zip") -> None:
    """One level as a column runs EXR (module docstring): density float32,
    the other channels half floats (a value a half cannot hold is refused,
    never written as Inf)."""
    import OpenImageIO as oiio

    columns, pixel = column_runs(level)
    total = int(columns[-1, -1, 2]) + int(columns[-1, -1, 1])
    rows = max(1, -(-total // RUNS_WIDTH))
    values = np.concatenate([level.albedo, level.density[:, None], level.normal, level.surface[:, None]], axis=1)
    if np.abs(np.delete(values, 3, axis=1)).max(initial=0.0) > HALF_MAX:
        raise ValueError(f"{path}: a value of {np.abs(values).max():.3g} does not fit a half float EXR")
    voxels = np.zeros((rows * RUNS_WIDTH, len(CHANNELS)), np.float32)
    voxels[pixel] = values
    nx, ny, nz = level.shape_xyz
    spec = oiio.ImageSpec(RUNS_WIDTH, rows, len(CHANNELS), oiio.FLOAT)
    spec.channelformats = [oiio.TypeDesc(oiio.FLOAT if c == "density" else oiio.HALF) for c in CHANNELS]
    spec.channelnames = CHANNELS
    table = oiio.ImageSpec(nx, nz, len(RUN_CHANNELS), oiio.UINT)
    table.channelnames = RUN_CHANNELS
    for s, name in ((spec, "voxels"), (table, "columns")):
        s.full_x = s.full_y = 0
        s.full_width, s.full_height = RUNS_WIDTH, rows  # OpenEXR parts of one file share the display window
        s.attribute("name", name)
        s.attribute("compression", compression)
        s.attribute("DateTime", "")
    attrs = {"volume_grid": [nx, ny, nz], "volume_layout": "column runs", "volume_runs_width": RUNS_WIDTH,
             "volume_runs_voxels": total, "volume_occupied_voxels": int(len(level.index)),
             "volume_bbox_min": [float(v) for v in level.origin], "volume_bbox_max": [float(v) for v in level.bbox_max],
             "volume_voxel_m": float(level.voxel_m), "volume_mip": int(mip),
             "volume_columns": "part 1: nx x nz pixels (row z, column x), run.y0, run.length, run.offset",
             "units": dict(zip(CHANNELS, CHANNEL_UNITS)), "volume_bytes": level.nbytes,
             "volume_pixel_type": "half (density float)", **(stats or {})}
    _header(spec, {**(provenance or {}), **attrs})
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), [spec, table]):
        raise OSError(f"cannot write {path}: {oiio.geterror() if out is None else out.geterror()}")
    ok = out.write_image(voxels.reshape(rows, RUNS_WIDTH, len(CHANNELS)))
    ok = ok and out.open(str(path), table, "AppendSubimage") and out.write_image(np.ascontiguousarray(columns))
    ok = out.close() and ok
    if not ok:
        raise OSError(f"cannot write {path}: {out.geterror()}")


def read_runs(path: Path | str) -> SparseLevel:
    """A level written by write_runs, its header attributes in `attributes`."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read: {oiio.geterror()}")
    try:
        voxels, attrs = read_channels(inp, path, "a column runs volume")
        voxels = voxels.reshape(-1, len(CHANNELS))
        if attrs.get("volume_layout") != "column runs" or not inp.seek_subimage(1, 0):
            raise InputError(f"{path}: not a column runs volume (no worldbake:volume_layout or no columns part)")
        tspec = inp.spec()
        tnames = tuple(tspec.channelnames)
        table = np.asarray(inp.read_image(1, 0, 0, tspec.nchannels, oiio.UINT), np.int64).reshape(-1, tspec.nchannels)
        table = table[:, [tnames.index(c) for c in RUN_CHANNELS]]
    finally:
        inp.close()
    nx, ny, nz = attrs["volume_grid"]
    if table.shape[0] != nx * nz:
        raise InputError(f"{path}: {table.shape[0]} columns for a grid of {nx} x {nz} columns")
    length = table[:, 1]
    owner = np.repeat(np.arange(len(length)), length)
    j = np.arange(len(owner)) - (np.cumsum(length) - length)[owner]
    pixel = table[owner, 2] + j
    vals = voxels[pixel]
    z, x = np.divmod(owner, nx)
    index = (z * ny + table[owner, 0] + j) * nx + x
    keep = (vals[:, 3] > 0) | (vals[:, 7] > 0)
    order = np.argsort(index[keep], kind="stable")
    vals, index = vals[keep][order], index[keep][order]
    return SparseLevel(index, np.ascontiguousarray(vals[:, 3]), np.ascontiguousarray(vals[:, 0:3]),
                       np.ascontiguousarray(vals[:, 4:7]), np.ascontiguousarray(vals[:, 7]), (nx, ny, nz),
                       np.asarray(attrs["volume_bbox_min"], np.float64), float(attrs["volume_voxel_m"]), attrs)


def read_level(path: Path | str) -> VolumeLevel:
    """A dense level from either volume file: a Z-slice atlas
    (worldlib.volumes.dense.write_atlas) or column runs (write_runs)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read: {oiio.geterror()}")
    try:
        layout = header_attributes(inp.spec()).get("volume_layout")
    finally:
        inp.close()
    return read_runs(path).to_dense() if layout == "column runs" else read_atlas(path)
