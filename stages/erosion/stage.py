"""The erosion stage: optionally geological time first (stream-power river
incision with uplift, Braun and Willett 2013, above a channel-initiation
area; hillslope creep and threshold landsliding; river deposition after Yuan
et al. 2019; optional hard strata: stream_power.py, hillslope.py), then thermal
weathering (talus slopes and scree, seed 003, Olsen's multi-neighbour rule)
and a storm of hydraulic erosion on the virtual-pipe shallow-water model
(seed 004; Mei et al. 2007, Stava et al. 2008) with sediment moved in flux
form so terrain + sediment is conserved.

Every parameter is physical (mm/h, degrees, hours, years, s/m, 1/s) and means
the same at any resolution. The whole state stays on the OpenCL device; only
diagnostics every few steps and the final maps come back.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np

from pipeline.contract import (Artifact, Check, CheckContext, Input, Param, ParamError, Params, Relief, ReportMap,
                               RunContext, Stage, ValueRange)
from pipeline.errors import InputError, StageError
from pipeline.grid import Grid
from worldlib.terrain.hillshade import hillshade

from . import simulate
from .physics import G, THERMAL_C, Physics

MAX_THERMAL_ITERATIONS = 200_000  # talus-rule iterations before the storm, and bank-slumping ones during it
MAX_STEPS = 2_000_000  # storm steps a bake may take (max_steps: WORLDBAKE_MAX_STEPS overrides it)
MAX_GEOLOGICAL_STEPS = 10_000
SLOPE_TOLERANCE_DEG = 0.5  # reported: cells steeper than talus + this after thermal weathering


class ErosionParams(Params):
    boundary: Literal["closed", "open", "periodic"] = Param(
        "open", description="grid edges: closed walls keep all water and sediment; open lets water and sediment "
        "flow out (free outfall); periodic wraps around (for tiling heightmaps)")
    # thermal weathering
    talus_angle_deg: float = Param(
        40.0, units="deg", description="angle of repose: thermal weathering moves material down slopes steeper than "
        "this (Olsen's multi-neighbour rule on the 8 neighbours)", ge=1.0, le=89.0)
    thermal_years: float = Param(
        300.0, units="years", description="duration of thermal weathering (scree and talus slopes) before the storm", ge=0.0, le=1e7)
    scree_diffusivity_m2_per_year: float = Param(
        1.0, units="m^2/year", description="rate of thermal weathering: how fast material above the talus angle "
        "slides, as the diffusivity D of flux = D * (slope - tan(talus)); one rule iteration is 0.5 dx^2 / D", ge=0.0, le=1e6)
    # the storm
    storm_hours: float = Param(
        0.35, units="h", description="duration of the hydraulic erosion storm (simulated time); 0 skips it", ge=0.0, le=1000.0)
    storm_cell_m: float = Param(
        0.0, units="m", description="the storm's own cell size: on finer terrain cells the shallow-water storm runs "
        "on blocks of f x f cells (f the largest whole factor with f dx <= this that divides both sides) and its "
        "terrain change, water and sediment come back to the fine cells conserving each block's volume, so the "
        "storm's CFL step (dt ~ dx) and cells stay those of this size at any resolution: its cost per cell does not "
        "grow on finer grids. Gullies narrower than this are not resolved. 0: the storm runs on the terrain's cells",
        ge=0.0, le=1e4)
    rain_mm_per_hour: float = Param(
        100.0, units="mm/h", description="uniform rain rate during the storm", ge=0.0, le=1e5)
    evaporation_mm_per_hour: float = Param(
        2.0, units="mm/h", description="evaporation (and infiltration) rate, taken from wherever there is water", ge=0.0, le=1e5)
    friction: float = Param(
        0.3, units="", description="Darcy-Weisbach friction factor f of the water flow (0.02 smooth channels .. 1 rough "
        "hillslopes); steady flow speed is sqrt(8 g depth slope / f)", ge=0.001, le=100.0)
    sediment_capacity_s_per_m: float = Param(
        3.0, units="s/m", description="Kc: the water can carry a sediment column C = Kc |q| sin(slope), q the unit "
        "discharge (m^2/s), i.e. a volume concentration Kc * speed * sin(slope)", ge=0.0, le=100.0)
    dissolve_rate_per_s: float = Param(
        0.5, units="1/s", description="Ks: where the water carries less than its capacity C, terrain is eroded at "
        "Ks * (C - S) metres per second", ge=0.0, le=100.0)
    deposit_rate_per_s: float = Param(
        0.5, units="1/s", description="Kd: where the water carries more than its capacity, sediment settles at "
        "Kd * (S - C) metres per second", ge=0.0, le=100.0)
    min_slope_deg: float = Param(
        2.0, units="deg", description="slope used for the capacity on flatter ground, so water on flats still carries sediment",
        ge=0.0, le=45.0)
    bank_diffusivity_m2_per_hour: float = Param(
        0.0, units="m^2/h", description="bank slumping during the storm: the talus rule runs at this rate (as "
        "scree_diffusivity) but only moves material into cells holding more than wet_depth_m of water, so banks "
        "steeper than the talus angle collapse into the channels; 0 turns it off", ge=0.0, le=1e8)
    # output maps
    moisture_time_hours: float = Param(
        0.1, units="h", description="time constant of the moisture map, a running average of water presence", gt=0.0, le=1e4)
    wet_depth_m: float = Param(
        0.01, units="m", description="water depth that counts as fully wet in the moisture map (shallower: "
        "proportionally), and that bank slumping needs in the receiving cell",
        gt=0.0, le=100.0)
    # geological time: stream-power fluvial erosion (Braun and Willett 2013), before the talus rule and the storm
    geological_years: float = Param(
        0.0, units="years", description="duration of stream-power river incision with uplift (implicit Braun-Willett "
        "scheme, no time-step limit; the map edges are base level whatever the boundary); 0 skips it", ge=0.0, le=1e9)
    geological_cell_m: float = Param(
        0.0, units="m", description="geological time's own cell size: on finer terrain cells the stream-power solve, "
        "creep and landsliding run on blocks of f x f cells (f the largest whole factor with f dx <= this that "
        "divides both sides; the block means of the heights) and their change comes back to the fine cells "
        "conserving each block's volume, so geological time costs the same per fine cell at any resolution and a "
        "tiled world's geology is 1/f^2 of its cells. Valleys narrower than this are not resolved (the talus rule "
        "and the storm still shape the fine cells). 0: geological time runs on the terrain's cells", ge=0.0, le=1e4)
    geological_step_years: float = Param(
        1.0e4, units="years", description="time step of the stream-power solve (stable at any size; smaller is more "
        "accurate)", ge=1.0, le=1e9)
    stream_power_k: float = Param(
        2.0e-5, units="m^(1-2m)/year", description="erodibility K of dh/dt = U - K A^m S^n (A drainage area in m^2)",
        gt=0.0, le=1e9)
    stream_power_m: float = Param(0.45, units="", description="drainage-area exponent m", ge=0.0, le=2.0)
    stream_power_n: float = Param(1.0, units="", description="slope exponent n (1 is closed form; else Newton)",
                                  ge=0.25, le=10.0)
    uplift_mm_per_year: float = Param(
        0.0, units="mm/year", description="uniform rock uplift U of every cell but the base-level edges", ge=0.0, le=1e5)
    geological_routing: Literal["d8", "rho8", "mfd"] = Param(
        "d8", description="flow routing of the stream-power solve: d8 (steepest of 8 neighbours: valleys lock onto "
        "the grid's axes and diagonals), rho8 (diagonal distance drawn afresh per cell and step, Fairfield and "
        "Leymarie 1991) or mfd (area and incision shared among all lower neighbours by slope^geological_mfd_exponent, "
        "Quinn 1991, as fastscapelib's multiple-receiver eroder; n = 1 only)")
    geological_mfd_exponent: float = Param(
        1.1, units="", description="mfd: share of flow ~ slope^p * contour length (1.1 Freeman's spread; larger "
        "concentrates the flow toward the steepest neighbour)", ge=0.1, le=20.0)
    channel_area_m2: float = Param(
        0.0, units="m^2", description="channel initiation: drainage area where river incision starts (mfd and d8 "
        "area); smaller catchments are hillslopes shaped by creep (hillslope_diffusivity) and landslides "
        "(critical_slope_deg) only. Real channel heads drain about 1e3 .. 1e5 m^2 (Montgomery and Dietrich 1988); "
        "0: every cell incises, and the slope at one cell's area is near vertical", ge=0.0, le=1e12)
    channel_specific_area_m: float = Param(
        0.0, units="m", description="channel initiation per unit contour width: rivers incise where the drainage "
        "area per metre of contour, A / dx, passes this (with multiple flow directions a planar hillslope's A grows "
        "with the cell width, so a threshold on A alone would put channel heads twice as far down a slope at half "
        "the cell size); the threshold used is max(channel_area_m2, this x dx). 0 turns it off", ge=0.0, le=1e9)
    critical_slope_deg: float = Param(
        0.0, units="deg", description="threshold landsliding during geological time: after each step no slope "
        "may exceed this angle (heights cut to the lower envelope of cones of this slope, 32-direction distances; "
        "the material joins the rivers' sediment). Mean hillslope gradients of threshold landscapes level off "
        "near 30 .. 35 degrees at 30 m (Montgomery and Brandon 2002); 0 turns it off", ge=0.0, le=89.0)
    strata_thickness_m: float = Param(
        0.0, units="m", description="lithology: horizontal beds of hard rock repeat every this many metres of rock "
        "(fixed to the rock, so they rise with the uplift) during geological time; hard beds stand as cliffs at "
        "strata_critical_slope_deg and erode at strata_k_factor times K, the soft rock between forms benches. "
        "Needs critical_slope_deg; 0 turns it off", ge=0.0, le=1e5)
    strata_hard_fraction: float = Param(
        0.3, units="", description="lithology: share of each strata_thickness_m that is hard rock", ge=0.0, le=1.0)
    strata_critical_slope_deg: float = Param(
        60.0, units="deg", description="lithology: the steepest slope the hard beds stand at (cliffs)", gt=0.0, le=89.0)
    strata_k_factor: float = Param(
        0.5, units="", description="lithology: erodibility K of the hard beds relative to stream_power_k (mfd "
        "routing)", gt=0.0, le=100.0)
    deposition_g: float = Param(
        0.0, units="", description="mfd: dimensionless deposition coefficient G of dh/dt = U - K A^m S + (G / A) Qs "
        "(Yuan et al. 2019; Qs the sediment flux from upstream, landslide material included): rivers lay down "
        "sediment where they slow (fans, transport-limited trunk valleys); about 1 is a mixed bedrock-alluvial "
        "river, 0 detachment-limited (all eroded material leaves)", ge=0.0, le=100.0)
    incision_width_m: float = Param(
        0.0, units="m", description="mfd: rivers incise by their flow per metre of width, K (w A / dx)^m S with "
        "w this width and A / dx the cell's drainage area per metre of contour. A valley's flow spreads over more, "
        "narrower cells on a finer grid, so the cell's own A falls with the cell size and the same valley would cut "
        "less and stand higher; per metre of width it does not, so the world is the same at any resolution (at "
        "dx = w this is K A^m S). 0: the cell's own A", ge=0.0, le=1e5)
    hillslope_diffusivity_m2_per_year: float = Param(
        0.0, units="m^2/year", description="hillslope transport during geological time: linear diffusion, implicit "
        "and isotropic (9-point Laplacian), the map edge fixed; 0 turns it off", ge=0.0, le=1e4)
    geological_flat_routing: Literal["epsilon", "distance"] = Param(
        "epsilon", description="routing across closed depressions during geological time: epsilon (Priority-Flood+"
        "epsilon, Barnes 2014: the flood order, straight lines along rows, columns and diagonals) or distance (the "
        "filled level tilted toward the depression's outlet by the Euclidean distance: water converges on the outlet "
        "from every direction)")
    geological_mfd_isotropic: bool = Param(
        True, description="mfd: scale each cell's incision so that a plane erodes at K A^m |grad h| whatever its "
        "direction (the plain mfd slope is 10 % steeper down the grid axes than between them)")
    geological_lake_fill: bool = Param(
        False, description="mfd: sediment settles in the closed depressions up to the routing surface every step "
        "(counted in the volume budget), so no pit survives to the next step")
    geological_breach: bool = Param(
        False, description="before geological time, carve every closed depression out along its least-cost path "
        "(complete breaching, Lindsay 2016), so no filled flat routes water in straight lines")
    # time stepping
    cfl: float = Param(
        0.5, units="", description="Courant number of the adaptive time step dt = cfl dx / max(|u| + sqrt(g h))",
        ge=0.05, le=0.9)
    dt_s: Optional[float] = Param(
        None, units="s", description="fixed time step instead of the adaptive one; the run is refused when it breaks "
        "the CFL limit (Courant number above 0.9)", gt=0.0, le=3600.0)


def strata_for(params: ErosionParams):
    """The hard beds of geological time, or None."""
    from .stream_power import Strata

    if params.strata_thickness_m <= 0 or params.strata_hard_fraction <= 0 or params.critical_slope_deg <= 0:
        return None
    return Strata(params.strata_thickness_m, params.strata_hard_fraction,
                  math.tan(math.radians(params.strata_critical_slope_deg)), params.strata_k_factor)


def channel_threshold_m2(params: ErosionParams, dx: float) -> float:
    """The drainage area where river incision starts on cells of dx metres."""
    return max(params.channel_area_m2, params.channel_specific_area_m * dx)


def physics_for(params: ErosionParams, dx: float) -> Physics:
    return Physics(
        dx=dx,
        boundary=params.boundary,
        rain=params.rain_mm_per_hour / 1000.0 / 3600.0,
        evaporation=params.evaporation_mm_per_hour / 1000.0 / 3600.0,
        friction=params.friction,
        capacity=params.sediment_capacity_s_per_m,
        min_slope_sin=math.sin(math.radians(params.min_slope_deg)),
        dissolve_rate=params.dissolve_rate_per_s,
        deposit_rate=params.deposit_rate_per_s,
        wet_depth=params.wet_depth_m,
        moisture_tau=params.moisture_time_hours * 3600.0,
        talus_tan=math.tan(math.radians(params.talus_angle_deg)),
        bank_diffusivity=params.bank_diffusivity_m2_per_hour / 3600.0,
        cfl=params.cfl,
    )


def thermal_iterations(params: ErosionParams, dx: float) -> int:
    """Rule iterations standing for thermal_years at this cell size (see Physics)."""
    if params.thermal_years <= 0 or params.scree_diffusivity_m2_per_year <= 0:
        return 0
    return int(math.ceil(_thermal_exact(params, dx) - 1e-9))


def _thermal_exact(params: ErosionParams, dx: float) -> float:
    return params.thermal_years * params.scree_diffusivity_m2_per_year / (THERMAL_C * dx * dx)


def thermal_c(params: ErosionParams, dx: float) -> float:
    """Olsen's c for those iterations: 0.5, scaled down so that iterations x c
    matches the years exactly (on coarse grids less than one iteration may be due)."""
    n = thermal_iterations(params, dx)
    return THERMAL_C * min(1.0, _thermal_exact(params, dx) / n) if n else THERMAL_C


def max_steps() -> tuple[int, str]:
    """The most steps a storm may take, and where that limit comes from:
    WORLDBAKE_MAX_STEPS when set, else MAX_STEPS. The plan refuses a storm
    estimated beyond it, and a running storm stops there."""
    env = os.environ.get("WORLDBAKE_MAX_STEPS", "").strip()
    if not env:
        return MAX_STEPS, "erosion's MAX_STEPS; WORLDBAKE_MAX_STEPS raises it"
    try:
        n = int(float(env))
    except (ValueError, OverflowError):
        n = 0
    if n < 1:
        raise InputError(f"WORLDBAKE_MAX_STEPS = {env!r}: must be a positive number of storm steps")
    return n, f"WORLDBAKE_MAX_STEPS = {env}"


def slump_iterations(params: ErosionParams, dx: float) -> float:
    """Bank-slumping iterations over the storm: its rule runs at
    bank_diffusivity (as the talus rule: one iteration is 0.5 dx^2 / D)."""
    return params.bank_diffusivity_m2_per_hour * params.storm_hours / (THERMAL_C * dx * dx)


def plan_for(params: ErosionParams, dx: float, ph: Physics) -> simulate.Plan:
    """The run plan, or InputError when the params cannot run on this grid."""
    n_th = thermal_iterations(params, dx)
    if n_th > MAX_THERMAL_ITERATIONS:
        raise InputError(
            f"erosion: thermal_years = {params.thermal_years:g} at scree_diffusivity_m2_per_year = "
            f"{params.scree_diffusivity_m2_per_year:g} needs {n_th} iterations of the talus rule on {dx:g} m cells "
            f"(at most {MAX_THERMAL_ITERATIONS}); lower one of them")
    n_slump = slump_iterations(params, dx)
    if n_slump > MAX_THERMAL_ITERATIONS:
        raise InputError(
            f"erosion: bank_diffusivity_m2_per_hour = {params.bank_diffusivity_m2_per_hour:g} over storm_hours = "
            f"{params.storm_hours:g} needs {n_slump:.3g} iterations of bank slumping on {dx:g} m cells (at most "
            f"{MAX_THERMAL_ITERATIONS}); lower one of them")
    most, most_how = max_steps()
    if params.geological_years > 0 and params.geological_years / params.geological_step_years > MAX_GEOLOGICAL_STEPS:
        raise InputError(
            f"erosion: geological_years = {params.geological_years:g} at geological_step_years = "
            f"{params.geological_step_years:g} is {params.geological_years / params.geological_step_years:.3g} steps "
            f"(at most {MAX_GEOLOGICAL_STEPS}); raise geological_step_years")
    if params.dt_s is not None:
        # the least the flow can do is a 1 m/s wave: a step beyond that limit can never run
        limit = ph.cfl_limit * dx / ph.min_wave_speed
        if params.dt_s > limit:
            raise InputError(
                f"erosion: dt_s = {params.dt_s:g} s breaks the CFL limit on {dx:g} m cells: even a {ph.min_wave_speed:g} m/s "
                f"wave needs dt_s <= {limit:.3g} s (Courant number {ph.cfl_limit}); lower dt_s or leave it unset "
                f"for the adaptive step")
        steps = params.storm_hours * 3600.0 / params.dt_s
        if steps > most:
            raise InputError(f"erosion: storm_hours = {params.storm_hours:g} at dt_s = {params.dt_s:g} s is "
                             f"{steps:.3g} steps (at most {most:,}: {most_how})")
    return simulate.Plan(thermal_iterations=n_th, thermal_c=thermal_c(params, dx), duration_s=params.storm_hours * 3600.0,
                         fixed_dt=params.dt_s, max_total_steps=most)


def storm_steps_least(params: ErosionParams, ph: Physics, shape: tuple[int, int]) -> tuple[float, float]:
    """An estimate, from below, of the adaptive storm's steps, known before
    the terrain exists; and the wave speed (m/s) it reaches by the end.

    Each step is dt = cfl dx / w with w >= max(|u| + sqrt(g h)) >= 1 m/s (the
    largest wave of the last diagnostic, at most 17 steps old), so the storm
    takes at least the integral of w(t) / (cfl dx) over its duration T. The
    rain less evaporation, q, adds q t of water per unit area by time t: with
    closed or periodic edges none leaves, the mean depth is at least q t and
    so is the deepest water: w(t) >= sqrt(g q t), a true lower bound. With
    open edges water also leaves at the edge, in channels; the estimate
    then stops the growth at the wave speed of the slowest steady flow that
    carries the whole map's rain out through one edge cell (unit discharge
    Q = q A / dx, w = (27 g Q / 4)^(1/3), the least |u| + sqrt(g h) with
    h u = Q): an estimate, not a bound (a map that drains in sheets, not in
    channels, has shallower water). The first 17 steps' lag is taken off."""
    T = params.storm_hours * 3600.0
    vmin, dx = ph.min_wave_speed, ph.dx
    q = max(ph.rain - ph.evaporation, 0.0)
    c = math.sqrt(G * q)
    tau = (simulate.Plan.check_every + 1) * ph.dt_limit(0.0)
    cap = math.inf
    if ph.boundary == "open":
        cap = max(vmin, (27.0 / 4.0 * G * q * shape[0] * shape[1] * dx) ** (1.0 / 3.0))
    if c == 0.0:
        return T * vmin / (ph.cfl * dx), vmin
    t1 = tau + (vmin / c) ** 2  # w reaches the 1 m/s floor
    t2 = tau + (cap / c) ** 2 if math.isfinite(cap) else math.inf  # and the open edges' cap
    area = vmin * min(T, t1)
    if T > t1:
        area += 2.0 / 3.0 * c * ((min(T, t2) - tau) ** 1.5 - (t1 - tau) ** 1.5)
    if T > t2:
        area += cap * (T - t2)
    w_end = min(cap, max(vmin, c * math.sqrt(max(T - tau, 0.0))))
    return area / (ph.cfl * dx), w_end


