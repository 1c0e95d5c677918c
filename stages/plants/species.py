"""The species schema: what a plant is, as data (TOML presets in configs/species/).

A species is either an L-system plant (`kind = "lsystem"`: axiom, rules,
iterations, angles, tropism, wood and leaf shape) or a grass tuft
(`kind = "grass"`: a set of Bezier blades, seeds 000 and 001).

Presets: every `configs/species/<name>.toml` is a SpeciesShape table and is
available by name. A world config refers to them as

    [plants]
    build = ["conifer", "grass"]                 # only these are meshed
    [plants.species.tallpine]                    # a new species from a preset
    preset = "conifer"                           # deep-merged under the keys below
    lsystem.iterations = 9
"""
from __future__ import annotations

import copy
import re
import tomllib
from pathlib import Path
from typing import Any, Literal, Optional

import pydantic

from pipeline.contract import Param
from pipeline.config import deep_merge

PRESET_DIR = Path(__file__).resolve().parents[2] / "configs" / "species"
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")

Vec3 = pydantic.conlist(float, min_length=3, max_length=3)
Colour = pydantic.conlist(pydantic.confloat(ge=0.0, le=1.0), min_length=3, max_length=3)


class Spec(pydantic.BaseModel):
    # NaN and Inf are refused in every number of a species (TOML can write them: nan, inf)
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Rule(Spec):
    """One production. `pred` is a module with formal parameters, e.g. "A(l,w)";
    `succ` a module string whose arguments are expressions in the formal
    parameters and the constants, e.g. "F(l) [+(30) A(l*0.8, w)] A(l*0.9, w)".
    `left`/`right` are context module strings (context-sensitive rules take
    precedence over context-free ones); `cond` a boolean expression; `p` the
    probability: matching rules of one predecessor are chosen by p, and with
    probability 1 - sum(p) the module stays as it is."""

    pred: str = Param(..., description="predecessor module, e.g. 'A' or 'A(l,w)'")
    succ: str = Param("", description="successor module string")
    p: float = Param(1.0, description="probability of this rule among the rules that match", ge=0.0, le=1.0)
    cond: str = Param("", description="condition on the formal parameters, e.g. 'l > 0.1'")
    left: str = Param("", description="left context, e.g. 'B' or 'B(x)'")
    right: str = Param("", description="right context")


