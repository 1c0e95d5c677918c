"""The stage on a tiled world (pipeline.tiles): every fine cell's work per
tile, the processes that span the world on their own coarse grids in the
stage's process, every map bitwise the untiled run's (stage.run; the steps
both share are in steps.py).

1. Block means (tile by tile) of the heights feed geological time on its
   own grid (geological_cell_m): one solve over 1/f^2 of the cells, its
   change a Prolongation each tile evaluates on its own cells.
2. The talus rule on the fine cells in rounds of THERMAL_ROUND iterations:
   a tile runs them on its cells and a halo of 2 cells per iteration (an
   iteration reads the neighbours' send factors, which read theirs), read
   from the round before; the halo's outer cells go wrong, never the
   tile's. The device kernels give a cell the same bits whatever the grid
   around it (kernels.cl), so the tile's cells are the whole run's.
3. The storm on its own grid (storm_cell_m): the block means of the
   weathered heights, tile by tile; one run in the stage's process.
4. The maps per tile from a one-cell halo (hillshade, slope pairs); the
   metrics reduced from the tiles' sums.

A world whose geology or storm would run on its fine cells, or whose blocks
do not fit its tiles, or with periodic edges, runs whole (the reason in the
metrics): those solves span every cell.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import StageError
from pipeline.grid import Grid
from pipeline.tiles import TileOutput
from worldlib.terrain.hillshade import hillshade

from . import steps as st
from .params import physics_for, plan_for

THERMAL_ROUND = 32  # talus-rule iterations per round: a halo of 64 cells (1.27x the cells of a 1024 tile)


def whole_reason(params, shape: tuple[int, int], dx: float, tile_cells: int) -> str | None:
    """Why this run cannot go per tile (it runs whole), or None."""
    from .coarse_grid import coarse_factor

    if params.boundary == "periodic":
        return "periodic edges wrap every tile's halo around the world"
    if params.geological_years > 0:
        fg = coarse_factor(*shape, dx, params.geological_cell_m)
        if fg == 1:
            return "geological time runs on the terrain's own cells (set geological_cell_m above the cell size)"
        if tile_cells % fg:
            return f"geological blocks of {fg} cells do not divide tiling.tile_cells = {tile_cells}"
    fs = coarse_factor(*shape, dx, params.storm_cell_m)
    if params.storm_hours > 0 and fs == 1:
        return "the storm runs on the terrain's own cells (set storm_cell_m above the cell size)"
    if fs > 1 and tile_cells % fs:
        return f"storm blocks of {fs} cells do not divide tiling.tile_cells = {tile_cells}"
    return None


def run(ctx, src, params, progress) -> tuple[dict[str, Any], dict[str, Any]]:
    """The tiled run of stage.run on the input heights `src` (a GridFile):
    the outputs as TileArrays, and the metrics."""
    from .coarse_grid import coarse_factor

    t_start = time.perf_counter()
    shape, dx = tuple(src.shape), float(src.cell_size_m)
    tiles, T = ctx.tiles, ctx.tiles.tile_cells
    ph = physics_for(params, dx)
    plan = plan_for(params, dx, ph)
    fg = coarse_factor(*shape, dx, params.geological_cell_m) if params.geological_years > 0 else 0
    fs = coarse_factor(*shape, dx, params.storm_cell_m)
    inputs = {"height": src}
    metrics: dict[str, Any] = {}

    progress(0.0, f"erosion {shape[1]}x{shape[0]} cells of {dx:g} m in tiles of {T}")
    _, parts = tiles.map(prepare_tile, "prepare", shape, inputs, params, fg)
    bad = [p for p in parts if p["error"]]
    if bad:
        raise StageError(bad[0]["error"])
    geology = None
    if fg:
        coarse = _assemble(tiles.tiles(shape), parts, "block_mean", fg)
        res = st.solve_geology(ctx.cl, coarse, dx * fg, params, lambda f, m: progress(0.4 * f, m))
        geology = st.FineGeology.of(res.height, coarse, fg, params, dx)
        del coarse, res.height
        metrics.update(res.stats, geological_cell_factor=fg, geological_detail_kept=geology.keep)

    # the talus rule in rounds, each reading the round before's change from a halo
    t0 = time.perf_counter()
    n_th, change = plan.thermal_iterations, None
    last_round = (n_th - 1) // THERMAL_ROUND * THERMAL_ROUND if n_th else 0
    # a resumed run whose last round is in the store takes it from there (the rounds before are not kept)
    done = last_round if n_th and tiles.kept(f"thermal{last_round}", shape) else 0
    idle = 0  # tile rounds in which no slope was above the talus angle
    while done < n_th:
        k = min(THERMAL_ROUND, n_th - done)
        last = done + k == n_th
        shared = {t.name: {"geology": _part(geology, t, 2 * k), "iterations": k, "cfrac": plan.thermal_c}
                  for t in tiles.tiles(shape)}
        grids, parts = tiles.map(thermal_tile, f"thermal{done}", shape, {**inputs, "change": change}, params,
                                 per_tile=shared, grids={"change": ("change",)}, cell_size_m=dx, keep=last)
        nonfinite = sum(p["nonfinite"] for p in parts)
        idle += sum(p["idle"] for p in parts)
        if nonfinite:
            raise StageError(f"erosion: thermal weathering blew up at iteration {done + k} (talus_angle_deg): "
                             f"{nonfinite} non-finite cells")
        _drop(change, tiles.work)
        change, done = grids["change"], done + k
        progress(0.4 + 0.2 * done / n_th, f"thermal weathering {done}/{n_th}")
    metrics.update(thermal_iterations=n_th, thermal_c=plan.thermal_c, thermal_seconds=time.perf_counter() - t0,
                   thermal_rounds=-(-n_th // THERMAL_ROUND), thermal_idle_tile_rounds=idle)

    storm = None
    if fs > 1:
        per_tile = {t.name: {"geology": _part(geology, t, 0)} for t in tiles.tiles(shape)}
        _, parts = tiles.map(storm_input_tile, "storm_input", shape, {**inputs, "change": change}, params,
                             per_tile=per_tile, keep=False)
        coarse_h = _assemble(tiles.tiles(shape), parts, "block_mean", fs)
        simc, fc, storm_metrics = st.coarse_storm(ctx.cl, coarse_h, params, dx * fs,
                                                  lambda f, m: progress(0.6 + 0.3 * f, m))
        del coarse_h
        storm = st.storm_fields(fc, fs)
        del fc
        metrics.update({k: v for k, v in storm_metrics.items() if k not in st.THERMAL_METRICS}, storm_cell_factor=fs, storm_cell_size_m=dx * fs,
                       opencl_storm_tile=[simc.nr, simc.tile_vectors], opencl_storm_avx512=simc.avx512)
        simc.finish()
        del simc

    per_tile = {t.name: {"geology": _part(geology, t, 1), "storm": _parts(storm, t, 1)} for t in tiles.tiles(shape)}
    grids, parts = tiles.map(maps_tile, "maps", shape, {**inputs, "change": change}, params, per_tile=per_tile,
                             grids={**{name: chans for name, chans in st.CHANNELS.items()},
                                    "hillshade": ("r", "g", "b")},
                             cell_size_m=dx, origin_m=src.origin_m)
    _drop(change, tiles.work)
    bad = [p for p in parts if p["error"]]
    if bad:
        raise StageError(bad[0]["error"].format(steps=metrics.get("steps", 0)))
    if n_th:
        moved = sum(p["thermal_abs_sum"] for p in parts)
        metrics["thermal_mass_residual_rel"] = abs(sum(p["thermal_sum"] for p in parts)) / max(moved, 1e-30)
    sums = {k: sum(p["sums"][k] for p in parts) for k in ("cells", "wear_sum", "deposition_sum", "water_sum",
                                                        "wet_cells")}
    sums.update(change_min=min(p["sums"]["change_min"] for p in parts),
                change_max=max(p["sums"]["change_max"] for p in parts))
    after = st.slope_excess_of(*[p["after_thermal"] for p in parts]) if n_th else {}
    final = st.slope_excess_of(*[p["final"] for p in parts])
    metrics.update(st.final_metrics(sums, after, final, dx))
    metrics["total_seconds"] = time.perf_counter() - t_start
    outputs = {f"erosion.{name}": grids[name] for name in st.CHANNELS}
    outputs["erosion.hillshade"] = grids["hillshade"]
    return outputs, metrics


def _assemble(tiles, parts: list[dict], key: str, f: int) -> np.ndarray:
    """The coarse map from the tiles' block means (each tile's blocks its own)."""
    rows = sum(p[key].shape[0] for t, p in zip(tiles, parts) if t.col == 0)
    cols = sum(p[key].shape[1] for t, p in zip(tiles, parts) if t.row == 0)
    out = np.empty((rows, cols))
    for t, p in zip(tiles, parts):
        out[t.row0 // f:t.row0 // f + p[key].shape[0], t.col0 // f:t.col0 // f + p[key].shape[1]] = p[key]
    return out


def _part(pro, tile, halo: int):
    """The coarse data of a Prolongation (or FineGeology) the tile's window(halo) reads (None: none)."""
    return None if pro is None else pro.part(*tile.window(halo))


