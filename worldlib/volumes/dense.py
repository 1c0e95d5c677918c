"""Voxel volumes of plants and forests: one level of a grid, its mips, and
the EXR pseudo-volume atlas they are stored in.

A level holds, per cubic voxel of edge `voxel_m` (arrays indexed [z, y, x],
voxel (i, j, k) centred at origin + (i + 1/2, j + 1/2, k + 1/2) voxel_m):

    density  extinction coefficient (1/m): a ray of length s through the
             voxel keeps exp(-density s) of its light. Foliage and bark
             surfaces give half their one-sided area per volume (the
             projected area of randomly turned leaves, Ross's G = 1/2);
             the woody solid gives its occupied share of the voxel times
             SOLID_OPTICAL_DEPTH / (finest voxel edge): opaque where full.
    albedo   linear RGB premultiplied by density (1/m): the mean albedo is
             albedo / density, so averaging voxels averages colour weighted
             by what blocks light;
    normal   mean unit surface normal of the voxel's surface (area-weighted);
             its length, at most 1, says how spread the normals are
             (1: one plane, 0: all directions);
    surface  surface area per volume (m^2/m^3), the normals' weight.

Mips average 2x2x2 voxels: density, albedo and surface are linear, so the
mean of every level is the finest level's (a grid's dimensions are
multiples of 2^(levels-1)); normals are the surface-weighted mean.

EXR has no 3-D image: a level is written as Z slices tiled in a 2-D atlas
(the pseudo-volume texture layout engines import, e.g. Unreal's volume
texture from a tiled 2-D texture): slice z sits at tile column z % tiles_x,
row z // tiles_x, and inside a tile image rows run from the top (largest
y) down, columns along +x, so a slice looks upright. The header records
worldbake:volume_grid (nx, ny, nz), volume_tiles (tiles_x, tiles_y),
volume_bbox_min / _max (m), volume_voxel_m, volume_mip, volume_slice_axis,
volume_row0 and any statistics given.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import InputError

CHANNELS = ("albedo.R", "albedo.G", "albedo.B", "density", "normal.x", "normal.y", "normal.z", "surface")
CHANNEL_UNITS = ("1/m", "1/m", "1/m", "1/m", "1", "1", "1", "1/m")
SOLID_OPTICAL_DEPTH = math.log(1000.0)  # a full solid voxel lets 0.1 % of the light through its edge
LEAF_PROJECTION = 0.5  # mean projected area of a randomly turned flat surface per one-sided area


@dataclass
class VolumeLevel:
    density: np.ndarray  # (nz, ny, nx) float32, 1/m
    albedo: np.ndarray  # (nz, ny, nx, 3) float32, density-premultiplied
    normal: np.ndarray  # (nz, ny, nx, 3) float32, length <= 1
    surface: np.ndarray  # (nz, ny, nx) float32, m^2/m^3
    origin: np.ndarray  # (3,) float64, the grid's min corner (x, y, z), m
    voxel_m: float
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        nz, ny, nx = self.density.shape
        return nx, ny, nz

    @property
    def bbox_max(self) -> np.ndarray:
        return self.origin + np.array(self.shape_xyz, np.float64) * self.voxel_m

    @property
    def nbytes(self) -> int:
        """Memory of the level as held and written: 8 float32 channels a voxel."""
        return int(self.density.size * len(CHANNELS) * 4)

    def mean_density(self) -> float:
        return float(np.mean(self.density, dtype=np.float64))

    def check_finite(self, what: str) -> None:
        for name in ("density", "albedo", "normal", "surface"):
            a = getattr(self, name)
            if not np.isfinite(a).all():
                raise FloatingPointError(f"{what}: the volume's {name} holds NaN or Inf")

    def atlas_info(self) -> dict[str, Any]:
        """How the level's file lays out its voxels (USD customData worldbake:atlas)."""
        return {"layout": "z slices", "tiles": list(atlas_tiles(self.shape_xyz[2]))}


def empty_level(shape_xyz: tuple[int, int, int], origin, voxel_m: float) -> VolumeLevel:
    nx, ny, nz = shape_xyz
    return VolumeLevel(np.zeros((nz, ny, nx), np.float32), np.zeros((nz, ny, nx, 3), np.float32),
                       np.zeros((nz, ny, nx, 3), np.float32), np.zeros((nz, ny, nx), np.float32),
                       np.asarray(origin, np.float64), float(voxel_m))


