"""The landscape stage: the ground as tiles a game engine imports, as Gaea and
World Machine write them for Unreal.

Per tile `<prefix>_x<col>_y<row>`: the height in float32 metres (EXR) and as
a 16-bit greyscale PNG over one range for the whole world (so tiles agree at
their borders), the range in the PNG's text chunks and in a JSON sidecar with
Unreal's import settings; per ground type an 8-bit weightmap
`<prefix>_<ground>_x<col>_y<row>.png` of the splat weights, the types of a
vertex summing to 255. Tiles are N vertices a side, N one of Unreal's landscape
sizes (quads per section x sections per component x components + 1), and by
default share their border row and column. The stage runs only when a config
asks for it (`outputs = [..., "landscape"]`).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
import pydantic

from pipeline.contract import Artifact, Check, CheckContext, Input, Param, ParamError, Params, RunContext, Stage
from worldlib.ground import GROUND_TYPES, SPLAT_CHANNELS
from worldlib.terrain import GROUND_SOURCES

from . import files, tiling

MAX_TILE_VERTICES = 8161  # Unreal's largest landscape side: 255 quads x 2 x 16 components + 1 (8129 recommended)
MAX_LATTICE_VERTICES = 2.0 ** 32  # vertices of all tiles together (65536^2): beyond, the cell is far finer than any use
BAND_VERTICES = 2 ** 18  # vertices sampled at once inside a tile (rows of a tile per band = this / N)


class LandscapeParams(Params):
    quads_per_section: Literal[7, 15, 31, 63, 127, 255] = Param(
        63, units="quads", description="Unreal's Section Size: quads per side of a landscape section")
    sections_per_component: Literal[1, 2] = Param(
        2, units="", description="Unreal's Sections Per Component: 1 (1x1) or 2 (2x2)")
    components_per_tile: int = Param(
        8, units="components", description="landscape components per tile side; a tile is quads_per_section x "
        "sections_per_component x components_per_tile + 1 vertices a side (63 x 2 x 8 + 1 = 1009)", ge=1, le=64)
    tile_vertices: Optional[int] = Param(
        None, units="vertices", description="vertices per tile side instead of components_per_tile: a multiple of "
        "quads_per_section x sections_per_component, plus 1 (Unreal recommends 127, 253, 505, 1009, 2017, 4033 "
        "with 63 quads per section, 8129 with 127)", ge=8, le=MAX_TILE_VERTICES)
    share_borders: bool = Param(
        True, description="neighbouring tiles share their border row and column of vertices (World Composition, Gaea, "
        "World Machine); false: tiles abut, tile x starting at vertex x N (Unreal 5's tiled Import from File)")
    cell_size_m: Optional[float] = Param(
        None, units="m", description="the landscape's vertex spacing (Unreal's X/Y scale / 100); default the world's "
        "cell, where the vertices are the world's cell centres exactly", gt=0.0, le=1e4)
    fit: Literal["pad", "resample"] = Param(
        "pad", description="pad: the lattice at cell_size_m, the last tiles reaching past the world padded by edge "
        "clamping; resample: the largest spacing at most cell_size_m whose tiles span the world exactly along its "
        "longer axis (the other padded by less than a tile)")
    prefix: str = Param(
        "landscape", description="the tiles' file name prefix: <prefix>_x<col>_y<row>.png", min_length=1,
        max_length=64, pattern=r"^[A-Za-z][A-Za-z0-9_-]*$")
    weightmaps: bool = Param(True, description="write one 8-bit weightmap per ground type from the splat weights")

    @pydantic.field_validator("tile_vertices")
    @classmethod
    def _tile_vertices_fit(cls, v, info: pydantic.ValidationInfo):
        q, s = info.data.get("quads_per_section"), info.data.get("sections_per_component")
        if v is not None and q is not None and s is not None and (v - 1) % (q * s):
            sizes = ", ".join(str(q * s * k + 1) for k in (1, 2, 4, 8, 16, 32, 64) if q * s * k + 1 <= MAX_TILE_VERTICES)
            raise ValueError(f"{v} vertices is not a whole number of components of {q} quads x {s}x{s} sections "
                             f"({q * s} quads) plus 1: take one of {sizes}, or change quads_per_section / "
                             "sections_per_component")
        return v

    @property
    def vertices(self) -> int:
        """Vertices per tile side."""
        if self.tile_vertices is not None:
            return self.tile_vertices
        return self.quads_per_section * self.sections_per_component * self.components_per_tile + 1


def _layout(params: LandscapeParams, shape, cell_m: float, origin_m=(0.0, 0.0)) -> tiling.Layout:
    return tiling.plan_layout(tuple(shape), cell_m, origin_m, params.vertices, params.share_borders,
                              params.cell_size_m, params.fit)


def check(params: LandscapeParams, ctx: CheckContext) -> Check:
    """The tiling from the ground's size: a tile larger than Unreal takes, or a
    lattice beyond 2^32 vertices, is refused; memory is the input maps the
    engine hands over (height and six splat weights, float32) and one tile."""
    n = params.vertices
    if n > MAX_TILE_VERTICES:
        raise ParamError("components_per_tile", f"a tile of {n} vertices is larger than Unreal's largest landscape "
                         f"({MAX_TILE_VERTICES} vertices a side); lower components_per_tile")
    ground = ctx.inputs.get("ground")
    if ground is None:
        return Check()
    layout = _layout(params, ground.shape, ground.cell_size_m)
    cols, rows = layout.lattice
    if cols * rows > MAX_LATTICE_VERTICES:
        raise ParamError("cell_size_m", f"the landscape would be {cols} x {rows} vertices at {layout.cell_m:g} m "
                         f"(more than 2^32); raise cell_size_m (the world's cell is {ground.cell_size_m:g} m)")
    cells = ground.shape[0] * ground.shape[1]
    band = min(n, max(1, BAND_VERTICES // n)) * n
    held = f"the ground and splat {ground.shape[0]} x {ground.shape[1]} cells x 32 B"
    if ctx.tile_cells:  # run_tiled: the windows of a band (at the world's cell, a band's cells) and a world tile
        cells = min(cells, band + (ctx.tile_cells + 2) ** 2)
        held = f"windows of {cells:,} cells x 32 B"
    memory = 32 * cells + 16 * n * n + 400 * band
    layers = 1 + (len(GROUND_TYPES) if params.weightmaps else 0)
    return Check(memory_bytes=memory,
                 memory_how=f"{held} + a tile of "
                 f"{n}^2 vertices x 16 B + a band of {band:,} vertices x 400 B",
                 work=float(cols * rows * layers), work_unit="vertices", work_limit=0.0,
                 work_how=f"{layout.tiles[0]} x {layout.tiles[1]} tiles of {n}^2 vertices, {layers} maps each")


def _height_text(lo: float, hi: float, span: float, key: str) -> dict[str, str]:
    """The PNG's text chunks: the range, and how to decode a value."""
    return {"worldbake:height_min_m": repr(lo), "worldbake:height_max_m": repr(hi),
            "worldbake:height_range_m": repr(span), "worldbake:key": key,
            "ImageDescription": f"height in metres = {lo!r} + value / 65535 * {span!r}"}