def _parts(pros: dict | None, tile, halo: int) -> dict | None:
    return None if pros is None else {k: _part(p, tile, halo) for k, p in pros.items()}


def _drop(arrays, work: Path) -> None:
    """Delete a finished round's tile files from the run's work folder (a
    round not kept as units: only the next one reads them)."""
    if arrays is None:
        return
    for path in arrays.files.values():
        if Path(path).resolve().is_relative_to(Path(work).resolve()):
            Path(path).unlink(missing_ok=True)


def _heights(tctx, inputs: dict[str, Any], geology, halo: int) -> tuple[tuple[int, int, int, int], np.ndarray]:
    """The tile's window(halo) and its heights after geological time (float32), cell by cell as steps.geology."""
    window = tctx.tile.window(halo)
    h = np.asarray(inputs["height"].read(*window, channel=inputs["height"].channels[0]), np.float32)
    if geology is not None:
        h = geology.heights(h, window)
    return window, h


def prepare_tile(tctx, inputs: dict[str, Any], params, fg: int) -> TileOutput:
    """The input checks of steps.check_input on the tile, and its block means for geology."""
    from .coarse_grid import block_mean

    src = inputs["height"]
    h = np.asarray(src.read_tile(tctx.tile, channel=src.channels[0]), np.float32)
    summary: dict[str, Any] = {"error": ""}
    bad = ~np.isfinite(h)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        summary["error"] = (f"erosion: the input height has {int(bad.sum())} NaN or infinite cells in tile "
                            f"{tctx.tile.name} (first at row {tctx.tile.row0 + r}, column {tctx.tile.col0 + c}); "
                            f"fix the heightmap before eroding it")
    elif float(np.max(np.abs(h))) > 1e6:
        summary["error"] = (f"erosion: input heights reach {float(np.max(np.abs(h))):.3g} m; heights beyond 1e6 m "
                            f"are not terrain (wrong units?)")
    elif fg:
        summary["block_mean"] = block_mean(h, fg)
    return TileOutput({}, summary)