def grid_for_box(lo, hi, voxels_longest: int, multiple: int) -> tuple[np.ndarray, float, tuple[int, int, int]]:
    """Cubic voxels over the box lo..hi: `voxels_longest` along its longest
    side, the other sides rounded up to a multiple of `multiple` voxels (so
    that every mip halves exactly) and centred on the box. Returns (origin,
    voxel edge, (nx, ny, nz))."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    ext = np.maximum(hi - lo, 1e-6)
    voxel = float(ext.max()) / voxels_longest
    n = np.maximum(np.ceil(ext / voxel - 1e-9).astype(int), 1)
    n = -(-n // multiple) * multiple
    centre = 0.5 * (lo + hi)
    origin = centre - 0.5 * n * voxel
    return origin, voxel, (int(n[0]), int(n[1]), int(n[2]))


def _pool(a: np.ndarray) -> np.ndarray:
    """Sum of each 2x2x2 block over the first three axes, in float64."""
    nz, ny, nx = a.shape[:3]
    b = a.reshape(nz // 2, 2, ny // 2, 2, nx // 2, 2, *a.shape[3:])
    return b.sum(axis=(1, 3, 5), dtype=np.float64)  # float64 sums without a float64 copy of the level


def downsample(level: VolumeLevel) -> VolumeLevel:
    """The next mip: voxels twice the edge, linear channels averaged, normals
    the surface-weighted mean (never longer than 1)."""
    if any(s % 2 for s in level.density.shape):
        raise ValueError(f"a volume of {level.shape_xyz} voxels has no exact mip")
    surf = _pool(level.surface)
    weighted = _pool(level.normal * level.surface[..., None])
    # only where there is surface: most of a plant's box, and nearly all of a forest sector's, is air
    where = surf > 0
    mean = weighted[where] / surf[where][:, None]
    length = np.linalg.norm(mean, axis=-1, keepdims=True)
    normal = np.zeros(weighted.shape, np.float32)
    normal[where] = np.where(length > 1.0, mean / np.maximum(length, 1e-30), mean)
    return VolumeLevel((_pool(level.density) / 8).astype(np.float32), (_pool(level.albedo) / 8).astype(np.float32),
                       normal, (surf / 8).astype(np.float32), level.origin.copy(), 2 * level.voxel_m)


def pad_even(level: VolumeLevel) -> VolumeLevel:
    """The level with empty voxels added at the far side of every odd
    dimension (same origin, same sums): ready for downsample."""
    nz, ny, nx = level.density.shape
    pad = [(0, nz % 2), (0, ny % 2), (0, nx % 2)]
    if not any(p[1] for p in pad):
        return level
    return VolumeLevel(np.pad(level.density, pad), np.pad(level.albedo, pad + [(0, 0)]),
                       np.pad(level.normal, pad + [(0, 0)]), np.pad(level.surface, pad), level.origin.copy(),
                       level.voxel_m)


def mip_chain(level: VolumeLevel, count: int) -> list[VolumeLevel]:
    """level and its count - 1 mips."""
    out = [level]
    for _ in range(count - 1):
        out.append(downsample(out[-1]))
    return out


# --------------------------------------------------------------------------- the EXR atlas


def atlas_tiles(nz: int) -> tuple[int, int]:
    """(tiles_x, tiles_y) of a Z-slice atlas: as square as the slice count allows."""
    tx = max(1, math.ceil(math.sqrt(nz)))
    return tx, max(1, math.ceil(nz / tx))


def to_atlas(level: VolumeLevel) -> np.ndarray:
    """(tiles_y * ny, tiles_x * nx, channels) float32 atlas of the level."""
    nx, ny, nz = level.shape_xyz
    tx, ty = atlas_tiles(nz)
    vox = np.concatenate([level.albedo, level.density[..., None], level.normal, level.surface[..., None]], axis=-1)
    out = np.zeros((ty * ny, tx * nx, len(CHANNELS)), np.float32)
    for z in range(nz):
        r, c = divmod(z, tx)
        out[r * ny:(r + 1) * ny, c * nx:(c + 1) * nx] = vox[z, ::-1]
    return out


def from_atlas(atlas: np.ndarray, shape_xyz: tuple[int, int, int], origin, voxel_m: float) -> VolumeLevel:
    nx, ny, nz = shape_xyz
    tx, ty = atlas_tiles(nz)
    if atlas.shape[:2] != (ty * ny, tx * nx):
        raise ValueError(f"an atlas of {atlas.shape[:2]} pixels cannot hold {shape_xyz} voxels in {tx} x {ty} tiles")
    vox = np.empty((nz, ny, nx, atlas.shape[2]), np.float32)
    for z in range(nz):
        r, c = divmod(z, tx)
        vox[z] = atlas[r * ny:(r + 1) * ny, c * nx:(c + 1) * nx][::-1]
    return VolumeLevel(np.ascontiguousarray(vox[..., 3]), np.ascontiguousarray(vox[..., 0:3]),
                       np.ascontiguousarray(vox[..., 4:7]), np.ascontiguousarray(vox[..., 7]),
                       np.asarray(origin, np.float64), float(voxel_m))


HALF_MAX = 65504.0


def write_atlas(path: Path | str, level: VolumeLevel, mip: int, provenance: dict[str, Any] | None = None,
                stats: dict[str, Any] | None = None, half: bool = False) -> None:
    """One level as a zip EXR atlas with the layout in its header: float32,
    or with `half` every channel but density in 16-bit floats (3
    significant digits, about half the disk; the header's
    volume_pixel_type says which). Density stays float32 so that the stored
    mips keep the finest level's mean coverage. A value a half cannot hold
    is refused, never written as Inf."""
    import OpenImageIO as oiio

    atlas = to_atlas(level)
    if half and np.abs(atlas).max(initial=0.0) > HALF_MAX:
        raise ValueError(f"{path}: a value of {np.abs(atlas).max():.3g} does not fit a half float EXR")
    nx, ny, nz = level.shape_xyz
    tx, ty = atlas_tiles(nz)
    spec = oiio.ImageSpec(atlas.shape[1], atlas.shape[0], atlas.shape[2], oiio.FLOAT)
    if half:
        spec.channelformats = [oiio.TypeDesc(oiio.FLOAT if c == "density" else oiio.HALF) for c in CHANNELS]
    spec.channelnames = CHANNELS
    spec.attribute("compression", "zip")
    spec.attribute("DateTime", "")
    attrs = {"volume_grid": [nx, ny, nz], "volume_tiles": [tx, ty], "volume_bbox_min": [float(v) for v in level.origin],
             "volume_bbox_max": [float(v) for v in level.bbox_max], "volume_voxel_m": float(level.voxel_m),
             "volume_mip": int(mip), "volume_slice_axis": "z", "volume_row0": "largest y",
             "volume_tile_order": "slice z at tile column z % tiles_x, row z // tiles_x",
             "units": dict(zip(CHANNELS, CHANNEL_UNITS)), "volume_bytes": level.nbytes,
             "volume_pixel_type": "half (density float)" if half else "float"}
    attrs.update(stats or {})
    for k, v in {**(provenance or {}), **attrs}.items():
        spec.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(atlas)
    ok = out.close() and ok
    if not ok:
        raise OSError(f"cannot write {path}: {out.geterror()}")


def header_attributes(spec) -> dict[str, Any]:
    """The worldbake:* attributes of an OpenImageIO ImageSpec, JSON decoded."""
    attrs = {}
    for a in spec.extra_attribs:
        if a.name.startswith("worldbake:"):
            try:
                attrs[a.name[10:]] = json.loads(a.value)
            except (TypeError, ValueError):
                attrs[a.name[10:]] = a.value
    return attrs


def read_channels(inp, path: Path | str, what: str) -> tuple[np.ndarray, dict[str, Any]]:
    """The open EXR's first part as (rows, cols, CHANNELS) float32, in
    CHANNELS order (OpenEXR stores channels sorted by name), and its header
    attributes; `what` names the format in the error for other channels."""
    import OpenImageIO as oiio

    spec = inp.spec()
    names = tuple(spec.channelnames)
    if sorted(names) != sorted(CHANNELS):
        raise InputError(f"{path}: channels {names}, {what} has {CHANNELS}")
    pixels = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT), np.float32)
    pixels = pixels.reshape(spec.height, spec.width, spec.nchannels)[..., [names.index(c) for c in CHANNELS]]
    return pixels, header_attributes(spec)


def read_atlas(path: Path | str) -> VolumeLevel:
    """A level written by write_atlas, its header attributes in `attributes`
    (worldlib.volumes.sparse.read_level reads column runs files too)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read: {oiio.geterror()}")
    try:
        pixels, attrs = read_channels(inp, path, "a volume atlas")
    finally:
        inp.close()
    if "volume_grid" not in attrs:
        raise InputError(f"{path}: no worldbake:volume_grid attribute; not a volume atlas")
    if attrs.get("volume_layout") == "column runs":
        raise InputError(f"{path}: a column runs volume; worldlib.volumes.sparse.read_level reads it")
    level = from_atlas(np.ascontiguousarray(pixels), tuple(attrs["volume_grid"]),
                       attrs["volume_bbox_min"], attrs["volume_voxel_m"])
    level.attributes = attrs
    return level


