"""The vegetation stage's parameters: the world-wide settings and, per
species, its ecology (where it grows, how dense, how it competes).

Species are data. `[vegetation.species.NAME]` tables in a config add or
override species; the defaults are four species named like the plant presets
of configs/species/ (conifer, broadleaf, shrub, grass), so the plants stage
can mesh whatever this stage places. A table for a default species is merged
over the default (give only the keys that change); a new name must give
every key without a default. `grow` lists the species that take part (the
others are defined but cost nothing).

Preferences (altitude, slope, moisture, sunlight, curvature) are ranges with
soft edges: the factor is 0 outside [min, max], rises with a smoothstep over
`edge` inside each end and is 1 in between. Suitability is the product of
the five factors, and 0 under water.
"""
from __future__ import annotations

import copy
from typing import Any, Literal

import pydantic

from pipeline.contract import Param, Params
from pipeline.config import deep_merge

# The Poisson-disk sampler's saturation constant: after the default 6 passes
# a set of constant radius r holds at least KAPPA / r^2 points per m^2
# (tests/stages/vegetation/test_vegetation_placement.py checks it), and the
# radius is chosen so the saturated set holds 1 / FILL times the target; the
# selection keeps the target count out of it.
KAPPA = 0.60
FILL = 0.8
MAX_PLANT_SPECIES = 16
# No species grows on ground steeper than this: closed forest rarely stands
# above 35-40 deg, scattered trees reach about 45 deg and above 50 deg the
# ground is rock and scree (avalanche and protection forests: Bebi et al.
# 2009; Swiss NaiS guidelines, Frehner et al. 2005); a steeper slope_deg.max
# is refused.
MAX_SPECIES_SLOPE_DEG = 50.0


class Spec(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)


class Preference(Spec):
    """A preferred range with soft edges: factor 0 outside [min, max], a
    smoothstep over `edge` inside each end, 1 in between."""

    min: float = Param(..., description="lower end (factor 0 at and below it)")
    max: float = Param(..., description="upper end (factor 0 at and above it)")
    edge: float = Param(0.0, description="width of the soft edge inside each end (0: a hard edge)", ge=0.0)

    @pydantic.model_validator(mode="after")
    def _ordered(self):
        if not self.max > self.min:
            raise ValueError(f"max ({self.max:g}) must be above min ({self.min:g})")
        if 2.0 * self.edge > self.max - self.min:
            raise ValueError(f"edge ({self.edge:g}) must be at most half the range max - min ({self.max - self.min:g})")
        return self


