"""Per-instance colour variation: a multiplicative linear-RGB tint for every
instance, written on the PointInstancers as `primvars:tint` (color3f[],
interpolation vertex: one value per instance, the way USD gives primvars
per instance; Hydra/Storm, Houdini and Omniverse hand it to the prototype's
material). The plant materials read it with a UsdPrimvarReader (see
stages/plants/asset.py); it is near 1, so a renderer that ignores it shows
the textures as baked.

The tint has three parts, each a factor per channel:
- individual: counter-based random numbers of (seed, species, instance id):
  brightness within +-variation and a hue shift between yellow-green and
  blue-green (the same instance gets the same tint in every bake);
- site: dry ground gives olive, sun-bleached leaves, wet ground darker,
  bluer ones (moisture at the instance);
- age: young plants are lighter, yellower green until they mature.
"""
from __future__ import annotations

import numpy as np

from .reference import stream_key, uniform

# per channel direction of each effect (linear RGB, relative)
HUE_YELLOW = np.array([0.14, 0.05, -0.16])  # hue shift +1: yellower; -1: bluer
DRY = np.array([0.18, 0.06, -0.22])  # at moisture 0 (olive, bleached), opposite at moisture 1
YOUNG = np.array([0.10, 0.12, -0.05])  # a seedling is this much lighter / yellower than a mature plant
TINT_RANGE = (0.5, 1.6)


def instance_tints(seed: int, species: str, ids: np.ndarray, moisture: np.ndarray, age_years: np.ndarray,
                   maturity_years: float, variation: float) -> np.ndarray:
    """(n, 3) float32 multiplicative tints. ids: the instances' int64 ids
    (their random stream's counters); moisture 0..1 and age at each
    instance; variation: the relative amplitude (0: every tint is 1)."""
    ids = np.asarray(ids, np.int64)
    n = len(ids)
    if n == 0 or variation <= 0.0:
        return np.ones((n, 3), np.float32)
    key = stream_key(seed, "tint", species)
    lo = (ids & 0xFFFFFFFF).astype(np.uint32)
    hi = ((ids >> 32) & 0xFFFFFFFF).astype(np.uint32)
    u_bright = uniform(key, lo, hi, 0).astype(np.float64)
    u_hue = uniform(key, lo, hi, 1).astype(np.float64)
    bright = 1.0 + variation * (2.0 * u_bright - 1.0)
    hue = (2.0 * u_hue - 1.0)[:, None] * HUE_YELLOW[None, :]
    m = np.clip(np.nan_to_num(np.asarray(moisture, np.float64), nan=0.5), 0.0, 1.0)
    site = (1.0 - 2.0 * m)[:, None] * DRY[None, :]  # +1 dry .. -1 wet
    youth = np.clip(1.0 - np.asarray(age_years, np.float64) / max(maturity_years, 1e-6), 0.0, 1.0)
    young = youth[:, None] * YOUNG[None, :]
    tint = bright[:, None] * (1.0 + variation / 0.15 * (0.5 * hue + 0.5 * site) + young)
    return np.clip(tint, *TINT_RANGE).astype(np.float32)
