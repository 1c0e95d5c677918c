"""The ground albedo kernel (ground.cl) against its numpy reference
(reference.tile_albedo), on each OpenCL runtime and work-group size."""
from __future__ import annotations

import numpy as np
import pytest

from stages.world import ground, reference
from stages.world.ground_device import GroundAlbedo

pytestmark = pytest.mark.every_device


def _splat(rows, cols, seed=5):
    rng = np.random.default_rng(seed)
    w = rng.random((rows, cols, len(ground.SPLAT_ORDER))).astype(np.float32) ** 3
    return w / w.sum(axis=-1, keepdims=True)


@pytest.mark.parametrize("local", [None, (1, 1), (7, 3), (16, 4)])
def test_tile_albedo_equals_the_reference_and_is_deterministic(cl_env, local):
    splat = _splat(37, 53)  # rectangular, not a multiple of anything
    texel_m = 53 * 10.0 / (3 * 96)
    tables = ground.detail_tables(11, texel_m)
    baker = GroundAlbedo(cl_env, splat, tables, local=local)
    for u, v in ((0, 0), (2, 1), (1, 2)):
        ref = reference.tile_albedo(splat, 10.0, (-123.0, 45.5), 3, 96, u, v, tables, texel_m)
        got = baker.tile(10.0, (-123.0, 45.5), 3, 96, u, v, texel_m)
        # the same taps and detail texels; only the sum's rounding order differs (numpy's is a BLAS product)
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6)
        np.testing.assert_array_equal(got, GroundAlbedo(cl_env, splat, tables, local=(8, 8)).tile(
            10.0, (-123.0, 45.5), 3, 96, u, v, texel_m))


def test_the_splat_is_never_modified_and_the_overview_matches(cl_env):
    splat = _splat(16, 16)
    before = splat.copy()
    tables = ground.detail_tables(2, 160.0 / 32)
    got = GroundAlbedo(cl_env, splat, tables).tile(10.0, (0.0, 0.0), 1, 32, 0, 0, 160.0 / 32)
    np.testing.assert_array_equal(splat, before)
    np.testing.assert_allclose(got, reference.tile_albedo(splat, 10.0, (0.0, 0.0), 1, 32, 0, 0, tables, 160.0 / 32),
                               atol=2e-6)