class SpeciesEcology(Spec):
    kind: Literal["plant", "grass"] = Param(
        "plant", description="plant: individual instances from the ecosystem simulation and Poisson-disk placement; "
        "grass: a density and height field and jittered-grid tufts")
    altitude_m: Preference = Param(..., units="m", description="preferred altitude")
    slope_deg: Preference = Param(..., units="deg", description="preferred slope (max is the steepest slope it grows on)")
    moisture: Preference = Param(..., units="1", description="preferred moisture (0 dry .. 1 wet)")
    sunlight: Preference = Param(
        ..., units="1", description="preferred sunlight: mean insolation relative to open flat ground "
        "(direct sun with terrain shadows, plus diffuse sky light)")
    curvature_per_m: Preference = Param(
        Preference(min=-1.0, max=1.0, edge=0.0), units="1/m",
        description="preferred curvature (Laplacian of height; > 0 concave hollows, < 0 convex ridges)")
    density_per_ha: float = Param(
        ..., units="1/ha", description="plants (grass: tufts) per hectare on a fully suitable site the species holds "
        "alone; in a mixture it gets this times its relative yield from the ecosystem simulation",
        gt=0.0, le=1e6)
    min_spacing_m: float = Param(
        3.0, units="m", description="plant: smallest distance between two plants of the species (the Poisson-disk "
        "radius at the highest density; sparser places get a larger radius)", gt=0.0, le=1000.0)
    collision_radius_m: float = Param(
        0.5, units="m", description="plant: trunk clearance; two plants of different species are at least the sum "
        "of their collision radii apart. Species with a larger collision radius are placed first", ge=0.0, le=100.0)
    radius_m: float = Param(
        3.0, units="m", description="plant: radius of the sphere of influence at maturity (ecosystem competition, "
        "canopy cover)", gt=0.0, le=100.0)
    height_m: float = Param(
        5.0, units="m", description="height of the plant asset at scale 1 (the placeholder prototype has this height)",
        gt=0.0, le=200.0)
    scale_range: pydantic.conlist(pydantic.confloat(gt=0.0, le=100.0), min_length=2, max_length=2) = Param(
        [0.5, 1.5], units="", description="instance scale of the asset: [youngest, fully grown] (grass: [driest, "
        "lushest])")
    maturity_years: float = Param(
        30.0, units="years", description="plant: age at which it is fully grown and sheds seed", gt=0.0, le=5000.0)
    lifespan_years: float = Param(
        150.0, units="years", description="plant: mean age at death", gt=0.0, le=10000.0)
    lifespan_spread: float = Param(
        0.25, units="", description="plant: each plant's lifespan is lifespan_years * (1 +- spread), uniform",
        ge=0.0, le=0.9)
    shade_tolerance: float = Param(
        0.5, units="1/year", description="plant: probability per year of surviving domination (its sphere of "
        "influence overlaps a stronger plant's)", ge=0.0, le=1.0)
    seed_rate: float = Param(
        0.5, units="1/year", description="plant: seedlings a mature plant establishes per year on free, fully "
        "suitable ground", ge=0.0, le=1000.0)
    dispersal_m: float = Param(
        25.0, units="m", description="plant: seed dispersal distance (half-width of the seed shadow); short "
        "dispersal gives clusters", gt=0.0, le=10000.0)
    clustering: float = Param(
        0.0, units="", description="relative amplitude of a clumping noise on the density map (mean-preserving; "
        "0 none, 1 gaps and clumps)", ge=0.0, le=1.0)
    cluster_size_m: float = Param(100.0, units="m", description="wavelength of the clumping noise", gt=0.0, le=1e5)
    tilt_deg: float = Param(3.0, units="deg", description="largest random lean of an instance from the vertical", ge=0.0, le=45.0)
    tree: bool = Param(
        False, description="a tree: counted as forest (the forest by slope class of the stats and report) and "
        "kept out of avalanche paths and clearings, where shrubs, grass and herbs still grow")
    riparian: Preference = Param(
        Preference(min=-1.0, max=2.0, edge=0.0), units="1",
        description="preferred riparian index: 1 on the banks of rivers and lakes and on the flood-prone valley "
        "floor, 0 away from the water or high above it (see riparian_height_m, riparian_distance_m); the default "
        "range ignores it")

    @pydantic.model_validator(mode="after")
    def _consistent(self):
        if self.slope_deg.max > MAX_SPECIES_SLOPE_DEG:
            raise ValueError(
                f"slope_deg.max = {self.slope_deg.max:g} deg: no species grows on ground steeper than "
                f"{MAX_SPECIES_SLOPE_DEG:g} deg (closed forest rarely above 35-40 deg, scattered trees to about 45 deg, "
                "rock and scree above; the splat's rock_slope_* and scree_slope_* cover it)")
        if self.scale_range[1] < self.scale_range[0]:
            raise ValueError(f"scale_range {list(self.scale_range)} must be [smaller, larger]")
        if self.kind == "plant":
            feasible = KAPPA * FILL * 1e4 / self.min_spacing_m ** 2
            top = self.density_per_ha * (1.0 + self.clustering)
            if top > feasible:
                raise ValueError(
                    f"density_per_ha = {self.density_per_ha:g} (x (1 + clustering) = {top:g}) cannot be placed "
                    f"with min_spacing_m = {self.min_spacing_m:g} (at most {feasible:.4g} per ha); lower the "
                    f"density or min_spacing_m to at most {(KAPPA * FILL * 1e4 / top) ** 0.5:.3g} m")
            if self.collision_radius_m * 2.0 > self.min_spacing_m:
                raise ValueError(f"collision_radius_m = {self.collision_radius_m:g} is more than half of min_spacing_m "
                                 f"= {self.min_spacing_m:g}")
        return self


def _pref(lo, hi, edge):
    return {"min": lo, "max": hi, "edge": edge}


