"""Small worlds and a stage runner for the erosion tests."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.contract import RunContext
from pipeline.grid import Grid
from pipeline.opencl import get_cl
from stages.erosion import STAGE, ErosionParams
from stages.erosion.physics import Physics
from stages.erosion.reference import synthetic_world

# physics of a short, strong storm on small grids (SI units)
STORM = dict(rain=100e-3 / 3600, evaporation=2e-3 / 3600, friction=0.3, capacity=3.0,
             min_slope_sin=math.sin(math.radians(2.0)), dissolve_rate=0.5, deposit_rate=0.5)


def world(n: int = 64, size_m: float = 2000.0, relief_m: float = 300.0, seed: int = 7) -> tuple[np.ndarray, float]:
    """A small analytic mountain world and its cell size."""
    return synthetic_world(n, size_m=size_m, relief_m=relief_m, seed=seed, min_wavelength_m=size_m / 32), size_m / n


def physics(dx: float, boundary: str = "closed", **over) -> Physics:
    kw = dict(STORM)
    kw.update(over)
    return Physics(dx=dx, boundary=boundary, **kw)


def run_stage(height: np.ndarray, dx: float, tmp_path: Path, **params):
    """STAGE.run on a height array; returns (outputs, metrics, progress calls)."""
    calls = []
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="test", out_dir=tmp_path, seed=0, provenance={}, project_root=tmp_path,
                     progress=lambda f, m: calls.append((f, m)))
    out = STAGE.run(ctx, {"height": Grid(np.asarray(height, np.float32), cell_size_m=dx)}, ErosionParams(**params))
    return out, ctx.metrics, calls
