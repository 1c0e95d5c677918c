"""The erosion's steps that the whole run (stage.run) and the tiled run
(tiled.py) share, each the same operations for a cell whatever the window
around it: the input check, geological time (on the terrain's cells or its
own grid, FineGeology), the storm on its own grid (coarse_storm,
storm_fields, fine_fields), the output maps and the sums and slope pairs
their metrics come from."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import InputError, StageError
from pipeline.grid import Grid

from . import simulate
from .microrelief import MicroRelief
from .params import ErosionParams, channel_threshold_m2, physics_for, plan_for, strata_for


SLOPE_TOLERANCE_DEG = 0.5  # reported: cells steeper than talus + this after thermal weathering


def check_input(height: Grid) -> np.ndarray:
    h = height.channel(height.channels[0])
    if h.ndim != 2 or min(h.shape) < 3:
        raise InputError(f"erosion: the height grid must be 2-D with at least 3 x 3 cells, got {h.shape}")
    problem = input_problem(h, (0, 0))
    if problem:
        raise InputError(problem)
    return np.ascontiguousarray(h, dtype=np.float32)


def input_problem(h: np.ndarray, origin: tuple[int, int]) -> str:
    """What is wrong with input heights (a tile of them at `origin`: its rows
    and columns named in the world), or ''."""
    bad = ~np.isfinite(h)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        return (f"erosion: the input height has {int(bad.sum())} NaN or infinite cells (first at row "
                f"{origin[0] + r}, column {origin[1] + c}); fix the heightmap before eroding it")
    if float(np.max(np.abs(h))) > 1e6:
        return (f"erosion: input heights reach {float(np.max(np.abs(h))):.3g} m; heights beyond 1e6 m are not "
                f"terrain (wrong units?)")
    return ""


def slope_excess(h: np.ndarray, dx: float, talus_deg: float, periodic: bool) -> dict[str, float]:
    """How far the 8-neighbour slopes exceed the talus angle (float64)."""
    if periodic:
        h = np.pad(h, ((0, 1), (1, 1)), mode="wrap")  # every pair once: from each cell to its E, S, SE, SW
        return slope_excess_of(slope_excess_counts(h, (slice(0, h.shape[0] - 1), slice(1, h.shape[1] - 1)), dx,
                                                   talus_deg))
    return slope_excess_of(slope_excess_counts(h, (slice(0, h.shape[0]), slice(0, h.shape[1])), dx, talus_deg))


def slope_excess_counts(h: np.ndarray, inner: tuple[slice, slice], dx: float, talus_deg: float) -> dict[str, float]:
    """The worst excess over the talus angle (deg), the pairs above it by more
    than SLOPE_TOLERANCE_DEG and all pairs, of the pairs from a cell of
    h[inner] to its E, S, SE and SW neighbour inside h: a tile's (inner in a
    window with its halo) add up to the whole map's."""
    h = np.asarray(h, np.float64)
    rows, cols = h.shape
    worst, above, pairs = -math.inf, 0, 0
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r0, r1 = max(inner[0].start, -dr), min(inner[0].stop, rows - dr)
        c0, c1 = max(inner[1].start, -dc), min(inner[1].stop, cols - dc)
        if r1 <= r0 or c1 <= c0:
            continue
        d = np.abs(h[r0:r1, c0:c1] - h[r0 + dr:r1 + dr, c0 + dc:c1 + dc])
        ang = np.degrees(np.arctan(d / (dx * math.hypot(dr, dc))))
        worst = max(worst, float(ang.max()) - talus_deg)
        above += int((ang > talus_deg + SLOPE_TOLERANCE_DEG).sum())
        pairs += ang.size
    return {"worst": worst, "above": above, "pairs": pairs}


def slope_excess_of(*counts: dict[str, float]) -> dict[str, float]:
    """slope_excess from the counts of the tiles (slope_excess_counts)."""
    pairs = sum(c["pairs"] for c in counts)
    return {"max_excess_deg": max(max(c["worst"] for c in counts), 0.0) if pairs else 0.0,
            "fraction_above_tolerance": sum(c["above"] for c in counts) / max(pairs, 1)}


THERMAL_METRICS = ("thermal_iterations", "thermal_c", "thermal_seconds", "thermal_mass_residual_rel")


def geology(cl, h: np.ndarray, dx: float, params: ErosionParams, progress, seed: int) -> tuple[np.ndarray, dict]:
    """Geological time on the terrain's cells, or on its own grid
    (geological_cell_m, coarse_grid.py): the heights after it (float32) and
    its metrics. On its own grid the solve runs on the f x f block means and
    its result comes back to the fine cells (FineGeology), with the
    microrelief finer than its cells."""
    from worldlib.terrain.blocks import block_mean, coarse_factor

    fac = coarse_factor(h.shape[0], h.shape[1], dx, params.geological_cell_m)
    coarse = block_mean(h, fac) if fac > 1 else h.astype(np.float64)
    res = solve_geology(cl, coarse, dx * fac, params, progress)
    if fac == 1:
        return res.height.astype(np.float32), res.stats
    fine = FineGeology.of(res.height, coarse, fac, params, dx, seed, h.shape)
    return fine.heights(h, (0, 0) + h.shape), {**res.stats, **fine.metrics}