# Defaults for a temperate mountain range (heights about 200 .. 1500 m; the
# default world's configs/default.toml sets its own zones): spruce-like
# conifers from the valleys up to the tree line, broadleaves low and moist,
# shrubs everywhere up to the crests, grass in the open. Tree scales are
# relative to the plant presets (conifer about 5.5 m, broadleaf about 6 m,
# shrub 1.3 m, grass tuft 0.4 m).
# Slope limits (the stage's cell slope; the factor is 1 up to max - edge and
# 0 at max; min = -edge keeps the lower soft edge off flat ground): closed forest rarely stands on slopes over 35-40 deg and
# scattered trees reach about 45 deg (forestry slope classes: ground-based
# harvesting ends near 35 deg, cable yarding beyond; Bebi et al. 2009 and
# Frehner et al. 2005 on avalanche forests, whose release zones are the
# 30-50 deg slopes where the canopy is open); conifers (spruce, larch) hold
# the steepest ground, broadleaves (beech) less; shrubs (green alder, dwarf
# pine) and grass reach 50 deg, where rock and scree take over.
# Moisture: dry crests thin the conifers to half (the factor is 0.5 at
# moisture 0), waterlogged ground too (0.5 at 1).
# Banks (riparian index): spruce avoids the flooded soils of the bank zone
# (grey alder, willow and ash take them: the broadleaf and shrub species
# here), so the conifer's riparian preference ends at 0.6.
DEFAULT_SPECIES: dict[str, dict[str, Any]] = {
    "conifer": dict(
        altitude_m=_pref(500.0, 1480.0, 200.0), slope_deg=_pref(-10.0, 45.0, 10.0), moisture=_pref(-0.1, 1.1, 0.2),
        sunlight=_pref(0.15, 3.0, 0.15), riparian=_pref(-1.0, 0.6, 0.3), density_per_ha=80.0, min_spacing_m=4.5,
        collision_radius_m=1.0, radius_m=4.0, height_m=5.5, scale_range=[0.5, 3.2], maturity_years=40.0,
        lifespan_years=250.0, shade_tolerance=0.85, seed_rate=0.6, dispersal_m=30.0, clustering=0.3,
        cluster_size_m=150.0, tilt_deg=2.0, tree=True),
    "broadleaf": dict(
        altitude_m=_pref(100.0, 1100.0, 200.0), slope_deg=_pref(-10.0, 40.0, 10.0), moisture=_pref(0.2, 1.0, 0.2),
        sunlight=_pref(0.45, 3.0, 0.2), density_per_ha=70.0, min_spacing_m=5.0, collision_radius_m=1.2,
        radius_m=5.0, height_m=6.0, scale_range=[0.5, 3.3], maturity_years=30.0, lifespan_years=180.0,
        shade_tolerance=0.7, seed_rate=0.6, dispersal_m=25.0, clustering=0.3, cluster_size_m=120.0, tilt_deg=4.0,
        tree=True),
    "shrub": dict(
        altitude_m=_pref(100.0, 1560.0, 100.0), slope_deg=_pref(-10.0, 50.0, 10.0), moisture=_pref(0.0, 1.1, 0.1),
        sunlight=_pref(0.3, 3.0, 0.15), density_per_ha=100.0, min_spacing_m=3.0, collision_radius_m=0.5,
        radius_m=1.8, height_m=1.3, scale_range=[0.4, 1.3], maturity_years=8.0, lifespan_years=30.0,
        shade_tolerance=0.8, seed_rate=0.6, dispersal_m=12.0, clustering=0.4, cluster_size_m=60.0, tilt_deg=6.0),
    "grass": dict(
        kind="grass", altitude_m=_pref(0.0, 1600.0, 120.0), slope_deg=_pref(-10.0, 50.0, 10.0),
        moisture=_pref(0.02, 1.0, 0.1), sunlight=_pref(0.2, 3.0, 0.2), density_per_ha=400.0,
        height_m=0.4, scale_range=[0.6, 1.4], clustering=0.3, cluster_size_m=40.0, tilt_deg=8.0),
}


def resolve_species(tables: Any) -> Any:
    """The config's species tables merged over the defaults (a default
    species' table needs only the keys that change)."""
    if not isinstance(tables, dict):
        return tables
    out = {k: copy.deepcopy(v) for k, v in DEFAULT_SPECIES.items()}
    for name, table in tables.items():
        if isinstance(table, SpeciesEcology):
            out[name] = table
            continue
        if not isinstance(table, dict):
            out[name] = table  # pydantic reports the type error
            continue
        out[name] = deep_merge(DEFAULT_SPECIES[name], table) if name in DEFAULT_SPECIES else table
    return out