def thermal_tile(tctx, inputs: dict[str, Any], params, shared: dict) -> TileOutput:
    """`iterations` of the talus rule on the tile and a halo of 2 cells per
    iteration, from the change of the round before (none: the first)."""
    from .device import DeviceSim
    from .physics import talus_thresholds

    k = shared["iterations"]
    window, h = _heights(tctx, inputs, shared["geology"], 2 * k)
    before = inputs["change"]
    dT = np.zeros_like(h) if before is None else np.asarray(before.read(*window), np.float32)
    ph = physics_for(params, inputs["height"].cell_size_m)
    if not _any_above_talus(h, dT, *talus_thresholds(ph)):
        # no cell sends: every iteration adds 0 to dT, which keeps its bits (dT is never -0)
        out = dT[tctx.tile.inner(2 * k)]
        return TileOutput({"change": np.ascontiguousarray(out)}, {"nonfinite": int((~np.isfinite(out)).sum()),
                                                                  "idle": True})
    sim = DeviceSim(tctx.cl, h, ph, change=dT, thermal_only=True)
    sim.thermal(k, cfrac=shared["cfrac"])
    out = sim.change()[tctx.tile.inner(2 * k)]
    sim.finish()
    return TileOutput({"change": np.ascontiguousarray(out)}, {"nonfinite": int((~np.isfinite(out)).sum()),
                                                              "idle": False})


