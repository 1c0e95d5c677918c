"""The erosion stage: optionally geological time first (stream-power river
incision with uplift, Braun and Willett 2013, above a channel-initiation
area; hillslope creep and threshold landsliding; river deposition after Yuan
et al. 2019; optional hard strata: stream_power.py, hillslope.py; on its own
coarser grid, the microrelief below that grid's cells: microrelief.py), then thermal
weathering (talus slopes and scree, seed 003, Olsen's multi-neighbour rule)
and a storm of hydraulic erosion on the virtual-pipe shallow-water model
(seed 004; Mei et al. 2007, Stava et al. 2008) with sediment moved in flux
form so terrain + sediment is conserved.

Every parameter is physical (mm/h, degrees, hours, years, s/m, 1/s) and means
the same at any resolution. The whole state stays on the OpenCL device; only
diagnostics every few steps and the final maps come back.
The seed is the microrelief's (its noise per world cell).

The parameters and what follows from them on a grid: params.py; the steps
the whole run and the tiled run (tiled.py) share: steps.py.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.contract import (Artifact, Check, CheckContext, Input, ParamError, Relief, ReportMap, RunContext, Stage,
                               ValueRange)
from pipeline.errors import InputError, StageError
from pipeline.grid import Grid
from worldlib.terrain.hillshade import hillshade

from . import simulate
from .params import ErosionParams, max_steps, physics_for, plan_for, storm_steps_least
from .physics import Physics
from .steps import (CHANNELS, THERMAL_METRICS, check_input, coarse_storm, final_metrics, fine_fields, geology,
                    map_sums, output_maps, slope_excess, storm_fields)


def _thermal_and_storm(cl, h: np.ndarray, params: ErosionParams, ph: Physics, plan: simulate.Plan,
                       progress, after_thermal) -> tuple[Any, dict[str, np.ndarray], dict]:
    """Thermal weathering on the terrain's cells, then the storm: on the same
    cells, or on the storm's own grid (coarse_grid.py) when the cells are finer
    than storm_cell_m. Returns the simulator of the storm (its OpenCL settings
    go to the metrics), the final fields on the terrain's cells (dT the change
    since h) and the metrics."""
    import dataclasses

    from worldlib.terrain.blocks import block_mean

    from .coarse_grid import storm_factor
    from .device import DeviceSim

    dx = ph.dx
    fac = storm_factor(h.shape[0], h.shape[1], dx, params.storm_cell_m)
    sim = DeviceSim(cl, h, ph)
    if fac == 1:
        metrics = simulate.run(sim, ph, plan, progress=progress, after_thermal=after_thermal)
        progress(0.96, "reading the maps back")
        return sim, sim.fields(), metrics
    fine = simulate.run(sim, ph, dataclasses.replace(plan, duration_s=0.0), progress=progress,
                        after_thermal=after_thermal)
    dT_thermal = sim.fields()["dT"]
    sim.finish()
    del sim
    simc, fc, metrics = coarse_storm(cl, block_mean(h + dT_thermal.astype(np.float64), fac), params, dx * fac, progress)
    metrics.update({k: fine[k] for k in THERMAL_METRICS if k in fine})
    metrics["total_seconds"] += fine["total_seconds"]
    metrics.update(storm_cell_factor=fac, storm_cell_size_m=dx * fac)
    progress(0.96, "reading the maps back")
    rows, cols = h.shape
    return simc, fine_fields(storm_fields(fc, fac), dT_thermal, (0, 0, rows, cols)), metrics


def run(ctx: RunContext, inputs: dict[str, Any], params: ErosionParams) -> dict[str, Any]:
    grid: Grid = inputs["height"]
    h = check_input(grid)
    dx = float(grid.cell_size_m)
    ph = physics_for(params, dx)
    plan = plan_for(params, dx, ph)
    h_in = h
    geology_stats: dict[str, Any] = {}
    progress = ctx.progress
    if params.geological_years > 0:
        share = 0.5  # of the progress bar
        h, geology_stats = geology(ctx.cl, h, dx, params, lambda f, m: ctx.progress(share * f, m), ctx.seed)
        progress = lambda f, m: ctx.progress(share + (1 - share) * f, m)  # noqa: E731
    progress(0.0, f"erosion {h.shape[1]}x{h.shape[0]} cells of {dx:g} m: {plan.thermal_iterations} talus "
                  f"iterations, {params.storm_hours:g} h storm")
    after_thermal = {}

    def on_thermal_done(fields: dict[str, np.ndarray]) -> None:
        after_thermal.update(slope_excess(h + fields["dT"], dx, params.talus_angle_deg, params.boundary == "periodic"))

    sim, f, metrics = _thermal_and_storm(ctx.cl, h, params, ph, plan, progress, on_thermal_done)
    metrics.update(geology_stats)
    height = (h + f["dT"]).astype(np.float32)
    for name, arr in (("height", height), ("water", f["W"]), ("sediment", f["S"])):
        if not np.isfinite(arr).all():
            raise StageError(f"erosion: non-finite {name} in the final state (step {metrics['steps']})")
    maps = output_maps(h_in, height, f)
    out_grid = lambda name: Grid(maps[name], cell_size_m=dx, channels=CHANNELS[name], origin_m=grid.origin_m)  # noqa: E731
    outputs = {f"erosion.{name}": out_grid(name) for name in CHANNELS}
    ctx.progress(0.98, "hillshade")
    outputs["erosion.hillshade"] = hillshade(outputs["erosion.height"])
    final = slope_excess(height, dx, params.talus_angle_deg, params.boundary == "periodic")
    metrics.update(final_metrics(map_sums(maps, params.wet_depth_m), after_thermal, final, dx),
                   opencl_local_size=list(sim.local), opencl_vector_width=sim.vw,
                   opencl_vector_width_thermal=sim.vw_thermal,
                   opencl_storm_tile=[sim.nr, sim.tile_vectors], opencl_storm_local_size=list(sim.local_storm),
                   opencl_storm_avx512=sim.avx512)
    ctx.metrics.update(metrics)
    ctx.progress(1.0, "done")
    return outputs


def run_tiled(ctx: RunContext, inputs: dict[str, Any], params: ErosionParams) -> dict[str, Any]:
    """run on a tiled world (tiled.py): the fine cells per tile, geological
    time and the storm on their own grids; the same files. A world whose
    geology or storm spans its fine cells runs whole (the reason in the metrics)."""
    from pipeline import exr

    from . import tiled

    src = inputs["height"]
    why = tiled.whole_reason(params, tuple(src.shape), float(src.cell_size_m), ctx.tiles.tile_cells)
    if why is not None:
        ctx.metrics["tiled_steps"] = f"none: {why}; the stage ran whole"
        return run(ctx, {"height": exr.read_grid(src.path)}, params)
    outputs, metrics = tiled.run(ctx, src, params, ctx.progress)
    metrics["tiled_steps"] = "talus rule in rounds, block means, maps; geology and storm on their own grids"
    ctx.metrics.update(metrics)
    ctx.progress(1.0, "done")
    return outputs


BYTES_PER_CELL_STORM = 200  # the device state (about 30 float32 fields, double-buffered) and the host copies
BYTES_PER_CELL_GEOLOGY = 96  # the stream-power solve's float64 fields and the flow routing's


def check(params: ErosionParams, ctx: CheckContext) -> Check:
    """The run plan on the input's cell size (step counts within their
    limits) and the memory from its cells, before any stage runs."""
    if params.deposition_g > 0 and params.geological_routing != "mfd":
        raise ParamError("deposition_g", f"{params.deposition_g:g} needs geological_routing = \"mfd\" (the "
                         f"sediment flux is routed over multiple flow directions), got {params.geological_routing!r}; "
                         f"set deposition_g = 0 or switch the routing")
    height = ctx.inputs.get("height")
    if height is None:
        return Check()
    dx = height.cell_size_m
    ph = physics_for(params, dx)
    try:
        plan_for(params, dx, ph)
    except InputError as e:
        raise ParamError("", str(e).removeprefix("erosion: ")) from None
    cells = height.shape[0] * height.shape[1]
    if params.dt_s is None and params.storm_hours > 0:
        from .coarse_grid import storm_factor

        fac = storm_factor(height.shape[0], height.shape[1], dx, params.storm_cell_m)  # the storm's own grid
        dx, ph = dx * fac, physics_for(params, dx * fac)
        least, wave = storm_steps_least(params, ph, (height.shape[0] // fac, height.shape[1] // fac))
        limit, limit_how = max_steps()
        if least > limit:
            net = (params.rain_mm_per_hour - params.evaporation_mm_per_hour)
            raise ParamError("storm_hours", f"{params.storm_hours:g} hours on {dx:g} m cells needs at least about "
                             f"{least:.3g} adaptive steps (dt = cfl dx / (|u| + sqrt(g h)); {max(net, 0):g} mm/h of "
                             f"rain net of evaporation deepens the water until waves reach {wave:.3g} m/s, "
                             f"dt {ph.dt_limit(wave):.3g} s), more than the {limit:,} a storm may take ({limit_how}); "
                             f"shorten the storm, lower the rain or coarsen the grid")
    shape = tuple(height.shape)
    if ctx.tile_cells:
        from .tiled import THERMAL_ROUND, whole_reason

        if whole_reason(params, shape, height.cell_size_m, ctx.tile_cells) is None:
            return _tiled_memory(params, shape, height.cell_size_m, ctx.tile_cells + 4 * THERMAL_ROUND)
    per_cell = BYTES_PER_CELL_STORM + (BYTES_PER_CELL_GEOLOGY if params.geological_years > 0 else 0)
    return Check(memory_bytes=per_cell * cells, memory_how=f"the terrain's {cells:,} cells x {per_cell} B")


def _tiled_memory(params: ErosionParams, shape: tuple[int, int], dx: float, held: int) -> Check:
    """A tiled run holds one tile with its halo at a time, and the coarse
    grids of geology and the storm (with their prolongations) whole."""
    from worldlib.terrain.blocks import coarse_factor

    cells = shape[0] * shape[1]
    parts = [(BYTES_PER_CELL_STORM * held * held, f"a tile and its halo ({held}^2 cells x {BYTES_PER_CELL_STORM} B)")]
    if params.geological_years > 0:
        fg = coarse_factor(*shape, dx, params.geological_cell_m)
        per = BYTES_PER_CELL_GEOLOGY + BYTES_PER_CELL_STORM
        parts.append((per * cells // fg ** 2, f"geology's {cells // fg ** 2:,} cells x {per} B"))
    fs = coarse_factor(*shape, dx, params.storm_cell_m)
    if fs > 1:
        parts.append((BYTES_PER_CELL_STORM * cells // fs ** 2,
                      f"the storm's {cells // fs ** 2:,} cells x {BYTES_PER_CELL_STORM} B"))
    memory = max(m for m, _ in parts)  # one at a time: the tiles' passes, the geology, the storm
    return Check(memory_bytes=memory, memory_how="the largest of " + ", ".join(how for _, how in parts))


STAGE = Stage(
    name="erosion",
    version=1,
    description="Optional geological time (stream-power incision with uplift, implicit Braun-Willett scheme), "
    "thermal weathering (talus angle, Olsen's rule) and hydraulic erosion on the virtual-pipe "
    "shallow-water model with mass-conserving sediment transport, on the OpenCL device",
    inputs=(Input("height", one_of=("heightmap.height",), description="the terrain to erode", channels=("height",),
                  units="m"),),
    outputs=(
        Artifact("erosion.height", kind="grid", file="height.exr", channels=("height",), units="m",
                 description="eroded terrain height, float32, one value per cell"),
        Artifact("erosion.water", kind="grid", file="water.exr", channels=("water.depth",), units="m",
                 description="water depth at the end of the storm"),
        Artifact("erosion.flow", kind="grid", file="flow.exr", channels=("flow.vx", "flow.vz", "flow.speed"), units="m/s",
                 description="flow velocity at the end of the storm: vx east, vz south (rows), and speed"),
        Artifact("erosion.sediment", kind="grid", file="sediment.exr", channels=("sediment.depth",), units="m",
                 description="suspended sediment (column height) at the end of the storm"),
        Artifact("erosion.change", kind="grid", file="change.exr",
                 channels=("change.net", "change.wear", "change.deposition"), units="m",
                 description="terrain change: net (eroded height minus input), wear = max(-net, 0), deposition = max(net, 0)"),
        Artifact("erosion.moisture", kind="grid", file="moisture.exr", channels=("moisture",), units="1",
                 description="moisture: running average of water presence over the storm, 0 (dry) .. 1 (always wet)"),
        Artifact("erosion.hillshade", kind="image", file="hillshade.png", dtype="uint8",
                 description="hillshade preview of the eroded terrain (sun from the north-west at 45 degrees), 8-bit RGB"),
    ),
    params=ErosionParams,
    run=run,
    run_tiled=run_tiled,
    check=check,
    report=(ReportMap("erosion.height", "height", name="height", title="Height ({artifact})",
                      relief=Relief(hillshade, ("erosion.height",), "height")),
            ReportMap("erosion.change", "change.net", name="change",
                      title="Erosion change ({channel}, deposition red, erosion blue)", palette="diverging",
                      values=ValueRange(symmetric_percentile=99.0), note="clipped at the 99th percentile of |change|",
                      relief=Relief(hillshade, ("erosion.height",), "height"))),
    source_dir=Path(__file__).resolve().parent,
    uses_seed=True,
    uses_opencl=True,
)