def _default_species() -> dict[str, SpeciesEcology]:
    return {k: SpeciesEcology.model_validate(v) for k, v in DEFAULT_SPECIES.items()}


class VegetationParams(Params):
    species: dict[str, SpeciesEcology] = Param(
        _default_species(), description="species by name (tables [vegetation.species.NAME]); the defaults conifer, "
        "broadleaf, shrub and grass match the plant presets; a table for a default species overrides only its keys")
    grow: list[str] = Param(
        sorted(DEFAULT_SPECIES), description="the species that take part in this world (the others are defined but "
        "cost nothing); at most one of kind grass")
    # local attributes
    latitude_deg: float = Param(46.0, units="deg", description="latitude of the world, for the sun's path", ge=-89.0, le=89.0)
    diffuse_fraction: float = Param(
        0.3, units="", description="share of sunlight that is diffuse sky light (weighted by sky view), the rest is "
        "direct sun", ge=0.0, le=1.0)
    horizon_directions: int = Param(12, units="", description="azimuths of the horizon scan (sky view, sun shadows)", ge=4, le=64)
    horizon_distance_m: float = Param(1500.0, units="m", description="how far the horizon scan looks", gt=0.0, le=1e6)
    horizon_step_growth: float = Param(
        1.3, units="", description="each horizon sample is this much farther than the one before (the first is one "
        "cell away)", gt=1.0, le=4.0)
    curvature_scale_m: float = Param(24.0, units="m", description="length over which curvature (Laplacian) is measured", gt=0.0, le=1e4)
    moisture_fallback_radius_m: float = Param(
        200.0, units="m", description="without hydrology or erosion moisture: moisture from the topographic position "
        "(height below the mean within this radius)", gt=0.0, le=1e5)
    moisture_fallback_scale_m: float = Param(
        40.0, units="m", description="without hydrology: a cell this far below its surroundings has moisture 1, this "
        "far above 0", gt=0.0, le=1e4)
    # sites: tree line by aspect, banks, avalanche paths, clearings (sites.py)
    treeline_aspect_shift_m: float = Param(
        150.0, units="m", description="how much higher every species' altitude range lies on a steep sun-facing "
        "slope than on a steep shaded one (south- against north-facing in the northern hemisphere; half of it up, "
        "half down, less on gentler ground, none on the flat): tree lines on sunny slopes are typically 100-200 m "
        "higher (Holtmeier 2009; Koerner 2012)", ge=0.0, le=2000.0)
    riparian_height_m: float = Param(
        3.0, units="m", description="the riparian index falls from 1 at the water's level to 0 this high above the "
        "nearest river or lake (the flood-prone banks and valley floor, a height above the nearest drainage)",
        gt=0.0, le=1000.0)
    riparian_distance_m: float = Param(
        60.0, units="m", description="the riparian index falls to 0 this far from the river's edge (half its "
        "width from its centre line) or the lake shore", gt=0.0, le=1e5)
    avalanche_release_min_m: float = Param(
        1150.0, units="m", description="avalanches release only above this altitude (enough snow)",
        ge=-11000.0, le=9000.0)
    avalanche_release_slope_min_deg: float = Param(
        30.0, units="deg", description="gentlest release slope (slab avalanches release on 30-50 deg slopes: "
        "Schweizer et al. 2003; McClung and Schaerer 2006)", ge=0.0, le=90.0)
    avalanche_release_slope_max_deg: float = Param(
        50.0, units="deg", description="steepest release slope (steeper ground sheds its snow in small sluffs)",
        ge=0.0, le=90.0)
    avalanche_release_share: float = Param(
        0.3, units="", description="share of the possible release area (altitude and slope) where avalanches "
        "release: patches of a counter-based noise of wavelength avalanche_release_patch_m; 0: no avalanches",
        ge=0.0, le=1.0)
    avalanche_release_patch_m: float = Param(
        300.0, units="m", description="wavelength of the noise that picks the release patches", gt=0.0, le=1e5)
    avalanche_alpha_deg: float = Param(
        26.0, units="deg", description="run-out angle: an avalanche runs down the steepest descent from its "
        "release until the line at this angle below the horizontal from its release meets the ground (the alpha "
        "angle of the alpha-beta model, Lied and Bakkehoi 1980: about 20-30 deg for large paths)",
        gt=5.0, le=60.0)
    avalanche_track_width_m: float = Param(
        40.0, units="m", description="width of the tree-free track along an avalanche's flow line (a soft edge as "
        "wide again); typical tracks are 20-100 m wide", ge=0.0, le=1e4)
    clearing_share: float = Param(
        0.06, units="", description="share of the land in clearings (windthrow, fire, old pastures: natural "
        "gaps and disturbance patches) where no tree grows; patches of a counter-based noise; 0: none",
        ge=0.0, le=0.9)
    clearing_size_m: float = Param(
        250.0, units="m", description="wavelength of the clearing noise: clearings are about a third of it across",
        gt=0.0, le=1e5)
    # ecosystem simulation
    years: int = Param(100, units="years", description="years of the ecosystem simulation (seeding, growth, "
                       "self-thinning, death by age)", ge=0, le=100000)
    step_years: int = Param(
        5, units="years", description="years per simulation step (per-year probabilities are compounded; the run "
        "has years // step_years steps)", ge=1, le=100)
    sim_cell_m: float = Param(
        8.0, units="m", description="cell of the simulation grid (at most one plant per cell); coarser is faster",
        gt=0.0, le=1000.0)
    initial_density_per_ha: float = Param(
        1000.0, units="1/ha", description="plants of random species (in proportion to suitability) and random age at "
        "the start, at most one per simulation cell; the population starts large and thins itself", ge=0.0, le=1e6)
    background_seed_per_ha: float = Param(
        0.5, units="1/(ha year)", description="seedlings from far away per hectare and year (every species, on free "
        "suitable ground), so isolated places are colonised", ge=0.0, le=1e4)
    stress_mortality: float = Param(
        0.01, units="1/year", description="extra death rate of a plant on an unsuitable site: rate * (1 - "
        "suitability) per year", ge=0.0, le=1.0)
    share_radius_m: float = Param(
        40.0, units="m", description="radius over which simulated plants are counted for each species' relative "
        "yield (its density in the mixture over the density it reaches alone)", ge=0.0, le=1e5)
    # placement
    poisson_passes: int = Param(
        6, units="", description="dart-throwing passes of the Poisson-disk sampler (fewer than 4 leave too few "
        "candidates for the densest targets: shortfalls are reported)", ge=1, le=64)
    density_block_m: float = Param(
        128.0, units="m", description="block over which the placed count is matched to the target count (stochastic "
        "rounding per block)", gt=0.0, le=1e5)
    # grass
    grass_max_tufts: int = Param(
        300000, units="tufts", description="cap on written grass tufts; the tuft spacing grows to stay under it", ge=0, le=100_000_000)
    grass_canopy_shade: float = Param(
        0.8, units="", description="how much full tree canopy cover thins the grass (0 not at all, 1 none under trees)", ge=0.0, le=1.0)
    grass_jitter: float = Param(
        0.8, units="", description="tuft jitter as a share of the tuft spacing (tufts are at least (1 - jitter) * "
        "spacing apart)", ge=0.0, le=1.0)
    tint_variation: float = Param(
        0.15, units="", description="per-instance colour variation: relative amplitude of each instance's tint "
        "(primvars:tint on the PointInstancers: random brightness and hue, drier sites olive, young plants lighter; "
        "0: every tint is 1)", ge=0.0, le=0.5)
    # terrain splat weights (seed 004, both defects fixed)
    snow_min_m: float = Param(1350.0, units="m", description="snow starts at this altitude", ge=-11000.0, le=9000.0)
    snow_max_m: float = Param(1500.0, units="m", description="full snow above this altitude", ge=-11000.0, le=9000.0)
    snow_slope_deg: float = Param(45.0, units="deg", description="snow slides off slopes steeper than this", ge=0.0, le=90.0)
    snow_melt: float = Param(1.0, units="", description="how much moisture melts snow", ge=0.0, le=100.0)
    rock_slope_min_deg: float = Param(42.0, units="deg", description="rock starts showing at this slope", ge=0.0, le=90.0)
    rock_slope_max_deg: float = Param(58.0, units="deg", description="bare rock from this slope", ge=0.0, le=90.0)
    rock_min_m: float = Param(1450.0, units="m", description="rock starts showing at this altitude", ge=-11000.0, le=9000.0)
    rock_max_m: float = Param(1700.0, units="m", description="bare rock above this altitude", ge=-11000.0, le=9000.0)
    scree_slope_min_deg: float = Param(32.0, units="deg", description="scree starts at this slope", ge=0.0, le=90.0)
    scree_slope_max_deg: float = Param(45.0, units="deg", description="full scree from this slope (where not rock)", ge=0.0, le=90.0)
    mud_moisture: float = Param(0.85, units="", description="moisture above which the ground turns to mud", ge=0.0, le=1.0)
    mud_slope_deg: float = Param(12.0, units="deg", description="mud only on slopes gentler than this", ge=0.0, le=90.0)
    dry_moisture: float = Param(0.35, units="", description="grass is dry below this moisture and green above it", ge=0.0, le=1.0)
    alpine_min_m: float = Param(1100.0, units="m", description="grass turns green (alpine meadow) from this altitude", ge=-11000.0, le=9000.0)
    alpine_max_m: float = Param(1400.0, units="m", description="grass fully green above this altitude", ge=-11000.0, le=9000.0)
    moisture_jitter_m: float = Param(
        8.0, units="m", description="jitter of the 3x3 moisture filter of the splat weights (seed 004, normalised "
        "by the sum of its weights)", ge=0.0, le=1e4)
    # output
    mesh_max_vertices: int = Param(
        1025, units="vertices", description="terrain mesh vertices per side the instances sit on: the world's "
        "mesh_max_vertices", ge=2, le=8193)
    tile_max_instances: int = Param(
        20000, units="instances", description="quadtree tiles are split until each holds at most this many instances",
        ge=1, le=10_000_000)
    tile_min_size_m: float = Param(256.0, units="m", description="quadtree tiles are not split below this size", gt=0.0, le=1e6)

    @pydantic.model_validator(mode="before")
    @classmethod
    def _merge_species(cls, data: Any) -> Any:
        if isinstance(data, dict) and "species" in data:
            data = dict(data)
            data["species"] = resolve_species(data["species"])
        return data

    @pydantic.field_validator("species")
    @classmethod
    def _names(cls, v: dict[str, SpeciesEcology]) -> dict[str, SpeciesEcology]:
        import re

        for name in v:
            if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,63}", name):
                raise ValueError(f"species name {name!r} must be letters, digits and _ (a USD prim name)")
        return v

    @pydantic.field_validator("grow")
    @classmethod
    def _grow(cls, v: list[str], info: pydantic.ValidationInfo) -> list[str]:
        species = info.data.get("species")
        if species is None:
            return v
        unknown = [n for n in v if n not in species]
        if unknown:
            raise ValueError(f"grow names unknown species {unknown}; defined: {', '.join(sorted(species))}")
        if len(set(v)) != len(v):
            raise ValueError("grow lists a species twice")
        if sum(1 for n in v if species[n].kind == "plant") > MAX_PLANT_SPECIES:
            raise ValueError(f"at most {MAX_PLANT_SPECIES} species of kind plant")
        if sum(1 for n in v if species[n].kind == "grass") > 1:
            raise ValueError("at most one species of kind grass")
        return v

    @pydantic.model_validator(mode="after")
    def _ranges(self):
        for lo, hi in (("snow_min_m", "snow_max_m"), ("rock_slope_min_deg", "rock_slope_max_deg"),
                       ("rock_min_m", "rock_max_m"), ("scree_slope_min_deg", "scree_slope_max_deg"),
                       ("alpine_min_m", "alpine_max_m"),
                       ("avalanche_release_slope_min_deg", "avalanche_release_slope_max_deg")):
            if not getattr(self, hi) > getattr(self, lo):
                raise ValueError(f"{hi} ({getattr(self, hi):g}) must be above {lo} ({getattr(self, lo):g})")
        return self

    def plant_species(self) -> list[str]:
        """The growing species of kind plant, in `grow` order."""
        return [n for n in self.grow if self.species[n].kind == "plant"]

    def grass_species(self) -> str | None:
        return next((n for n in self.grow if self.species[n].kind == "grass"), None)


# the order of the preferences in the suitability kernel's table
NPREF_ORDER = ("altitude_m", "slope_deg", "moisture", "sunlight", "curvature_per_m")
