"""The erosion stage's parameters (ErosionParams) and what follows from
them on a grid of a given cell size: the physics, the run plan (talus-rule
iterations, storm limits), the channel threshold and the strata."""
from __future__ import annotations

import math
import os
from typing import Literal, Optional

from pipeline.contract import Param, Params
from pipeline.errors import InputError

from . import simulate
from .physics import G, THERMAL_C, Physics


MAX_THERMAL_ITERATIONS = 200_000  # talus-rule iterations before the storm, and bank-slumping ones during it


MAX_STEPS = 2_000_000  # storm steps a bake may take (max_steps: WORLDBAKE_MAX_STEPS overrides it)


MAX_GEOLOGICAL_STEPS = 10_000


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
    microrelief_rms_m: float = Param(
        0.1, units="m", description="where geological time runs on blocks of several cells: RMS height of the "
        "microrelief finer than the blocks (tree throw's pits and mounds, burrows), the steady state of random "
        "disturbances that creep flattens as they age (stages/erosion/microrelief.py), between microrelief_size_m "
        "and half the geology's cell. 0: the fine cells are the geology's smooth prolongation", ge=0.0, le=10.0)
    microrelief_size_m: float = Param(
        1.5, units="m", description="the microrelief's disturbances' size (the half-width of a fresh pit and mound; "
        "at least one cell is used)", gt=0.0, le=1000.0)
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
    landslide_round_sweeps: int = Param(
        0, units="sweeps", description="threshold landsliding: Jacobi sweeps rounding the cones of the 32-direction "
        "envelope toward round ones (eikonal, Godunov upwind; a sweep reaches one cell further from each foot, "
        "converged after as many sweeps as the longest hillslope has cells). Removes the fans of facets a close "
        "hillshade shows on big threshold cones; it raises the default world's grid anisotropy (0.92 -> 1.17 "
        "at 32, 0.99 at 128) and lowers a 1 m world's under an 8 m geology (1.35 -> 1.05 at 32): "
        "bench.landslide and the README. 0 turns it off", ge=0, le=100000)
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