def _write_tile(ctx: RunContext, params: LandscapeParams, layout: tiling.Layout, h: np.ndarray,
                splat: np.ndarray | None, col: int, row: int, rng: tuple[float, float, float]) -> dict:
    """One tile's files, sampled band by band of vertex rows; its sidecar entry."""
    lo, hi, span = rng
    n, name = layout.vertices, files.tile_name(params.prefix, col, row)
    heights = np.empty((n, n), np.float32)
    weights = np.empty((n, n, len(GROUND_TYPES)), np.uint8) if splat is not None else None
    step = max(1, BAND_VERTICES // n)
    for r0 in range(0, n, step):
        band = slice(r0, min(n, r0 + step))
        heights[band] = tiling.sample_tile(h, layout, col, row, band)
        if weights is not None:
            weights[band] = tiling.quantise_weights(tiling.sample_tile(splat, layout, col, row, band))
    values = tiling.quantise_heights(heights, lo, span)
    first = layout.tile_origin(col, row)
    files.write_height_exr(ctx.out_dir / files.DATA_DIR / f"{name}.exr", heights, layout.cell_m, first, ctx.provenance)
    files.write_height_png(ctx.out_dir / files.UNREAL_DIR / f"{name}.png", values, _height_text(lo, hi, span, ctx.key))
    maps = {}
    if weights is not None:
        for k, ground in enumerate(GROUND_TYPES):
            wname = files.tile_name(params.prefix, col, row, ground)
            files.write_weight_png(ctx.out_dir / files.UNREAL_DIR / f"{wname}.png", weights[..., k],
                                   {"worldbake:ground_type": ground, "worldbake:key": ctx.key})
            maps[ground] = f"{files.UNREAL_DIR}/{wname}.png"
    err = float(np.abs(tiling.decode_heights(values, lo, span) - heights.astype(np.float64)).max())
    entry = {
        "tile": [col, row], "name": name,
        "height_exr": f"{files.DATA_DIR}/{name}.exr", "height_png": f"{files.UNREAL_DIR}/{name}.png",
        "sidecar": f"{files.DATA_DIR}/{name}.json", "weightmaps": maps,
        "vertices": [n, n], "first_vertex": [col * layout.stride, row * layout.stride],
        "first_vertex_m": list(first), "cell_size_m": layout.cell_m,
        "valid_vertices": list(layout.tile_valid(col, row)),
        "height_min_m": lo, "height_max_m": hi, "height_range_m": span, "height_step_m": span / tiling.PNG_MAX,
        "decode": "height_m = height_min_m + value / 65535 * height_range_m",
        "tile_height_min_m": float(heights.min()), "tile_height_max_m": float(heights.max()),
        "quantisation_error_m": err,
        "unreal": tiling.unreal_settings(layout, col, row, lo, span, params.quads_per_section,
                                         params.sections_per_component),
    }
    files.write_sidecar(ctx.out_dir / entry["sidecar"], entry)
    return entry


def _splat(inputs: dict[str, Any]) -> np.ndarray | None:
    """The splat weights (rows, cols, k) in GROUND_TYPES order (a view when the grid holds them so)."""
    grid = inputs.get("splat")
    if grid is None:
        return None
    order = [list(grid.channels).index(c) for c in SPLAT_CHANNELS]
    return grid.data if order == list(range(grid.data.shape[2])) else grid.data[..., order]


def run(ctx: RunContext, inputs: dict[str, Any], params: LandscapeParams) -> dict[str, Any]:
    t0 = time.perf_counter()
    ground = inputs["ground"]
    h = ground.data
    finite = np.isfinite(h)
    nodata = int(h.size - np.count_nonzero(finite))
    lo, hi = float(np.min(h, where=finite, initial=np.inf)), float(np.max(h, where=finite, initial=-np.inf))
    if nodata:  # cells without data (an imported DEM's holes) stand at the lowest height: Unreal has no holes
        h = np.where(finite, h, np.float32(lo))
    del finite
    splat = _splat(inputs) if params.weightmaps else None
    return _write_tiles(ctx, params, ground, h, splat, (lo, hi), nodata, t0)


class _Window:
    """A grid input sliced like an array (grid[r0:r1, c0:c1]) but read by
    window from its file (pipeline.tiles.GridFile): the channels in `order`,
    no-data cells at `fill` (what run does to the whole array)."""

    def __init__(self, source, channels: tuple[str, ...] | None = None, fill: float | None = None):
        self.source, self.fill = source, fill
        self.order = None if channels is None else [list(source.channels).index(c) for c in channels]
        self.shape = tuple(source.shape) + (() if channels is None else (len(channels),))
        self.ndim = len(self.shape)

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rs, cs = key
        data = self.source.read(rs.start, cs.start, rs.stop - rs.start, cs.stop - cs.start)
        if self.order is not None:
            return data[..., self.order]
        if data.ndim == 3:
            data = data[..., 0]
        return np.where(np.isfinite(data), data, np.float32(self.fill)) if self.fill is not None else data


def height_range(tctx, inputs: dict[str, Any], params: LandscapeParams, shared: Any):
    """One world tile's lowest and highest finite height and its no-data cells."""
    from pipeline.tiles import TileOutput

    ground = inputs["ground"]
    h = ground.read_tile(tctx.tile, channel=ground.channels[0])
    finite = np.isfinite(h)
    return TileOutput({}, {"lo": float(np.min(h, where=finite, initial=np.inf)),
                           "hi": float(np.max(h, where=finite, initial=-np.inf)),
                           "nodata": int(h.size - np.count_nonzero(finite))})


def run_tiled(ctx: RunContext, inputs: dict[str, Any], params: LandscapeParams) -> dict[str, Any]:
    """run on a tiled world: the height range reduced over world tiles, then
    each landscape tile sampled from the windows of the inputs it covers."""
    t0 = time.perf_counter()
    ground = inputs["ground"]
    _, parts = ctx.tiles.map(height_range, "range", ground.shape, {"ground": ground}, params)
    lo, hi = min(p["lo"] for p in parts), max(p["hi"] for p in parts)
    nodata = sum(p["nodata"] for p in parts)
    h = _Window(ground, fill=lo if nodata else None)
    splat = _Window(inputs["splat"], SPLAT_CHANNELS) if params.weightmaps and "splat" in inputs else None
    return _write_tiles(ctx, params, ground, h, splat, (lo, hi), nodata, t0)


def _write_tiles(ctx: RunContext, params: LandscapeParams, ground, h, splat, height: tuple[float, float],
                 nodata: int, t0: float) -> dict[str, Any]:
    """Every landscape tile's files and the index, from the heights h and
    splat weights (arrays, or _Window) over the height range."""
    lo, hi = height
    span = hi - lo if hi > lo else 1.0  # a flat world: all 0 over a 1 m range
    layout = _layout(params, ground.shape, ground.cell_size_m, ground.origin_m)
    for sub in (files.UNREAL_DIR, files.DATA_DIR):
        (ctx.out_dir / sub).mkdir()
    tiles, count = [], layout.tiles[0] * layout.tiles[1]
    for row in range(layout.tiles[1]):
        for col in range(layout.tiles[0]):
            ctx.progress(len(tiles) / count, f"tile x{col} y{row} of {layout.tiles[0]} x {layout.tiles[1]}")
            entry = _write_tile(ctx, params, layout, h, splat, col, row, (lo, hi, span))
            tiles.append({k: entry[k] for k in ("tile", "name", "height_exr", "height_png", "sidecar", "weightmaps",
                                                "first_vertex_m", "valid_vertices", "quantisation_error_m")})
    cols, rows = layout.lattice
    ctx.metrics.update(
        tiles=count, tiles_x=layout.tiles[0], tiles_y=layout.tiles[1], tile_vertices=layout.vertices,
        lattice_vertices=[cols, rows], cell_size_m=layout.cell_m, height_min_m=lo, height_max_m=hi,
        padded_share=1.0 - layout.valid[0] * layout.valid[1] / (cols * rows), nodata_cells=nodata,
        quantisation_error_max_m=max(t["quantisation_error_m"] for t in tiles), seconds=time.perf_counter() - t0)
    ctx.progress(1.0, "done")
    return {"landscape.tiles": _index(params, layout, (lo, hi, span), tiles, splat is not None)}


def _index(params: LandscapeParams, layout: tiling.Layout, rng, tiles: list, weights: bool) -> dict:
    """landscape.json: the tiling, the range, Unreal's settings for the whole landscape and every tile's files."""
    lo, hi, span = rng
    cols, rows = layout.lattice
    return {
        "prefix": params.prefix, "tile_vertices": layout.vertices, "tiles": [layout.tiles[0], layout.tiles[1]],
        "share_borders": params.share_borders, "fit": params.fit, "cell_size_m": layout.cell_m,
        "world_cell_size_m": layout.world_cell_m, "world_cells": [layout.world_shape[1], layout.world_shape[0]],
        "lattice_vertices": [cols, rows], "valid_vertices": list(layout.valid),
        "padding": "vertices past valid_vertices repeat the world's edge (edge clamping)",
        "first_vertex_m": list(layout.origin_m),
        "height_min_m": lo, "height_max_m": hi, "height_range_m": span, "height_step_m": span / tiling.PNG_MAX,
        "decode": "height_m = height_min_m + value / 65535 * height_range_m",
        "ground_types": list(GROUND_TYPES) if weights else [],
        "unreal": {**tiling.unreal_settings(layout, 0, 0, lo, span, params.quads_per_section,
                                            params.sections_per_component),
                   "landscape_resolution": [cols, rows],
                   "landscape_components": [(cols - 1) // (params.quads_per_section * params.sections_per_component),
                                            (rows - 1) // (params.quads_per_section * params.sections_per_component)],
                   "heightmap_file": f"{files.UNREAL_DIR}/{files.tile_name(params.prefix, 0, 0)}.png",
                   "layer_files": {g: f"{files.UNREAL_DIR}/{files.tile_name(params.prefix, 0, 0, g)}.png"
                                   for g in (GROUND_TYPES if weights else ())}},
        "tile_list": tiles,
    }


STAGE = Stage(
    name="landscape",
    version=1,
    description="Landscape tiles for game engines (Unreal's sizes, as Gaea and World Machine write them): per tile "
    "a float height EXR, a 16-bit PNG over the world's height range with a JSON sidecar, and a weightmap per ground type",
    inputs=(
        Input("ground", one_of=GROUND_SOURCES, channels=("height",), units="m",
              description="the ground: the final terrain with the river beds carved"),
        Input("splat", one_of=("vegetation.splat",), optional=True, channels=SPLAT_CHANNELS, units="1",
              description="the splat weights of the ground types, one weightmap each"),
    ),
    outputs=(
        Artifact("landscape.tiles", kind="json", file="landscape.json", shape="any",
                 beside=("unreal/*.png", "data/*.exr", "data/*.json"),
                 description="the index of the tiles (range, Unreal settings, every tile's files); beside it unreal/ "
                 "(what Unreal imports: <prefix>_x<col>_y<row>.png 16-bit heights, <prefix>_<ground>_x<col>_y<row>.png "
                 "8-bit weightmaps) and data/ (<prefix>_x<col>_y<row>.exr float32 metres and .json sidecars)"),
    ),
    params=LandscapeParams,
    run=run,
    run_tiled=run_tiled,
    check=check,
    source_dir=Path(__file__).resolve().parent,
)
