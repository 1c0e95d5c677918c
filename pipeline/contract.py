"""The stage contract: what a stage declares, as data.

A stage is a `Stage` value exported as `STAGE` from `stages/<name>/__init__.py`.
It declares its inputs, outputs and parameter schema; the engine builds the
graph, the cache keys and the validation from these declarations alone and
never looks inside a stage (landlab's `_info` and xarray-simlab's intents are
the models).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Callable, Literal

import pydantic

ArtifactKind = Literal["grid", "usd", "texture", "image", "json"]


_PLACEHOLDER = re.compile(r"\{([A-Za-z_]+)\}")
NAME_CHARS = r"[A-Za-z0-9_-]+"  # what a placeholder binds: the safe names of pipeline.config


def _placeholder(pattern: str) -> str:
    found = _PLACEHOLDER.findall(pattern)
    if len(found) != 1:
        raise ValueError(f"channel pattern {pattern!r} must hold exactly one {{placeholder}}")
    return found[0]


def _pattern_regex(pattern: str) -> re.Pattern:
    if "{" not in pattern:
        return re.compile(re.escape(pattern))
    head, tail = _PLACEHOLDER.split(pattern, maxsplit=1)[0::2]
    return re.compile(re.escape(head) + f"({NAME_CHARS})" + re.escape(tail))


@dataclass(frozen=True)
class Artifact:
    """One named artifact a stage writes.

    kind:
      grid   float32 raster (EXR, named channels), with cell size and origin in metres
      usd    a USD layer (.usda / .usdc) to be composed into the world; the stage
             writes it (and any files beside it) at ctx.path(name)
      texture  a mip-mapped EXR texture for a material, written by the stage
             (worldlib.images.write_texture) at ctx.path(name)
      image  a preview picture for people (PNG), never read by another stage
      json   small structured data (statistics, tables)
    """

    name: str  # "<stage>.<what>", e.g. "heightmap.height"
    kind: ArtifactKind
    file: str  # file name inside the artifact folder, e.g. "height.exr"
    description: str = ""
    # units of the values: one for all channels ("m"), or one per channel
    # pattern, comma-separated ("m^2, m^3/s")
    units: str = ""
    # EXR channel names for grids. A name with a {placeholder}
    # ("density.{species}") declares a channel set: the stage writes one
    # channel per pattern with that placeholder for each name it binds
    # (channel_sets checks the written channels against this).
    channels: tuple[str, ...] = ()
    dtype: str = "float32"
    shape: str = "terrain"  # shape rule: "terrain" = (rows, cols) of the terrain grid, "any"
    publish: bool = False  # a world root layer: the engine publishes it to build/worlds/<name>/
    nodata_nan: bool = False  # grids: NaN marks "no data" here; otherwise any NaN or Inf is a blow-up
    # usd/texture: glob patterns of the files the stage writes beside `file`
    # that belong to this artifact (the layers it references, say "*.usdc")
    beside: tuple[str, ...] = ()
    # the stage may return None for it (no file is written), e.g. per-species
    # maps when no species is placed; its consumers must take it as optional
    optional: bool = False

    def unit_list(self) -> tuple[str, ...]:
        """The units of each entry of `channels` (one for non-grids)."""
        parts = tuple(u.strip() for u in self.units.split(",")) if self.units else ("",)
        n = max(len(self.channels), 1)
        return parts * n if len(parts) == 1 else parts

    def expand(self, written: tuple[str, ...]) -> dict[str, str]:
        """The declared channels that `written` binds, each with its unit:
        the fixed names, and every pattern's set for each name whose set is
        complete in `written` (a pattern name could fit two sets: the
        complete one decides)."""
        written_set = set(written)
        units = dict(zip(self.channels, self.unit_list()))
        out = {c: units[c] for c in self.channels if "{" not in c}
        by_var: dict[str, list[str]] = {}
        for pat in (c for c in self.channels if "{" in c):
            by_var.setdefault(_placeholder(pat), []).append(pat)
        # a name that completes two sets takes the units of the larger (more specific) one: it comes last
        for var, pats in sorted(by_var.items(), key=lambda item: len(item[1])):
            bound = {m.group(1) for c in written for p in pats if (m := _pattern_regex(p).fullmatch(c))}
            for name in sorted(bound):
                full = {p.replace("{" + var + "}", name): units[p] for p in pats}
                if full.keys() <= written_set:
                    out.update(full)
        return out

    def channel_units(self, written: tuple[str, ...]) -> dict[str, str]:
        """The unit of each written channel (which must pass channel_sets)."""
        units = self.expand(written)
        return {c: units[c] for c in written if c in units}

    def channel_sets(self, written: tuple[str, ...]) -> str | None:
        """None when `written` is exactly the declared channels: every fixed
        name once, and for each placeholder every pattern with it for each
        name bound (a complete set per name); else what is wrong."""
        if len(set(written)) != len(written):
            return f"repeats a channel in {list(written)}"
        declared = self.expand(written)
        missing = sorted(c for c in self.channels if "{" not in c and c not in written)
        if missing:
            return f"misses the declared channels {missing}"
        extra = sorted(set(written) - declared.keys())
        if extra:
            return f"has channels {extra} that are not declared (declared: {list(self.channels)})"
        return None


@dataclass(frozen=True)
class Input:
    """An artifact a stage reads.

    `one_of` lists artifact names in order of preference: the first whose
    producer is enabled in the config is used. This is how "the latest
    available version" works: terrain height comes from erosion when erosion
    runs and from heightmap otherwise.
    """

    role: str  # the key under which run() receives it
    one_of: tuple[str, ...]
    optional: bool = False
    description: str = ""
    # grids: the channels this stage reads and their units (one for all, or
    # comma-separated per channel); the graph check holds every producer in
    # one_of to them
    channels: tuple[str, ...] = ()
    units: str = ""


# --------------------------------------------------------------------------- what a stage shows in the report

RGB = tuple[int, int, int]  # 8-bit sRGB


@dataclass(frozen=True)
class Relief:
    """Shading of a map by a terrain's relief: each pixel's colour times
    (1 - strength) + strength * light."""

    # a Grid of heights -> the light of each cell: float in [0, 1], or 8-bit
    # (grey or RGB, 255 is full light) as previews are
    shade: Callable[[Any], Any]
    one_of: tuple[str, ...]  # the grid of heights: the first of these artifacts the world holds
    channel: str  # its channel of heights
    strength: float = 0.45


@dataclass(frozen=True)
class ValueRange:
    """The values a map's colour ramp spans: fixed ends, the data's min or
    max where an end is None, or -m .. m with m a percentile of |value|."""

    lo: float | None = None
    hi: float | None = None
    symmetric_percentile: float | None = None


@dataclass(frozen=True)
class ReportMap:
    """A map of a channel of one of the stage's grids.

    `channel` may be a pattern ("density.{species}"): one map per channel
    of the grid it matches, in the grid's order. With `categories` the
    matched channels are weights and one map shows the category (the name
    the pattern binds) of the largest weight per cell, with a legend of each
    category's share. `name` (the picture is report_<name>.png), `title` and
    `note` may use {artifact}, {channel} and the pattern's placeholder. A
    map of a later stage with the same name replaces an earlier one (the
    terrain's height is erosion's when erosion runs)."""

    artifact: str
    channel: str
    name: str
    title: str
    palette: str | tuple[tuple[float, RGB], ...] = "terrain"  # one of pipeline.report.PALETTES, or ramp stops
    values: ValueRange = ValueRange()
    units: str | None = None  # None: the channel's declared units
    note: str = ""
    relief: Relief | None = None
    categories: tuple[tuple[str, RGB], ...] = ()  # category -> colour (unlisted ones are grey)


@dataclass(frozen=True)
class MapFrame:
    """What a drawn map draws on: the relief's light at the map's pixels
    ((rows, cols) in [0, 1], row 0 north), the world x, z of the map's
    north-west corner and the metres per pixel."""

    light: Any
    origin_m: tuple[float, float]
    metres_per_px: float


@dataclass(frozen=True)
class Drawn:
    """A drawn map: its pixels ((rows, cols, 3) uint8) and legend entries."""

    rgb: Any
    legend: tuple[tuple[RGB, str], ...] = ()


@dataclass(frozen=True)
class DrawnMap:
    """A map the stage draws from the composed world (its world.usda) over
    the relief: draw(world_usda, frame) -> Drawn."""

    name: str
    title: str
    draw: Callable[[Path, MapFrame], Drawn]
    relief: Relief


@dataclass(frozen=True)
class ReportPicture:
    """A picture of the composed world: make(world_usda, out_png, cl) writes
    the PNG and returns its caption; cl is the engine's OpenCL device
    (pipeline.opencl.CL)."""

    name: str  # the picture is report_<name>.png
    make: Callable[[Path, Path, Any], str]


@dataclass(frozen=True)
class Table:
    """Rows for the report. A cell is text, a number, None (shown as "-") or
    (number, note); the footer is a last row of headers (totals, say)."""

    columns: tuple[str, ...]
    rows: tuple[tuple[Any, ...], ...]
    footer: tuple[Any, ...] = ()
    note: str = ""


@dataclass(frozen=True)
class ReportTable:
    """A section of tables about the composed world: make(world_usda) ->
    tables (none: the section is left out)."""

    title: str
    make: Callable[[Path], tuple[Table, ...]]


@dataclass(frozen=True)
class ReportWarning:
    """A warning for each channel of one of the stage's grids matching
    `channel` (a name or a pattern) that is nowhere above zero; `message`
    may use {channel} and the pattern's placeholder."""

    artifact: str
    channel: str
    message: str


