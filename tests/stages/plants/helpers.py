"""Helpers shared by the plants tests: a small stage run."""
from pathlib import Path

from pipeline.config import canonical_params
from pipeline.contract import RunContext
from pipeline.opencl import get_cl
from stages.plants import STAGE
from stages.plants.stage import PlantsParams


SMALL = {"build": ["grass", "bush"], "hausdorff_samples": 3000,
         "species": {"bush": {"preset": "shrub", "lsystem": {"iterations": 4}}}}


def run_stage(tmp: Path, params: dict, seed: int = 1):
    tmp.mkdir(parents=True, exist_ok=True)
    p = PlantsParams.model_validate(params, strict=True)
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="test", out_dir=tmp, seed=seed,
                     provenance={"stage": "plants", "version": 1, "key": "test", "params": canonical_params(p), "seed": seed},
                     project_root=Path("."))
    out = STAGE.run(ctx, {}, p)
    return out, ctx