# --------------------------------------------------------------------------- USD


def define_volume_prim(stage, path: str, level: VolumeLevel, atlas_file: str, purpose: str | None = None,
                       vdb_file: str | None = None):
    """A UsdVol.Volume prim for one level: extent = the grid's box, and a
    field per channel group. With `vdb_file` (worldlib.volumes.vdb) the
    fields are OpenVDBAsset prims naming its grids density and albedo (the
    plain colour there, not premultiplied), which Blender, Houdini and
    Omniverse render. Without it: EXR atlases are no field format USD knows
    (UsdVol has OpenVDB and Field3D assets only), so the fields are
    Field3DAsset prims that name no file. Either way the atlas path, layout
    and voxel size sit in customData worldbake:atlas for importers that read
    the pseudo-volume layout."""
    from pxr import Gf, Vt, UsdVol

    vol = UsdVol.Volume.Define(stage, path)
    vol.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, level.origin)), Gf.Vec3f(*map(float, level.bbox_max))]))
    if purpose:
        vol.CreatePurposeAttr(purpose)
    nx, ny, nz = level.shape_xyz
    for name in ("density", "albedo") if vdb_file else ("density", "albedo", "normal"):
        if vdb_file:
            fld = UsdVol.OpenVDBAsset.Define(stage, f"{path}/{name}")
            fld.CreateFilePathAttr(vdb_file)
        else:
            fld = UsdVol.Field3DAsset.Define(stage, f"{path}/{name}")
        fld.CreateFieldNameAttr(name)
        fld.CreateFieldDataTypeAttr("float" if name == "density" else "float3")
        if vdb_file and name == "albedo":  # how Houdini and Omniverse read a vec3 grid
            fld.CreateVectorDataRoleHintAttr("Color")
        vol.CreateFieldRelationship(name, fld.GetPath())
    info = level.atlas_info()
    data = {"file": atlas_file, "grid": Vt.IntArray([nx, ny, nz]), "voxel_m": float(level.voxel_m),
            "channels": Vt.StringArray(list(CHANNELS)), "layout": info["layout"]}
    if "tiles" in info:
        data["tiles"] = Vt.IntArray(info["tiles"])
    vol.GetPrim().SetCustomDataByKey("worldbake:atlas", data)
    return vol


def define_mip_volumes(stage, path: str, chain: list[VolumeLevel], atlas_files: list[str], purpose: str | None = None,
                       vdb_files: list[str] | None = None):
    """At `path` (an existing prim) a `mip` variant set whose variant mip<k>
    holds the UsdVol.Volume `path`/Volume of level k (selection mip0)."""
    prim = stage.GetPrimAtPath(path)
    vset = prim.GetVariantSets().AddVariantSet("mip")
    for k, (lv, file) in enumerate(zip(chain, atlas_files)):
        vset.AddVariant(f"mip{k}")
        vset.SetVariantSelection(f"mip{k}")
        with vset.GetVariantEditContext():
            define_volume_prim(stage, f"{path}/Volume", lv, file, purpose, vdb_files[k] if vdb_files else None)
    vset.SetVariantSelection("mip0")