ReportItem = ReportMap | DrawnMap | ReportPicture | ReportTable | ReportWarning


@dataclass(frozen=True)
class Stage:
    name: str
    version: int
    description: str
    inputs: tuple[Input, ...]
    outputs: tuple[Artifact, ...]
    params: type[pydantic.BaseModel]
    run: Callable[["RunContext", dict[str, Any], Any], dict[str, Any]]
    source_dir: Path  # stages/<name>: its files and every project module they import are in the key (pipeline.sources)
    uses_seed: bool = False  # the config's seed is part of the key and given in ctx.seed
    uses_opencl: bool = False  # the OpenCL device is part of the key
    # Params that must hold the same value in every stage declaring them (the
    # terrain mesh lattice, say: rivers, plants and the ground must use the
    # same triangles). A config sets them once in [shared]; the engine copies
    # them into each declaring stage and refuses a config where they differ.
    shared_params: tuple[str, ...] = ()
    # Validation beyond the schema, run for every planned stage before any
    # stage runs (pipeline.bake.check_world): parse what the params hold,
    # open the files they name, and estimate the run's memory and work from
    # the params and the sizes of the input grids. Raises ParamError; returns
    # a Check. None: the schema is all there is to check.
    check: Callable[[Any, "CheckContext"], "Check"] | None = None
    # What the world's report.html shows of this stage beyond its row in the
    # stage table (pipeline.report lays it out): maps of its grids, pictures
    # and tables of the composed world, warnings.
    report: tuple["ReportItem", ...] = ()
    # The run on a tiled world ([tiling] tile_cells; pipeline.tiles): the
    # same signature as run, its grid inputs handles read by window
    # (pipeline.tiles.GridFile), ctx.tiles the TileRunner that maps its
    # per-tile functions; grid outputs may be TileArrays. Its artifacts are
    # the same bytes as run's. None: the stage runs whole on tiled worlds too.
    run_tiled: Callable[["RunContext", dict[str, Any], Any], dict[str, Any]] | None = None

    def output(self, name: str) -> Artifact:
        for a in self.outputs:
            if a.name == name:
                return a
        raise KeyError(f"stage {self.name} has no output {name}")


