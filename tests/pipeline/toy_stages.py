"""Tiny stages for engine tests: fast, numpy only, same contract as real ones."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from pipeline import usdio
from pipeline.contract import Artifact, Input, Param, Params, ProjectPath, Stage
from pipeline.grid import Grid

HERE = Path(__file__).parent
CALLS: list[str] = []  # which stages actually ran, in order
HOOKS: dict = {}  # stage name -> a function called when it starts (tests of concurrency)


class SourceParams(Params):
    size: int = Param(8, ge=2, le=64, units="cells", description="cells per side")
    level_m: float = Param(1.0, ge=-100.0, le=100.0, units="m", description="base level")
    mode: Literal["ramp", "flat", "nan", "extra_file", "extra_channel"] = Param("ramp", description="what to generate")
    data: ProjectPath | None = Param(None, description="optional file whose bytes are added")


def run_source(ctx, inputs, params):
    CALLS.append("source")
    h = np.add.outer(np.arange(params.size), np.arange(params.size)).astype(np.float32) + params.level_m
    if params.mode == "flat":
        h[:] = params.level_m
    if params.mode == "nan":
        h[1, 2] = np.nan
    if params.data:
        h += len(ctx.resolve(params.data).read_bytes())
    h += ctx.seed % 7
    if params.mode == "extra_file":
        (ctx.out_dir / "notes.txt").write_text("not declared")
    if params.mode == "extra_channel":
        return {"source.height": Grid(np.stack([h, h], -1), 10.0, ("height", "height2"))}
    return {"source.height": Grid(h, 10.0)}


class ShiftParams(Params):
    amount_m: float = Param(0.5, ge=0.0, le=10.0, units="m", description="added height")
    fail_after_write: bool = Param(False, description="raise after writing a file (atomicity test)")


def run_shift(ctx, inputs, params):
    CALLS.append("shift")
    g = inputs["terrain"]
    if params.fail_after_write:
        (ctx.out_dir / "scratch.txt").write_text("half")
        raise RuntimeError("boom")
    return {"shift.height": Grid(g.data + np.float32(params.amount_m), g.cell_size_m)}


class AssembleParams(Params):
    label: str = Param("x", description="a label")


def run_assemble(ctx, inputs, params):
    CALLS.append("assemble")
    if "assemble" in HOOKS:
        HOOKS["assemble"]()
    stage, _ = usdio.create_stage(ctx.path("assemble.root"), ctx.provenance)
    stage.GetRootLayer().Save()
    # a part that depends on the label alone: reused while the terrain changes (pipeline.units)
    unit = ctx.unit("label", {"label": params.label})
    if unit.restore(ctx.out_dir) is None:
        CALLS.append("assemble.label")
        (ctx.out_dir / "label.txt").write_text(f"{params.label} {unit.provenance['unit_key']}\n")
        unit.save(ctx.out_dir, ["label.txt"], {"label": params.label})
    return {"assemble.root": ctx.path("assemble.root"),
            "assemble.stats": {"mean": float(inputs["terrain"].data.mean()), "label": params.label}}


TOY = {
    "source": Stage("source", 1, "toy source", (), (Artifact("source.height", "grid", "height.exr", channels=("height",), units="m"),),
                    SourceParams, run_source, HERE, uses_seed=True),
    "shift": Stage("shift", 1, "toy refinement", (Input("terrain", ("source.height",)),),
                   (Artifact("shift.height", "grid", "height.exr", channels=("height",), units="m"),), ShiftParams, run_shift, HERE),
    "assemble": Stage("assemble", 1, "toy world", (Input("terrain", ("shift.height", "source.height")),),
                      (Artifact("assemble.root", "usd", "world.usda", shape="any", publish=True, beside=("label.txt",)),
                       Artifact("assemble.stats", "json", "stats.json", shape="any")),
                      AssembleParams, run_assemble, HERE),
}