def solve_geology(cl, h: np.ndarray, dx: float, params: ErosionParams, progress):
    """The stream-power solve with creep, landslides and strata on cells of
    dx metres (stream_power.run); its budget checked. Its stats name the cell
    size it ran on."""
    from . import stream_power

    res = stream_power.run(cl, h, dx, params.geological_years, params.geological_step_years,
                           params.stream_power_k, params.stream_power_m, params.stream_power_n,
                           params.uplift_mm_per_year / 1000.0, progress=progress,
                           routing=params.geological_routing, channel_area_m2=channel_threshold_m2(params, dx),
                           diffusivity_m2_per_year=params.hillslope_diffusivity_m2_per_year,
                           breach=params.geological_breach, mfd_exponent=params.geological_mfd_exponent,
                           flat_routing=params.geological_flat_routing, fill_lakes=params.geological_lake_fill,
                           mfd_isotropic=params.geological_mfd_isotropic,
                           critical_slope=math.tan(math.radians(params.critical_slope_deg)),
                           deposition_g=params.deposition_g, strata=strata_for(params),
                           incision_width_m=params.incision_width_m, round_sweeps=params.landslide_round_sweeps)
    if res.budget_relative_error > 1e-9:
        raise StageError(f"erosion: stream power lost {res.budget_relative_error:.2e} of the eroded volume "
                         f"on its way to base level")
    res.stats.update(channel_area_used_m2=channel_threshold_m2(params, dx), geological_cell_size_m=dx)
    return res