class Params(pydantic.BaseModel):
    """Base class of every stage's parameter schema: unknown keys are errors,
    values are validated on assignment, and `enabled` switches the stage."""

    model_config = pydantic.ConfigDict(extra="forbid", validate_assignment=True, frozen=True)

    enabled: bool = pydantic.Field(True, description="run this stage")


def Param(default: Any, *, units: str = "", description: str = "", **constraints: Any) -> Any:
    """A parameter with its units and valid range (ge/le/gt/lt) as data.
    The README's parameter tables are generated from these declarations."""
    return pydantic.Field(default, description=description, json_schema_extra={"units": units}, **constraints)


class ParamError(Exception):
    """A stage's check found a bad value: `key` is the param's dotted name
    inside the stage's table (e.g. "species.oak.lsystem.rules"), or "" when
    the message names the keys itself; the engine names the config file and
    the stage."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key, self.message = key, message


@dataclass(frozen=True)
class GridInfo:
    """What a check knows of a grid before it exists."""

    shape: tuple[int, int]
    cell_size_m: float
    set_by: str = ""  # the config key that sets the size, named when a run that reads it is too large


@dataclass(frozen=True)
class Check:
    """A stage's answer before it runs: the grids it will write (those of
    terrain shape default to its terrain input's), the peak memory it will
    hold and the work it will do, each with how it was estimated."""

    memory_bytes: float = 0.0
    memory_how: str = ""
    grids: dict[str, GridInfo] = field(default_factory=dict)  # artifact name -> size
    work_how: str = ""
    # the work of the run in work_unit (cell-steps, rays, texels: the stage's
    # documented unit), the most a run may do (0: no limit; pipeline.limits:
    # WORLDBAKE_MAX_WORK_SCALE multiplies it) and the param a refusal names
    # (dotted inside the stage's table; "": the stage's table)
    work: float = 0.0
    work_unit: str = ""
    work_limit: float = 0.0
    work_key: str = ""


@dataclass
class CheckContext:
    """What a stage's check may use."""

    seed: int
    project_root: Path
    inputs: dict[str, GridInfo]  # role -> size of each grid input the plan gives it
    tile_cells: int = 0  # the world tile a run_tiled stage holds at once ([tiling]); 0: it runs whole

    def resolve(self, project_path: str) -> Path:
        return self.project_root / project_path


