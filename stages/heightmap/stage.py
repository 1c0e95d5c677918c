"""The heightmap stage: procedural terrain (fBm, ridged multifractal, domain
warp, fault formation) on the OpenCL device, or an imported DEM.

Cells are pixel-is-area: cell (row, col) samples x = (col + 0.5) dx,
z = (row + 0.5) dx metres with dx = size_m / resolution. Every length is in
metres, so the same config at 512^2 and 4096^2 gives the same landforms.
`window` bakes one tile of the world, bit-identical to the same crop of the
whole map.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
import pydantic

from pipeline.contract import (Artifact, Check, CheckContext, GridInfo, Param, ParamError, Params, ProjectPath, Relief,
                               ReportMap, RunContext, Stage)
from pipeline.errors import InputError, StageError
from pipeline.grid import Grid
from worldlib.terrain.hillshade import hillshade

from worldlib.terrain import dem

from . import noise


class HeightmapParams(Params):
    size_m: float = Param(8192.0, units="m", description="extent of the square world (east-west = north-south)", ge=1.0, le=1e6)
    resolution: int = Param(1024, units="cells", description="cells per side of the world grid", ge=2, le=16384)
    # a list, not a tuple: configs arrive as TOML arrays and are validated strictly
    window: Optional[pydantic.conlist(int, min_length=4, max_length=4)] = Param(
        None, units="cells",
        description="bake only this tile [col0, row0, cols, rows] of the world grid; bit-identical to the same crop of the whole map",
    )
    generator: Literal["fbm", "ridged", "warped", "fault", "dem"] = Param(
        "warped", description="fbm: fractal gradient noise; ridged: Musgrave ridged multifractal; warped: domain-warped "
        "fbm or ridged (warp_basis); fault: fault formation (seed 003) plus optional noise; dem: import dem_path",
    )
    tileable: bool = Param(
        False, description="seamless periodic tiling: each octave has a whole number of cycles over size_m (not with fault or dem)",
    )
    # fractal noise
    wavelength_m: float = Param(4096.0, units="m", description="wavelength of the first (largest) octave", gt=0.0, le=1e7)
    octaves: int = Param(
        10, units="", description="number of octaves; those shorter than two cells are skipped (they would only alias)", ge=1, le=16,
    )
    lacunarity: float = Param(2.0, units="", description="frequency ratio between successive octaves", ge=1.5, le=4.0)
    hurst: float = Param(
        1.0, units="", description="Hurst exponent H: octave amplitude ratio (gain) = lacunarity**-H; "
        "fbm's power spectrum falls as k**-(2H+2)", ge=0.0, le=1.0,
    )
    relief_m: float = Param(
        700.0, units="m", description="vertical scale: heights lie within base_m +- relief_m (fault: +- relief_m is three standard "
        "deviations of the fault sum); not used by dem", ge=0.0, le=1e5,
    )
    base_m: float = Param(800.0, units="m", description="height offset, the middle of the height range (not used by dem)", ge=-1e5, le=1e5)
    # domain warp
    warp_basis: Literal["fbm", "ridged"] = Param("ridged", description="the noise that the warped generator displaces")
    warp_strength_m: float = Param(
        400.0, units="m", description="warped: root-mean-square displacement of the domain warp", ge=0.0, le=1e6,
    )
    warp_wavelength_m: float = Param(6000.0, units="m", description="warped: wavelength of the warp field's first octave", gt=0.0, le=1e7)
    warp_octaves: int = Param(3, units="", description="warped: octaves of the warp field", ge=1, le=16)
    # ridged multifractal
    ridge_offset: float = Param(1.0, units="", description="ridged: Musgrave's offset (ridge sharpness); signal = (offset - |noise|)^2", ge=0.5, le=2.0)
    ridge_gain: float = Param(2.0, units="", description="ridged: Musgrave's gain; how strongly ridges suppress detail in valleys", ge=0.0, le=8.0)
    # fault formation
    fault_count: int = Param(256, units="", description="fault: number of fault lines", ge=1, le=20000)
    fault_softness_m: float = Param(200.0, units="m", description="fault: width of the smooth step across a fault line", gt=0.0, le=1e6)
    fault_delta_min_ratio: float = Param(
        0.1, units="", description="fault: last step height / first step height; steps decrease linearly "
        "delta_i = dmax - (dmax - dmin) i / n (seed 003)", ge=0.0, le=1.0,
    )
    fault_noise_fraction: float = Param(
        0.15, units="", description="fault: share of relief_m given to an fbm detail layer (the thesis adds Perlin noise)", ge=0.0, le=1.0,
    )
    # DEM import
    dem_path: Optional[ProjectPath] = Param(
        None, units="path", validate_default=True, description="dem: the DEM file (EXR, TIFF, 16-bit PNG; first channel), at its own cells when its cell size is known (dem_cell_size_m), else stretched over the square world",
    )
    dem_cell_size_m: Optional[float] = Param(
        None, units="m", description="dem: the DEM's cell size; the world is then the DEM's own cells (rows x cols, "
        "rectangular when the DEM is; resolution and size_m unused). Default: the cell size the file states "
        "(GeoTIFF pixel scale, EXR attribute worldbake:cell_size_m); a file stating none is stretched over the square world",
        gt=0.0, le=1e5,
    )
    dem_min_m: Optional[float] = Param(
        None, units="m", description="dem: height of the smallest integer value (or of 0.0 for a normalised float file)", ge=-1e5, le=1e5,
    )
    dem_max_m: Optional[float] = Param(
        None, units="m", validate_default=True, description="dem: height of the largest integer value (or of 1.0 for a normalised float file)", ge=-1e5, le=1e5,
    )

    # Cross-field checks are field validators (on the later field, reading the
    # earlier ones from info.data) so that each error names its key.
    @pydantic.field_validator("window")
    @classmethod
    def _window_inside(cls, v, info: pydantic.ValidationInfo):
        if v is not None:
            col0, row0, cols, rows = v
            if col0 < 0 or row0 < 0 or cols < 1 or rows < 1:
                raise ValueError(f"window [col0, row0, cols, rows] = {list(v)} needs col0, row0 >= 0 and cols, rows >= 1")
            res = info.data.get("resolution")
            if res is not None and (col0 + cols > res or row0 + rows > res):
                raise ValueError(f"window {list(v)} reaches past the {res}x{res} world grid")
        return v

    @pydantic.field_validator("tileable")
    @classmethod
    def _tileable_generator(cls, v, info: pydantic.ValidationInfo):
        gen = info.data.get("generator")
        if v and gen in ("fault", "dem"):
            why = "fault lines are not periodic" if gen == "fault" else "an imported DEM is not periodic"
            raise ValueError(f"tileable = true is not possible with generator = {gen!r}: {why}")
        return v

    @pydantic.field_validator("wavelength_m")
    @classmethod
    def _wavelength_resolved(cls, v, info: pydantic.ValidationInfo):
        size, res, gen = info.data.get("size_m"), info.data.get("resolution"), info.data.get("generator")
        if size is not None and res is not None and gen not in (None, "dem") and v < 2.0 * size / res:
            raise ValueError(f"wavelength_m = {v:g} is shorter than two cells ({2.0 * size / res:g} m): the map would be flat")
        return v

    @pydantic.field_validator("warp_strength_m")
    @classmethod
    def _warp_inside_world(cls, v, info: pydantic.ValidationInfo):
        size = info.data.get("size_m")
        if size is not None and v > size:
            raise ValueError(f"warp_strength_m = {v:g} is larger than the world (size_m = {size:g})")
        return v

    @pydantic.field_validator("dem_path", mode="after")
    @classmethod
    def _dem_needed(cls, v, info: pydantic.ValidationInfo):
        if info.data.get("generator") == "dem" and not v:
            raise ValueError("generator = 'dem' needs dem_path, the DEM file")
        return v

    @pydantic.field_validator("dem_max_m")
    @classmethod
    def _dem_range(cls, v, info: pydantic.ValidationInfo):
        lo = info.data.get("dem_min_m")
        if (lo is None) != (v is None) and "dem_min_m" in info.data:
            raise ValueError("give both dem_min_m and dem_max_m, or neither")
        if v is not None and lo is not None and not lo < v:
            raise ValueError(f"dem_max_m ({v:g}) must be above dem_min_m ({lo:g})")
        return v

    @property
    def cell_size_m(self) -> float:
        return self.size_m / self.resolution

    @property
    def tile(self) -> tuple[int, int, int, int]:
        return tuple(self.window) if self.window is not None else (0, 0, self.resolution, self.resolution)


def spec_from_params(p: HeightmapParams, seed: int) -> noise.TerrainSpec:
    """The kernel tables for a noise/fault generator."""
    return noise.make_spec(
        seed=seed, generator=p.generator, size_m=p.size_m, resolution=p.resolution, wavelength_m=p.wavelength_m,
        octaves=p.octaves, lacunarity=p.lacunarity, hurst=p.hurst, relief_m=p.relief_m, base_m=p.base_m,
        tileable=p.tileable, warp_strength_m=p.warp_strength_m, warp_wavelength_m=p.warp_wavelength_m,
        warp_octaves=p.warp_octaves, warp_basis=p.warp_basis, ridge_offset=p.ridge_offset, ridge_gain=p.ridge_gain,
        fault_count=p.fault_count, fault_softness_m=p.fault_softness_m,
        fault_delta_min_ratio=p.fault_delta_min_ratio, fault_noise_fraction=p.fault_noise_fraction,
    )


def heights(
    env, p: HeightmapParams, seed: int, local_size=None, progress=None, dem_file: Path | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """The float32 heights of the params' tile and diagnostics, the noise
    and fault generators run on the OpenCL device `env` (pipeline.opencl.CL;
    a DEM needs none: None). `dem_file` is the resolved dem_path (default:
    dem_path as given)."""
    tile = p.tile
    if p.generator == "dem":
        t0 = time.perf_counter()
        path = dem_file or p.dem_path
        cell = p.dem_cell_size_m or dem.dem_cell_size(path)
        if cell is not None:  # the DEM's own cells: the world is its rows x cols
            src = dem.read_dem(path, p.dem_min_m, p.dem_max_m, max_abs_m=dem.MAX_HEIGHT_M)
            dem.check_shape(path, src.shape[1], src.shape[0], own_cells=True)
            col0, row0, cols, rows = tile if p.window is not None else (0, 0, src.shape[1], src.shape[0])
            h = np.ascontiguousarray(src[row0:row0 + rows, col0:col0 + cols], np.float32)
            return h, {"dem_seconds": time.perf_counter() - t0, "dem_cell_size_m": float(cell),
                       "dem_shape": list(src.shape)}
        h = dem.load_dem(path, p.resolution, tile, p.dem_min_m, p.dem_max_m)
        return h, {"dem_seconds": time.perf_counter() - t0}
    spec = spec_from_params(p, seed)
    if env is None:
        raise ValueError(f"heightmap: the {p.generator} generator runs on an OpenCL device; none was handed in")
    vw = noise.vector_width(env.device)
    h, seconds = noise.bake(env, spec, tile, local_size=local_size, progress=progress, vw=vw)
    return h, {"kernel_seconds": seconds, "kernel_mcells_per_s": h.size / max(seconds, 1e-12) / 1e6,
               "opencl_vector_width": vw, **spec.info}


def run(ctx: RunContext, inputs: dict[str, Any], params: HeightmapParams) -> dict[str, Any]:
    ctx.progress(0.0, f"{params.generator} {params.tile[2]}x{params.tile[3]} cells")
    dem_file = ctx.resolve(params.dem_path) if params.dem_path else None
    h, info = heights(ctx.cl, params, ctx.seed, progress=lambda f, m: ctx.progress(0.9 * f, m), dem_file=dem_file)
    if not np.isfinite(h).all():
        raise StageError(f"heightmap: generator {params.generator!r} produced {int((~np.isfinite(h)).sum())} non-finite heights")
    col0, row0, _, _ = params.tile
    dx = info.get("dem_cell_size_m", params.cell_size_m)
    grid = Grid(h, cell_size_m=dx, channels=("height",), origin_m=(col0 * dx, row0 * dx))
    ctx.progress(0.9, "hillshade")
    shade = hillshade(grid)
    h64 = h.astype(np.float64)
    ctx.metrics.update(
        height_min_m=float(h64.min()), height_max_m=float(h64.max()), height_mean_m=float(h64.mean()),
        height_std_m=float(h64.std()), cells=int(h.size), cell_size_m=dx, **info,
    )
    ctx.progress(1.0, "done")
    return {"heightmap.height": grid, "heightmap.hillshade": shade}


def world_shape(params: HeightmapParams, project_root: Path) -> tuple[int, int]:
    """rows x cols of the whole world: the resolution's square, or a DEM's own cells."""
    if params.generator == "dem":
        path = project_root / params.dem_path
        if params.dem_cell_size_m or dem.dem_cell_size(path):
            return tuple(dem.scan_raster(path).shape)
    return params.resolution, params.resolution


def height_tile(tctx, inputs: dict[str, Any], params: HeightmapParams, shared: Any):
    """One world tile's heights and hillshade (pipeline.tiles): the heights
    of the tile and a one-cell halo (the hillshade's gradient), both
    bit-identical to the same cells of the whole map."""
    from pipeline.tiles import TileOutput

    r0, c0, rows, cols = tctx.tile.window(1)
    window = params.model_copy(update={"window": [c0, r0, cols, rows]})
    dem_file = tctx.project_root / params.dem_path if params.dem_path else None
    h, info = heights(tctx.cl, window, tctx.seed, dem_file=dem_file)
    if not np.isfinite(h).all():
        raise StageError(f"heightmap: generator {params.generator!r} produced {int((~np.isfinite(h)).sum())} "
                         f"non-finite heights in tile {tctx.tile.name}")
    dx = info.get("dem_cell_size_m", params.cell_size_m)
    inner = tctx.tile.inner(1)
    shade = hillshade(Grid(h, cell_size_m=dx, channels=("height",)))[inner]
    own = h[inner].astype(np.float64)
    # the generator's description, not how fast this run was: a tile's summary is content (its unit's JSON)
    info = {k: v for k, v in info.items() if isinstance(v, (int, float, str)) and not k.startswith(("kernel_", "dem_s"))}
    return TileOutput({"height": np.ascontiguousarray(h[inner]), "hillshade": shade},
                      {"min": float(own.min()), "max": float(own.max()), "sum": float(own.sum()),
                       "sum_sq": float(np.square(own).sum()), "cells": int(own.size), "cell_size_m": dx, "info": info})


def run_tiled(ctx: RunContext, inputs: dict[str, Any], params: HeightmapParams) -> dict[str, Any]:
    """run on a tiled world: each tile a task (height_tile); the same files."""
    if params.window is not None:  # one window of the world: not split further
        return run(ctx, inputs, params)
    shape = world_shape(params, ctx.project_root)
    ctx.progress(0.0, f"{params.generator} {shape[1]}x{shape[0]} cells in tiles of {ctx.tiles.tile_cells}")
    dx = params.cell_size_m
    if params.generator == "dem" and shape != (params.resolution, params.resolution):
        dx = float(params.dem_cell_size_m or dem.dem_cell_size(ctx.resolve(params.dem_path)))
    grids, parts = ctx.tiles.map(height_tile, "height", shape, {}, params,
                                 grids={"height": ("height",), "hillshade": ("r", "g", "b")}, cell_size_m=dx)
    cells = sum(p["cells"] for p in parts)
    mean = sum(p["sum"] for p in parts) / cells
    ctx.metrics.update(
        height_min_m=min(p["min"] for p in parts), height_max_m=max(p["max"] for p in parts), height_mean_m=mean,
        height_std_m=float(np.sqrt(max(0.0, sum(p["sum_sq"] for p in parts) / cells - mean * mean))), cells=cells,
        cell_size_m=dx, **parts[0]["info"])
    ctx.progress(1.0, "done")
    return {"heightmap.height": grids["height"], "heightmap.hillshade": grids["hillshade"]}


BYTES_PER_CELL = 48  # float32 height, float64 DEM resampling rows, hillshade RGB, the device band, the EXR write


def _held(rows: int, cols: int, tile_cells: int) -> tuple[int, int]:
    """The cells a run holds at once: the world, or a tile and its halo."""
    return (min(rows, tile_cells + 2), min(cols, tile_cells + 2)) if tile_cells else (rows, cols)


def _tiled(ctx: CheckContext) -> str:
    return f" (a tile of tiling.tile_cells = {ctx.tile_cells} and its halo)" if ctx.tile_cells else ""


def check(params: HeightmapParams, ctx: CheckContext) -> Check:
    """The grid it will write; an imported DEM checked now from its header
    and a bounded read (dem.scan_raster: its size, shape, cell size, NaN and
    the range of its heights), so a bad file is named before any stage runs."""
    res = params.resolution
    cols, rows = (params.window[2], params.window[3]) if params.window else (res, res)
    held = _held(rows, cols, ctx.tile_cells if params.window is None else 0)
    memory = BYTES_PER_CELL * held[0] * held[1]
    how = f"heightmap.resolution = {res}: {held[0]} x {held[1]} cells{_tiled(ctx)} x {BYTES_PER_CELL} B"
    grid = GridInfo((rows, cols), params.size_m / res, "heightmap.resolution")
    if params.generator == "dem":
        path = ctx.resolve(params.dem_path)
        try:
            src = dem.scan_raster(path)
            cell = params.dem_cell_size_m or dem.dem_cell_size(path)
            dem.check_shape(path, src.width, src.height, own_cells=cell is not None)
            dem.check_dem(path, params.dem_min_m, params.dem_max_m)
        except InputError as e:
            raise ParamError("dem_path", str(e)) from None
        if cell is not None:  # the world is the DEM's own cells
            if params.window is not None:
                c0, r0, cols, rows = params.window
                if c0 + cols > src.shape[1] or r0 + rows > src.shape[0]:
                    raise ParamError("window", f"window {list(params.window)} reaches past the DEM's "
                                               f"{src.shape[1]} x {src.shape[0]} cells")
            else:
                rows, cols = src.shape
            held = _held(rows, cols, ctx.tile_cells if params.window is None else 0)
            memory = BYTES_PER_CELL * held[0] * held[1]
            how = f"heightmap.dem_path: {held[0]} x {held[1]} cells{_tiled(ctx)} x {BYTES_PER_CELL} B"
            grid = GridInfo((rows, cols), float(cell), "heightmap.dem_path")
        memory += 16 * src.size
        how += f" + the DEM's {src.shape[1]} x {src.shape[0]} pixels x 16 B"
    return Check(memory_bytes=memory, memory_how=how, grids={"heightmap.height": grid})


STAGE = Stage(
    name="heightmap",
    version=1,
    description="Terrain heights: fBm, ridged multifractal, domain-warped noise or fault formation on the OpenCL "
    "device (seed 003), optionally seamlessly tileable, or an imported DEM",
    inputs=(),
    outputs=(
        Artifact(
            "heightmap.height", kind="grid", file="height.exr", channels=("height",), units="m",
            description="terrain height above the datum, float32, one value per cell (pixel-is-area)",
        ),
        Artifact(
            "heightmap.hillshade", kind="image", file="hillshade.png", shape="terrain", dtype="uint8",
            description="hillshade preview (sun from the north-west at 45 degrees), 8-bit RGB",
        ),
    ),
    params=HeightmapParams,
    run=run,
    run_tiled=run_tiled,
    check=check,
    report=(ReportMap("heightmap.height", "height", name="height", title="Height ({artifact})",
                      relief=Relief(hillshade, ("heightmap.height",), "height")),),
    source_dir=Path(__file__).resolve().parent,
    uses_seed=True,
    uses_opencl=True,
)
