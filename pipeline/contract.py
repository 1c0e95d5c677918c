"""The stage contract: what a stage declares, as data.

A stage is a `Stage` value exported as `STAGE` from `stages/<name>/__init__.py`.
It declares its inputs, outputs and parameter schema; the engine builds the
graph, the cache keys and the validation from these declarations alone and
never looks inside a stage (landlab's `_info` and xarray-simlab's intents are
the models).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Callable, Literal

import pydantic

ArtifactKind = Literal["grid", "usd", "texture", "image", "json"]


@dataclass(frozen=True)
class Artifact:
    """One named artifact a stage writes.

    kind:
      grid   float32 raster (EXR, named channels), with cell size and origin in metres
      usd    a USD layer (.usda / .usdc) to be composed into the world; the stage
             writes it (and any files beside it) at ctx.path(name)
      texture  a mip-mapped EXR texture for a material, written by the stage
             (pipeline.exr.write_texture) at ctx.path(name)
      image  a preview picture for people (PNG), never read by another stage
      json   small structured data (statistics, tables)
    """

    name: str  # "<stage>.<what>", e.g. "heightmap.height"
    kind: ArtifactKind
    file: str  # file name inside the artifact folder, e.g. "height.exr"
    description: str = ""
    units: str = ""  # units of the values, e.g. "m"
    channels: tuple[str, ...] = ()  # EXR channel names for grids
    dtype: str = "float32"
    shape: str = "terrain"  # shape rule: "terrain" = (rows, cols) of the terrain grid, "any"
    publish: bool = False  # a world root layer: the engine publishes it to build/worlds/<name>/
    nodata_nan: bool = False  # grids: NaN marks "no data" here; otherwise any NaN or Inf is a blow-up


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

    def path(self, artifact_name: str) -> Path:
        """Where an output artifact's file goes."""
        return self.out_dir / self.stage.output(artifact_name).file

    def asset_path(self, target: Path) -> str:
        """A USD asset path from this stage's output folder to `target` (an
        input artifact's file), relative, valid once the run is moved into
        place: out_dir is a temporary folder at another depth."""
        from .usdio import relative_asset_path

        return relative_asset_path(target, (self.final_dir or self.out_dir) / "layer.usda")

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