class LSystemSpec(Spec):
    axiom: str = Param(..., description="start module string")
    rules: list[Rule] = Param([], description="productions")
    iterations: int = Param(4, units="", description="derivation steps", ge=0, le=64)
    angle: float = Param(25.0, units="deg", description="default turn angle of + - & ^ < > / \\", ge=0.0, le=360.0)
    length: float = Param(1.0, units="m", description="default segment length of F", ge=0.0, le=1000.0)
    constants: dict[str, float] = Param({}, description="named numbers usable in expressions")
    passive: str = Param("", description="symbols without rules and without turtle meaning that the strings may use (markers)")
    ignore: str = Param("+-&^<>/\\|$~t!?'\":;c.%", description="symbols skipped when matching contexts")
    angle_jitter: float = Param(0.0, units="deg", description="uniform random offset added to every turn (seeded)", ge=0.0, le=90.0)
    length_jitter: float = Param(0.0, units="", description="relative random change of every segment length (seeded)", ge=0.0, le=0.9)
    tropism: Vec3 = Param([0.0, -1.0, 0.0], units="", description="tropism direction T (gravity = [0,-1,0])")
    tropism_strength: float = Param(0.0, units="rad", description="bend per segment toward T: e |H x T| (ABOP)", ge=0.0, le=2.0)
    length_ratio: float = Param(0.9, units="", description="' multiplies the length by this, \" divides", gt=0.0, le=10.0)
    width_ratio: float = Param(0.7, units="", description="! multiplies the radius by this, ? divides", gt=0.0, le=10.0)
    angle_ratio: float = Param(0.9, units="", description=": multiplies the angle by this, ; divides", gt=0.0, le=10.0)

    @pydantic.field_validator("axiom")
    @classmethod
    def _axiom_not_empty(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("the axiom is empty: an L-system needs at least one module to start from")
        return v

    @pydantic.field_validator("rules", mode="before")
    @classmethod
    def _rule_strings(cls, v: Any) -> Any:
        """Accept Lparser-style 'A=succ' strings beside rule tables."""
        if isinstance(v, list):
            out = []
            for r in v:
                if isinstance(r, str):
                    if "=" not in r:
                        raise ValueError(f"rule {r!r} must be 'PRED=SUCC' or a table with pred and succ")
                    pred, succ = r.split("=", 1)
                    out.append({"pred": pred.strip(), "succ": succ.strip()})
                else:
                    out.append(r)
            return out
        return v


class WoodSpec(Spec):
    radius_model: Literal["pipe", "turtle"] = Param(
        "pipe", description="pipe: radii from the branching topology, r = tip_radius * n^(1/pipe_exponent) with n the tips "
        "downstream (da Vinci / pipe model); turtle: radii from the string (radius, ! and ?)")
    tip_radius: float = Param(0.004, units="m", description="pipe: radius of a terminal twig", ge=0.0, le=10.0)
    pipe_exponent: float = Param(2.5, units="", description="pipe: exponent e in r_parent^e = sum r_child^e", ge=1.0, le=4.0)
    leaf_weight: float = Param(0.2, units="", description="pipe: tips a leaf counts for", ge=0.0, le=10.0)
    radius: float = Param(0.1, units="m", description="turtle: initial radius", ge=0.0, le=100.0)
    max_edge: float = Param(0.03, units="m", description="target ring edge length; sides = clamp(2 pi r / max_edge)", gt=0.0, le=100.0)
    sides_min: int = Param(4, units="", description="fewest sides of a branch ring", ge=3, le=64)
    sides_max: int = Param(12, units="", description="most sides of a branch ring", ge=3, le=64)
    max_joint_angle: float = Param(
        50.0, units="deg", description="a turn sharper than this ends the tube and starts a new one (the union closes the joint)",
        ge=0.0, le=180.0)
    cap_bulge: float = Param(0.5, units="", description="end caps bulge forward by this times the radius", ge=0.0, le=2.0)
    bark_uv_length: float = Param(1.0, units="m", description="branch length per texture repeat along v", gt=0.0, le=1000.0)


class LeafSpec(Spec):
    shape: Literal["none", "card", "ellipse", "needles"] = Param(
        "none", description="card: a quad; ellipse: a folded leaf blade with a midrib; needles: a bundle of needles")
    length: float = Param(0.1, units="m", description="leaf length (needle length)", gt=0.0, le=100.0)
    width: float = Param(0.05, units="m", description="leaf width (needle width)", gt=0.0, le=100.0)
    petiole: float = Param(0.0, units="m", description="stalk length before the blade starts", ge=0.0, le=100.0)
    segments: int = Param(4, units="", description="ellipse: rows along the blade", ge=2, le=32)
    fold: float = Param(20.0, units="deg", description="ellipse: V-fold of the two halves about the midrib", ge=0.0, le=80.0)
    curl: float = Param(0.15, units="", description="droop of the tip as a fraction of the length", ge=-1.0, le=1.0)
    needles: int = Param(8, units="", description="needles: needles per bundle", ge=1, le=64)
    spread: float = Param(35.0, units="deg", description="needles: half-angle of the bundle cone", ge=0.0, le=90.0)
    size_jitter: float = Param(0.2, units="", description="relative random change of leaf size (seeded)", ge=0.0, le=0.9)


class FoliageSpec(Spec):
    """Foliage cards (seed 002): a cluster of `leaves_per_card` leaves of the
    [leaf] model on a short stem is rendered once into the species' card
    texture, and every L of the L-system carries one such card (two crossed
    ones if `crossed`). An optional flower head sits at the stem's tip."""

    cards: bool = Param(True, description="foliage as textured alpha-tested cards (false: one leaf mesh per L)")
    leaves_per_card: int = Param(7, units="", description="leaves (needle bundles) on one card's cluster", ge=1, le=64)
    stem_length: float = Param(0.2, units="m", description="length of the cluster's stem (the card's size follows)", gt=0.0, le=10.0)
    stem_width: float = Param(0.004, units="m", description="width of the cluster's stem", gt=0.0, le=1.0)
    leaf_start: float = Param(0.15, units="", description="share of the stem below the first leaf", ge=0.0, le=0.95)
    leaf_angle: float = Param(50.0, units="deg", description="angle between a leaf and the stem", ge=0.0, le=120.0)
    divergence: float = Param(137.5, units="deg", description="turn about the stem from one leaf to the next (180: two ranks, a flat spray)",
                              ge=0.0, le=360.0)
    taper: float = Param(0.3, units="", description="leaves near the stem's tip are smaller by this share", ge=0.0, le=0.9)
    crossed: bool = Param(True, description="two crossed cards per cluster (reads from the side), else one")
    flower_petals: int = Param(0, units="", description="petals of a flower head at the stem's tip (0: none)", ge=0, le=64)
    flower_petal_length: float = Param(0.02, units="m", description="petal length", gt=0.0, le=1.0)
    flower_color: Colour = Param([0.75, 0.7, 0.15], description="linear RGB of the petals")
    flower_center_color: Colour = Param([0.5, 0.3, 0.05], description="linear RGB of the flower's centre")


class GrassSpec(Spec):
    """Bezier blades (seed 000) on a round tuft footprint; the last LOD is the
    5-quad slice tuft of seed 001."""

    blades: int = Param(48, units="", description="blades per tuft", ge=1, le=20000)
    segments: int = Param(8, units="", description="blade segments n at LOD0 (2n-1 triangles per blade)", ge=1, le=10)
    width_min: float = Param(0.006, units="m", description="blade width at the root, smallest", gt=0.0, le=10.0)
    width_max: float = Param(0.012, units="m", description="blade width at the root, largest", gt=0.0, le=10.0)
    height_min: float = Param(0.2, units="m", description="blade height, smallest", gt=0.0, le=100.0)
    height_max: float = Param(0.45, units="m", description="blade height, largest", gt=0.0, le=100.0)
    bend: float = Param(0.25, units="", description="max tip offset b as a fraction of the blade height; offset = b(2R-1), R~U[0,1] "
                        "per axis (seed 000 eq. 2.2 with its one-sided lean bug fixed)", ge=0.0, le=2.0)
    control_xz: float = Param(0.25, units="", description="Bezier control point: horizontal share of the tip offset, +-", ge=0.0, le=1.0)
    control_y_min: float = Param(0.75, units="", description="Bezier control point height / blade height, smallest", ge=0.0, le=2.0)
    control_y_max: float = Param(0.9, units="", description="Bezier control point height / blade height, largest", ge=0.0, le=2.0)
    taper: float = Param(1.5, units="", description="width(t) = width (1 - t^taper) (seed 000's alpha silhouette)", gt=0.0, le=10.0)
    tuft_radius: float = Param(0.06, units="m", description="radius of the tuft footprint", ge=0.0, le=100.0)
    outward: float = Param(0.5, units="", description="share of the lean pointing away from the tuft centre", ge=0.0, le=1.0)


class SpeciesShape(Spec):
    kind: Literal["lsystem", "grass"] = Param("lsystem", description="an L-system plant or a grass tuft")
    description: str = Param("", description="free text")
    lsystem: Optional[LSystemSpec] = Param(None, description="the L-system (kind lsystem)")
    wood: WoodSpec = Param(WoodSpec(), description="branches")
    leaf: LeafSpec = Param(LeafSpec(), description="leaves")
    grass: Optional[GrassSpec] = Param(None, description="the blade set (kind grass)")
    foliage: FoliageSpec = Param(FoliageSpec(), description="foliage cards: the leaf cluster each L carries")
    bark_color: Colour = Param([0.32, 0.24, 0.17], description="linear RGB of the bark")
    leaf_color: Colour = Param([0.18, 0.38, 0.10], description="linear RGB of leaves (grass: at the root)")
    leaf_tip_color: Colour = Param([0.30, 0.55, 0.16], description="linear RGB at leaf and blade tips")
    roughness: float = Param(0.7, units="", description="UsdPreviewSurface roughness", ge=0.0, le=1.0)

    @pydantic.model_validator(mode="after")
    def _kind_has_its_table(self):
        if self.kind == "lsystem" and self.lsystem is None:
            raise ValueError("kind 'lsystem' needs an [lsystem] table (axiom, rules, iterations, angle)")
        if self.kind == "grass" and self.grass is None:
            raise ValueError("kind 'grass' needs a [grass] table")
        if self.grass is not None:
            g = self.grass
            if g.width_min > g.width_max or g.height_min > g.height_max or g.control_y_min > g.control_y_max:
                raise ValueError("grass: each *_min must be at most its *_max")
        if self.wood.sides_min > self.wood.sides_max:
            raise ValueError("wood: sides_min must be at most sides_max")
        return self


def preset_tables(directory: Path = PRESET_DIR) -> dict[str, dict]:
    """The raw tables of configs/species/*.toml, by file stem."""
    out = {}
    if directory.is_dir():
        for p in sorted(directory.glob("*.toml")):
            if NAME_RE.match(p.stem):
                with open(p, "rb") as f:
                    out[p.stem] = tomllib.load(f)
    return out


def resolve_species(given: dict[str, Any] | None, presets: dict[str, dict]) -> dict[str, Any]:
    """Presets plus the config's species; a table with `preset = NAME` is
    deep-merged over that preset. Raises ValueError naming what is allowed."""
    out: dict[str, Any] = {k: copy.deepcopy(v) for k, v in presets.items()}
    for name, table in (given or {}).items():
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise ValueError(f"species name {name!r} must be a USD prim name: a letter or _, then letters, digits, _")
        if isinstance(table, SpeciesShape):
            out[name] = table
            continue
        if not isinstance(table, dict):
            raise ValueError(f"species {name!r} must be a table, got {table!r}")
        table = dict(table)
        base = table.pop("preset", None)
        if base is not None:
            if base not in presets:
                raise ValueError(f"species {name!r}: preset {base!r} not found (presets: {', '.join(sorted(presets))})")
            table = deep_merge(presets[base], table)
        out[name] = table
    return out
