"""The ground albedo kernel (ground.cl) against its numpy reference
(reference.tile_albedo), on each OpenCL runtime and work-group size."""
from __future__ import annotations

import numpy as np
import pytest

from stages.world import ground, reference
from stages.world.ground_device import GroundAlbedo

pytestmark = pytest.mark.every_device


def _baker(cl_env, splat, tables, **kw):
    """GroundAlbedo reading its windows of `splat`."""
    return GroundAlbedo(cl_env, lambda r0, c0, rows, cols: splat[r0:r0 + rows, c0:c0 + cols], splat.shape, tables,
                        **kw)


def _splat(rows, cols, seed=5):
    rng = np.random.default_rng(seed)
    w = rng.random((rows, cols, len(ground.SPLAT_ORDER))).astype(np.float32) ** 3
    return w / w.sum(axis=-1, keepdims=True)


@pytest.mark.parametrize("local", [None, (1, 1), (7, 3), (16, 4)])
def test_tile_albedo_equals_the_reference_and_is_deterministic(cl_env, local):
    splat = _splat(37, 53)  # rectangular, not a multiple of anything
    texel_m = 53 * 10.0 / (3 * 96)
    tables = ground.detail_tables(11, texel_m)
    baker = _baker(cl_env, splat, tables, local=local)
    for u, v in ((0, 0), (2, 1), (1, 2)):
        ref = reference.tile_albedo(splat, 10.0, (-123.0, 45.5), 3, 96, u, v, tables, texel_m)
        got = baker.tile(10.0, (-123.0, 45.5), 3, 96, u, v, texel_m)
        # the same taps and detail texels; only the sum's rounding order differs (numpy's is a BLAS product)
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6)
        np.testing.assert_array_equal(got, _baker(cl_env, splat, tables, local=(8, 8)).tile(
            10.0, (-123.0, 45.5), 3, 96, u, v, texel_m))


def test_the_splat_is_never_modified_and_the_overview_matches(cl_env):
    splat = _splat(16, 16)
    before = splat.copy()
    tables = ground.detail_tables(2, 160.0 / 32)
    got = _baker(cl_env, splat, tables).tile(10.0, (0.0, 0.0), 1, 32, 0, 0, 160.0 / 32)
    np.testing.assert_array_equal(splat, before)
    np.testing.assert_allclose(got, reference.tile_albedo(splat, 10.0, (0.0, 0.0), 1, 32, 0, 0, tables, 160.0 / 32),
                               atol=2e-6)


def test_bands_of_texel_rows_read_windows_and_give_the_whole_tile(cl_env):
    """A small window budget cuts the tile into bands of a few texel rows,
    each reading only its cells: the same texels, bit for bit."""
    splat = _splat(61, 47)
    texel_m = 47 * 10.0 / (2 * 80)
    tables = ground.detail_tables(3, texel_m)
    windows = []

    def read(r0, c0, rows, cols):
        windows.append((r0, c0, rows, cols))
        return splat[r0:r0 + rows, c0:c0 + cols]

    whole = _baker(cl_env, splat, tables).tile(10.0, (5.0, -7.0), 2, 80, 1, 0, texel_m)
    banded = GroundAlbedo(cl_env, read, splat.shape, tables, window_bytes=6 * 4 * 30 * 8).tile(
        10.0, (5.0, -7.0), 2, 80, 1, 0, texel_m)
    np.testing.assert_array_equal(banded, whole)
    assert len(windows) >= 4 and max(w[2] for w in windows) <= 10 and all(w[3] < 47 for w in windows)
