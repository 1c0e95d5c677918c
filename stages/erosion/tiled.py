"""The stage on a tiled world (pipeline.tiles): every fine cell's work per
tile, the processes that span the world on their own coarse grids in the
stage's process, every map bitwise the untiled run's (stage.run; the steps
both share are in steps.py).

1. Block means (tile by tile) of the heights feed geological time on its
   own grid (geological_cell_m): one solve over 1/f^2 of the cells, its
   result (steps.FineGeology) evaluated once per tile on the tile's cells,
   the heights every later pass reads.
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
    from worldlib.terrain.blocks import coarse_factor

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
    t_start = time.perf_counter()
    shape, dx = tuple(src.shape), float(src.cell_size_m)
    progress(0.0, f"erosion {shape[1]}x{shape[0]} cells of {dx:g} m in tiles of {ctx.tiles.tile_cells}")
    metrics: dict[str, Any] = {}
    heights = _geology(ctx, src, params, progress, metrics)
    inputs = {"height": src, "heights": heights}
    change = _talus_rounds(ctx.tiles, inputs, params, metrics, progress)
    inputs["change"] = change
    storm = _storm(ctx, inputs, params, progress, metrics)
    # each tile gets the few coarse cells of the storm's state its window reads, not the whole grid
    per_tile = {t.name: storm and {k: p.part(*t.window(1)) for k, p in storm.items()} for t in ctx.tiles.tiles(shape)}
    grids, parts = ctx.tiles.map(maps_tile, "maps", shape, inputs, params, per_tile=per_tile,
                                 grids={**st.CHANNELS, "hillshade": ("r", "g", "b")},
                                 cell_size_m=dx, origin_m=src.origin_m)
    ctx.tiles.discard(change)
    bad = [p for p in parts if p["error"]]
    if bad:
        raise StageError(bad[0]["error"].format(steps=metrics.get("steps", 0)))
    metrics.update(_map_metrics(parts, metrics["thermal_iterations"], dx), total_seconds=time.perf_counter() - t_start)
    outputs = {f"erosion.{name}": grids[name] for name in st.CHANNELS}
    outputs["erosion.hillshade"] = grids["hillshade"]
    return outputs, metrics


def _geology(ctx, src, params, progress, metrics: dict):
    """The input checked per tile, then geological time on its own grid from
    the tiles' block means; the heights after it (TileArrays, each tile's
    own cells, steps.FineGeology), or the input's when there is none."""
    from worldlib.terrain.blocks import coarse_factor

    tiles, shape, dx = ctx.tiles, tuple(src.shape), float(src.cell_size_m)
    fg = coarse_factor(*shape, dx, params.geological_cell_m) if params.geological_years > 0 else 0
    _, parts = tiles.map(prepare_tile, "prepare", shape, {"height": src}, params, fg)
    bad = [p for p in parts if p["error"]]
    if bad:
        raise StageError(bad[0]["error"])
    if not fg:
        return src
    coarse = _assemble(tiles.tiles(shape), parts, "block_mean", fg)
    res = st.solve_geology(ctx.cl, coarse, dx * fg, params, lambda f, m: progress(0.4 * f, m))
    geology = st.FineGeology.of(res.height, coarse, fg, params, dx, ctx.seed, shape)
    metrics.update(res.stats, **geology.metrics)
    grids, _ = tiles.map(heights_tile, "heights", shape, {"height": src}, params,
                         per_tile={t.name: geology.part(*t.window()) for t in tiles.tiles(shape)},
                         grids={"heights": ("height",)}, cell_size_m=dx)
    return grids["heights"]