def _any_above_talus(Tb: np.ndarray, dT: np.ndarray, t_ax: np.float32, t_dg: np.float32) -> bool:
    """Whether any pair of neighbours differs by more than the talus rule's
    threshold, as its kernels test it (float32 heights Tb + dT, d > t)."""
    h = (Tb + dT).astype(np.float32)
    for a, b, t in ((h[:, 1:], h[:, :-1], t_ax), (h[1:], h[:-1], t_ax), (h[1:, 1:], h[:-1, :-1], t_dg),
                    (h[1:, :-1], h[:-1, 1:], t_dg)):
        if (np.abs(a - b) > t).any():
            return True
    return False


def storm_input_tile(tctx, inputs: dict[str, Any], params, shared: dict) -> TileOutput:
    """The tile's block means of the weathered heights: the storm's grid."""
    from .coarse_grid import coarse_factor, block_mean

    src = inputs["height"]
    _, h = _heights(tctx, inputs, shared["geology"], 0)
    dT = _thermal_change(inputs, tctx.tile.window(0), h)
    fs = coarse_factor(*src.shape, src.cell_size_m, params.storm_cell_m)
    return TileOutput({}, {"block_mean": block_mean(h + dT.astype(np.float64), fs)})


def _thermal_change(inputs: dict[str, Any], window, h: np.ndarray) -> np.ndarray:
    before = inputs["change"]
    return np.zeros_like(h) if before is None else np.asarray(before.read(*window), np.float32)


def maps_tile(tctx, inputs: dict[str, Any], params, shared: dict) -> TileOutput:
    """The tile's output maps (steps.output_maps) and hillshade from its
    cells and a one-cell halo; its sums and slope pairs for the metrics."""

    src = inputs["height"]
    dx = float(src.cell_size_m)
    window, h = _heights(tctx, inputs, shared["geology"], 1)
    h_in = np.asarray(src.read(*window, channel=src.channels[0]), np.float32)
    dT = _thermal_change(inputs, window, h)
    inner = tctx.tile.inner(1)
    summary: dict[str, Any] = {"error": "", "thermal_sum": float(dT[inner].astype(np.float64).sum()),
                               "thermal_abs_sum": float(np.abs(dT[inner].astype(np.float64)).sum()),
                               "after_thermal": st.slope_excess_counts(h + dT, inner, dx, params.talus_angle_deg)}
    if shared["storm"] is not None:
        f = st.fine_fields(shared["storm"], dT, window)
    else:  # no storm: the fine simulator's fields after the talus rule alone
        zeros = np.zeros_like(h)
        f = {"dT": dT, "W": zeros, "S": zeros, "vx": zeros, "vz": zeros, "M": zeros}
    height = (h + f["dT"]).astype(np.float32)
    for name, arr in (("height", height), ("water", f["W"]), ("sediment", f["S"])):
        if not np.isfinite(arr[inner]).all():
            summary["error"] = f"erosion: non-finite {name} in the final state (step {{steps}})"
    maps = st.output_maps(h_in, height, f)
    shade = hillshade(Grid(maps["height"], cell_size_m=dx, channels=("height",)))
    own = {name: np.ascontiguousarray(a[inner]) for name, a in maps.items()}
    summary.update(sums=st.map_sums(own, params.wet_depth_m),
                   final=st.slope_excess_counts(maps["height"], inner, dx, params.talus_angle_deg))
    return TileOutput({**own, "hillshade": np.ascontiguousarray(shade[inner])}, summary)
