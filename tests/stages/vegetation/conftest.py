"""Shared fixtures: small synthetic terrains (fast on 2 cores)."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.opencl import get_cl


def synthetic_height(rows: int, cols: int, dx: float, seed: int = 0) -> np.ndarray:
    """Hills and valleys from about 300 to 1300 m with slopes from flat to
    about 60 degrees (median near 25), plus a little noise."""
    from scipy import ndimage

    z, x = np.meshgrid((np.arange(rows) + 0.5) * dx, (np.arange(cols) + 0.5) * dx, indexing="ij")
    h = 800 + 450 * np.sin(x / 330.0 + 0.3) * np.cos(z / 410.0) + 40 * np.sin(x / 61.0 + 1.0) * np.sin(z / 83.0)
    rng = np.random.default_rng(seed)
    h += 12 * ndimage.gaussian_filter(rng.standard_normal((rows, cols)), 2.0)
    return h.astype(np.float32)


def on_pocl(env) -> bool:
    return "portable computing language" in env.device.platform.name.lower()


@pytest.fixture(scope="session")
def pocl() -> bool:
    return on_pocl(get_cl())