def _talus_rounds(tiles, inputs: dict, params, metrics: dict, progress):
    """The talus rule in rounds, each reading the round before's change from
    a halo; the final change (TileArrays), or None when no iteration is due."""
    t0 = time.perf_counter()
    shape, dx = tuple(inputs["height"].shape), float(inputs["height"].cell_size_m)
    plan = plan_for(params, dx, physics_for(params, dx))
    n_th, change = plan.thermal_iterations, None
    last_round = (n_th - 1) // THERMAL_ROUND * THERMAL_ROUND if n_th else 0
    # a resumed run whose last round is in the store takes it from there (the rounds before are not kept)
    done = last_round if n_th and tiles.kept(f"thermal{last_round}", shape) else 0
    idle = 0  # tile rounds in which no slope was above the talus angle
    while done < n_th:
        k = min(THERMAL_ROUND, n_th - done)
        grids, parts = tiles.map(thermal_tile, f"thermal{done}", shape, {**inputs, "change": change}, params,
                                 {"iterations": k, "cfrac": plan.thermal_c}, grids={"change": ("change",)},
                                 cell_size_m=dx, keep=done + k == n_th)
        nonfinite = sum(p["nonfinite"] for p in parts)
        if nonfinite:
            raise StageError(f"erosion: thermal weathering blew up at iteration {done + k} (talus_angle_deg): "
                             f"{nonfinite} non-finite cells")
        idle += sum(p["idle"] for p in parts)
        tiles.discard(change)
        change, done = grids["change"], done + k
        progress(0.4 + 0.2 * done / n_th, f"thermal weathering {done}/{n_th}")
    metrics.update(thermal_iterations=n_th, thermal_c=plan.thermal_c, thermal_seconds=time.perf_counter() - t0,
                   thermal_rounds=-(-n_th // THERMAL_ROUND), thermal_idle_tile_rounds=idle)
    return change


def _storm(ctx, inputs: dict, params, progress, metrics: dict) -> dict | None:
    """The storm on its own grid from the tiles' block means of the
    weathered heights; its final state as Prolongations (None: no storm grid)."""
    from worldlib.terrain.blocks import coarse_factor

    src = inputs["height"]
    shape, dx = tuple(src.shape), float(src.cell_size_m)
    fs = coarse_factor(*shape, dx, params.storm_cell_m)
    if fs == 1:
        return None
    _, parts = ctx.tiles.map(storm_input_tile, "storm_input", shape, inputs, params, fs, keep=False)
    coarse_h = _assemble(ctx.tiles.tiles(shape), parts, "block_mean", fs)
    simc, fc, storm_metrics = st.coarse_storm(ctx.cl, coarse_h, params, dx * fs, lambda f, m: progress(0.6 + 0.3 * f, m))
    metrics.update({k: v for k, v in storm_metrics.items() if k not in st.THERMAL_METRICS}, storm_cell_factor=fs,
                   storm_cell_size_m=dx * fs, opencl_storm_tile=[simc.nr, simc.tile_vectors],
                   opencl_storm_avx512=simc.avx512)
    simc.finish()
    return st.storm_fields(fc, fs)


def _map_metrics(parts: list[dict], n_th: int, dx: float) -> dict:
    """The final metrics from the tiles' sums and slope pairs (steps.final_metrics)."""
    metrics = {}
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
    return metrics


def _assemble(tiles, parts: list[dict], key: str, f: int) -> np.ndarray:
    """The coarse map from the tiles' block means (each tile's blocks its own)."""
    rows = sum(p[key].shape[0] for t, p in zip(tiles, parts) if t.col == 0)
    cols = sum(p[key].shape[1] for t, p in zip(tiles, parts) if t.row == 0)
    out = np.empty((rows, cols))
    for t, p in zip(tiles, parts):
        out[t.row0 // f:t.row0 // f + p[key].shape[0], t.col0 // f:t.col0 // f + p[key].shape[1]] = p[key]
    return out


def _read(handle, window: tuple[int, int, int, int]) -> np.ndarray:
    """A window of a one-channel grid (the input's GridFile or a pass's TileArrays), float32."""
    return np.asarray(handle.read(*window, channel=handle.channels[0]), np.float32)


def _heights_and_change(tctx, inputs: dict[str, Any], halo: int):
    """The tile's window(halo), its heights after geological time and the
    talus rule's change so far (zeros before the first round)."""
    window = tctx.tile.window(halo)
    h = _read(inputs["heights"], window)
    before = inputs.get("change")
    return window, h, (np.zeros_like(h) if before is None else _read(before, window))


def prepare_tile(tctx, inputs: dict[str, Any], params, fg: int) -> TileOutput:
    """The input checks of steps.check_input on the tile, and its block means for geology."""
    from worldlib.terrain.blocks import block_mean

    h = _read(inputs["height"], tctx.tile.window())
    summary: dict[str, Any] = {"error": st.input_problem(h, (tctx.tile.row0, tctx.tile.col0))}
    if fg and not summary["error"]:
        summary["block_mean"] = block_mean(h, fg)
    return TileOutput({}, summary)


def heights_tile(tctx, inputs: dict[str, Any], params, geology) -> TileOutput:
    """The tile's heights after geological time on its own grid (steps.FineGeology), computed once for every pass."""
    window = tctx.tile.window()
    return TileOutput({"heights": geology.heights(_read(inputs["height"], window), window)})


def thermal_tile(tctx, inputs: dict[str, Any], params, shared: dict) -> TileOutput:
    """`iterations` of the talus rule on the tile and a halo of 2 cells per
    iteration, from the change of the round before (none: the first)."""
    from .device import DeviceSim
    from .physics import talus_thresholds

    k = shared["iterations"]
    _, h, dT = _heights_and_change(tctx, inputs, 2 * k)
    ph = physics_for(params, inputs["height"].cell_size_m)
    idle = not _any_above_talus(h, dT, *talus_thresholds(ph))
    if idle:  # no cell sends: every iteration adds 0 to dT, which keeps its bits (dT is never -0)
        out = dT[tctx.tile.inner(2 * k)]
    else:
        sim = DeviceSim(tctx.cl, h, ph, change=dT, thermal_only=True)
        sim.thermal(k, cfrac=shared["cfrac"])
        out = sim.change()[tctx.tile.inner(2 * k)]
        sim.finish()
    return TileOutput({"change": np.ascontiguousarray(out)}, {"nonfinite": int((~np.isfinite(out)).sum()),
                                                              "idle": idle})


def _any_above_talus(Tb: np.ndarray, dT: np.ndarray, t_ax: np.float32, t_dg: np.float32) -> bool:
    """Whether any pair of neighbours differs by more than the talus rule's
    threshold, as its kernels test it (float32 heights Tb + dT, d > t)."""
    h = (Tb + dT).astype(np.float32)
    for a, b, t in ((h[:, 1:], h[:, :-1], t_ax), (h[1:], h[:-1], t_ax), (h[1:, 1:], h[:-1, :-1], t_dg),
                    (h[1:, :-1], h[:-1, 1:], t_dg)):
        if (np.abs(a - b) > t).any():
            return True
    return False


def storm_input_tile(tctx, inputs: dict[str, Any], params, fs: int) -> TileOutput:
    """The tile's block means of the weathered heights: the storm's grid."""
    from worldlib.terrain.blocks import block_mean

    _, h, dT = _heights_and_change(tctx, inputs, 0)
    return TileOutput({}, {"block_mean": block_mean(h + dT.astype(np.float64), fs)})


def maps_tile(tctx, inputs: dict[str, Any], params, storm: dict | None) -> TileOutput:
    """The tile's output maps (steps.output_maps) and hillshade from its
    cells and a one-cell halo; its sums and slope pairs for the metrics."""
    src = inputs["height"]
    dx = float(src.cell_size_m)
    window, h, dT = _heights_and_change(tctx, inputs, 1)
    h_in = _read(src, window)
    inner = tctx.tile.inner(1)
    summary: dict[str, Any] = {"error": "", "thermal_sum": float(dT[inner].astype(np.float64).sum()),
                               "thermal_abs_sum": float(np.abs(dT[inner].astype(np.float64)).sum()),
                               "after_thermal": st.slope_excess_counts(h + dT, inner, dx, params.talus_angle_deg)}
    if storm is not None:
        f = st.fine_fields(storm, dT, window)
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