def check_input(height: Grid) -> np.ndarray:
    h = height.channel(height.channels[0])
    if h.ndim != 2 or min(h.shape) < 3:
        raise InputError(f"erosion: the height grid must be 2-D with at least 3 x 3 cells, got {h.shape}")
    bad = ~np.isfinite(h)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(f"erosion: the input height has {int(bad.sum())} NaN or infinite cells (first at row {r}, "
                         f"column {c}); fix the heightmap before eroding it")
    if float(np.max(np.abs(h))) > 1e6:
        raise InputError(f"erosion: input heights reach {float(np.max(np.abs(h))):.3g} m; heights beyond 1e6 m are "
                         f"not terrain (wrong units?)")
    return np.ascontiguousarray(h, dtype=np.float32)


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


def geology(cl, h: np.ndarray, dx: float, params: ErosionParams, progress) -> tuple[np.ndarray, dict]:
    """Geological time on the terrain's cells, or on its own grid
    (geological_cell_m, coarse_grid.py): the heights after it (float32) and
    its metrics. On its own grid the solve runs on the f x f block means and
    its result comes back to the fine cells (FineGeology)."""
    from .coarse_grid import block_mean, coarse_factor

    fac = coarse_factor(h.shape[0], h.shape[1], dx, params.geological_cell_m)
    coarse = block_mean(h, fac) if fac > 1 else h.astype(np.float64)
    res = solve_geology(cl, coarse, dx * fac, params, progress)
    if fac == 1:
        return res.height.astype(np.float32), res.stats
    fine = FineGeology.of(res.height, coarse, fac, params, dx)
    return fine.heights(h, (0, 0) + h.shape), {**res.stats, "geological_cell_factor": fac,
                                                "geological_detail_kept": fine.keep}


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
                           incision_width_m=params.incision_width_m)
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
    cells, would otherwise come back on top of the eroded land)."""

    f: int
    change: Any  # Prolongation of the solved change (keep = 1)
    after: Any  # Prolongation of the solved heights (keep < 1)
    before: Any  # Prolongation of the block means (0 < keep < 1)
    keep: float

    @classmethod
    def of(cls, coarse_after: np.ndarray, coarse_before: np.ndarray, f: int, params: ErosionParams,
           dx: float) -> "FineGeology":
        from .coarse_grid import Prolongation

        D, t = params.hillslope_diffusivity_m2_per_year, params.geological_years
        keep = math.exp(-D * t * (math.pi / (f * dx)) ** 2)
        after = np.asarray(coarse_after, np.float64)
        if keep == 1.0:
            return cls(f, Prolongation.conserving(after - coarse_before, f), None, None, keep)
        before = Prolongation.conserving(coarse_before, f) if keep > 0.0 else None
        return cls(f, None, Prolongation.conserving(after, f), before, keep)

    def part(self, row0: int, col0: int, rows: int, cols: int) -> "FineGeology":
        """The coarse data fine cells [row0, +rows) x [col0, +cols) read (what a tile is sent)."""
        cut = lambda p: None if p is None else p.part(row0, col0, rows, cols)  # noqa: E731
        return FineGeology(self.f, cut(self.change), cut(self.after), cut(self.before), self.keep)

    def heights(self, h: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
        """The fine heights after geological time of the window's cells (h their input), float32."""
        if self.change is not None:
            return (h + self.change.window(*window)).astype(np.float32)
        fine = self.after.window(*window)
        if self.before is not None:
            fine += self.keep * (h - self.before.window(*window))
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


def _thermal_and_storm(cl, h: np.ndarray, params: ErosionParams, ph: Physics, plan: simulate.Plan,
                       progress, after_thermal) -> tuple[Any, dict[str, np.ndarray], dict]:
    """Thermal weathering on the terrain's cells, then the storm: on the same
    cells, or on the storm's own grid (coarse_grid.py) when the cells are finer
    than storm_cell_m. Returns the simulator of the storm (its OpenCL settings
    go to the metrics), the final fields on the terrain's cells (dT the change
    since h) and the metrics."""
    import dataclasses

    from .coarse_grid import block_mean, storm_factor
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
        h, geology_stats = geology(ctx.cl, h, dx, params, lambda f, m: ctx.progress(share * f, m))
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
    from .coarse_grid import coarse_factor

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
    uses_seed=False,
    uses_opencl=True,
)