@dataclass
class RunContext:
    """What a running stage may use besides its inputs and params."""

    stage: Stage
    key: str
    out_dir: Path
    seed: int
    provenance: dict[str, Any]
    project_root: Path
    progress: Callable[[float, str], None] = field(default=lambda f, m: None)
    metrics: dict[str, Any] = field(default_factory=dict)
    final_dir: Path | None = None  # where out_dir will be renamed to once the run is whole
    input_artifacts: dict[str, str] = field(default_factory=dict)  # role -> the artifact the plan chose for it
    units: Any = None  # pipeline.units.Units of this run (the engine's; None: nothing is reused)
    # The OpenCL device (pipeline.opencl.CL: context, queue, device) the
    # engine chose, for a stage declaring uses_opencl (None otherwise): the
    # device its key names. The stage passes it to the code that runs kernels.
    cl: Any = None
    tiles: Any = None  # pipeline.tiles.TileRunner of a tiled run (run_tiled); None otherwise

    def path(self, artifact_name: str) -> Path:
        """Where an output artifact's file goes."""
        return self.out_dir / self.stage.output(artifact_name).file

    def asset_path(self, target: Path) -> str:
        """A USD asset path from this stage's output folder to `target` (an
        input artifact's file), relative, valid once the run is moved into
        place: out_dir is a temporary folder at another depth."""
        from .usdio import relative_asset_path

        return relative_asset_path(target, (self.final_dir or self.out_dir) / "layer.usda")

    def unit(self, name: str, material: Any):
        """A part of this run that later runs may reuse (pipeline.units):
        `material` is everything the part depends on besides the stage's
        code (a content digest of what it reads, the params it uses)."""
        from .units import Units

        if self.units is None:
            self.units = Units(None, None, self.stage.name, {"stage": self.stage.name, "version": self.stage.version,
                                                             "seed": self.seed if self.stage.uses_seed else None})
        return self.units.unit(name, material)

    def resolve(self, project_path: str) -> Path:
        """The absolute path of a ProjectPath parameter (checked by the engine)."""
        return self.project_root / project_path


class _ProjectPathMarker:
    """Marks a parameter as a file path relative to the project root. The
    engine checks that it stays inside the project and exists, and hashes the
    file's bytes into the cache key (the path's text alone would not notice
    an edited file)."""


PROJECT_PATH = _ProjectPathMarker()
ProjectPath = Annotated[str, PROJECT_PATH]