@dataclass(frozen=True)
class FineGeology:
    """Geological time on its own grid, carried to the fine cells: each
    block's result spread smoothly (Prolongation.conserving of the solved
    heights) plus `keep` times the fine detail the block means did not hold
    (the input less the same spread of its block means). Hillslope creep of
    diffusivity D over the years t damps a height wave of wavenumber k by
    exp(-D k^2 t); the detail is shorter than two coarse cells, so keep is
    that factor at k = pi / (f dx): 1 without creep (the detail survives as
    it would in the fine solve: nothing there touches it), 0 for the default
    world's 5 Myr at 0.03 m^2/year, where the fine solve too would have
    flattened it (the raw heightmap's sub-8 m noise, 42 deg median slope at 1 m
    cells, would otherwise come back on top of the eroded land). On top of
    it the microrelief (microrelief.py): the relief finer than the blocks
    that disturbances keep renewing while creep flattens it."""

    f: int
    change: Any  # Prolongation of the solved change (keep = 1)
    after: Any  # Prolongation of the solved heights (keep < 1)
    before: Any  # Prolongation of the block means (0 < keep < 1)
    keep: float
    micro: MicroRelief | None = None  # the relief finer than the geology's cells, added on top

    @classmethod
    def of(cls, coarse_after: np.ndarray, coarse_before: np.ndarray, f: int, params: ErosionParams,
           dx: float, seed: int, shape: tuple[int, int]) -> "FineGeology":
        """shape: the world's fine cells (the microrelief's noise wraps on it when the edges are periodic)."""
        from .coarse_grid import Prolongation

        D, t = params.hillslope_diffusivity_m2_per_year, params.geological_years
        keep = math.exp(-D * t * (math.pi / (f * dx)) ** 2)
        micro = MicroRelief.of(seed, shape, dx, f * dx, params.microrelief_rms_m, params.microrelief_size_m,
                               periodic=params.boundary == "periodic")
        after = np.asarray(coarse_after, np.float64)
        if keep == 1.0:
            return cls(f, Prolongation.conserving(after - coarse_before, f), None, None, keep, micro)
        before = Prolongation.conserving(coarse_before, f) if keep > 0.0 else None
        return cls(f, None, Prolongation.conserving(after, f), before, keep, micro)

    @property
    def metrics(self) -> dict[str, Any]:
        return {"geological_cell_factor": self.f, "geological_detail_kept": self.keep,
                "microrelief_rms_m": self.micro.rms_m if self.micro else 0.0,
                "microrelief_classes": len(self.micro.sizes_m) if self.micro else 0}

    def part(self, row0: int, col0: int, rows: int, cols: int) -> "FineGeology":
        """The coarse data fine cells [row0, +rows) x [col0, +cols) read (what a tile is sent)."""
        cut = lambda p: None if p is None else p.part(row0, col0, rows, cols)  # noqa: E731
        return FineGeology(self.f, cut(self.change), cut(self.after), cut(self.before), self.keep, self.micro)

    def heights(self, h: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
        """The fine heights after geological time of the window's cells (h their input), float32."""
        if self.change is not None:
            fine = h + self.change.window(*window)
        else:
            fine = self.after.window(*window)
            if self.before is not None:
                fine += self.keep * (h - self.before.window(*window))
        if self.micro is not None:
            fine = fine + self.micro.field(window)
        return fine.astype(np.float32)


def storm_fields(fc: dict[str, np.ndarray], fac: int) -> dict[str, Any]:
    """The coarse storm's final state as Prolongations to the fine cells:
    terrain change conserving each block's volume, water and sediment
    likewise and non-negative, velocity and moisture bilinear."""
    from .coarse_grid import Prolongation

    out = {"dT": Prolongation.conserving(fc["dT"], fac), "W": Prolongation.positive(fc["W"], fac),
           "S": Prolongation.positive(fc["S"], fac)}
    out.update({k: Prolongation.linear(fc[k], fac) for k in ("vx", "vz", "M")})
    return out


def fine_fields(storm: dict[str, Any], dT_thermal: np.ndarray, window: tuple[int, int, int, int]) -> dict[str, np.ndarray]:
    """The fine cells of a window after the storm on its own grid: dT the
    talus rule's change (float32) plus the storm's (float64), the rest float32."""
    fields = {"dT": dT_thermal.astype(np.float64) + storm["dT"].window(*window)}
    fields.update({k: storm[k].window(*window).astype(np.float32) for k in ("W", "S", "vx", "vz", "M")})
    return fields


def coarse_storm(cl, coarse_h: np.ndarray, params: ErosionParams, dx: float, progress):
    """The storm alone on its own grid's heights (the block means): its
    simulator, its final fields on the coarse cells and its metrics."""
    import dataclasses

    from .device import DeviceSim

    phc = physics_for(params, dx)
    planc = dataclasses.replace(plan_for(params, dx, phc), thermal_iterations=0)
    simc = DeviceSim(cl, coarse_h.astype(np.float32), phc)
    metrics = simulate.run(simc, phc, planc, progress=progress)
    return simc, simc.fields(), metrics


# the channels of each output grid, in the order output_maps stacks them
CHANNELS = {"height": ("height",), "water": ("water.depth",), "flow": ("flow.vx", "flow.vz", "flow.speed"),
            "sediment": ("sediment.depth",), "change": ("change.net", "change.wear", "change.deposition"),
            "moisture": ("moisture",)}


def output_maps(h_in: np.ndarray, height: np.ndarray, f: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The output grids' arrays (float32) from the input heights, the final
    heights and the final fields, cell by cell (a tile's are the whole map's)."""
    speed = np.sqrt(f["vx"].astype(np.float64) ** 2 + f["vz"].astype(np.float64) ** 2).astype(np.float32)
    change = (height.astype(np.float64) - h_in).astype(np.float32)  # geology, talus and storm together
    c32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    return {"height": c32(height), "water": c32(f["W"]), "flow": c32(np.stack([f["vx"], f["vz"], speed], axis=-1)),
            "sediment": c32(f["S"]),
            "change": c32(np.stack([change, np.maximum(-change, 0), np.maximum(change, 0)], axis=-1)),
            "moisture": c32(np.clip(f["M"], 0.0, 1.0))}


def map_sums(maps: dict[str, np.ndarray], wet_depth_m: float) -> dict[str, float]:
    """What the final metrics sum over the cells (float64): a tile's add up to the world's."""
    c64 = maps["change"][..., 0].astype(np.float64)
    return {"cells": int(c64.size), "change_min": float(c64.min()), "change_max": float(c64.max()),
            "wear_sum": float(np.maximum(-c64, 0).sum()), "deposition_sum": float(np.maximum(c64, 0).sum()),
            "water_sum": float(maps["water"].astype(np.float64).sum()),
            "wet_cells": int((maps["water"] > wet_depth_m).sum())}


def final_metrics(sums: dict[str, float], after_thermal: dict, final: dict, dx: float) -> dict[str, Any]:
    return dict(
        cells=sums["cells"], cell_size_m=dx,
        thermal_max_excess_deg=after_thermal.get("max_excess_deg"),
        thermal_fraction_above_talus=after_thermal.get("fraction_above_tolerance"),
        slope_tolerance_deg=SLOPE_TOLERANCE_DEG,
        final_max_excess_deg=final["max_excess_deg"], final_fraction_above_talus=final["fraction_above_tolerance"],
        wear_max_m=max(-sums["change_min"], 0.0), deposition_max_m=max(sums["change_max"], 0.0),
        wear_volume_m3=sums["wear_sum"] * dx * dx, deposition_volume_m3=sums["deposition_sum"] * dx * dx,
        water_volume_m3=sums["water_sum"] * dx * dx, wet_fraction=sums["wet_cells"] / max(sums["cells"], 1),
    )
