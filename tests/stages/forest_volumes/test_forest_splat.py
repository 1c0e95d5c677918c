"""The sector splat kernel against its numpy reference: equal sums (64-bit
fixed point) for every work-group size and on every device, and a splat
that keeps what each instance holds."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib.volumes import dense as volume
from stages.forest_volumes import reference, splat
from stages.forest_volumes.stage import _rotations

pytestmark = pytest.mark.every_device


@pytest.fixture(scope="module")
def scene():
    """A 6 x 5 x 4 source of random voxels (a third empty) and 40 turned,
    scaled instances, some of them beyond the grid's edge."""
    rng = np.random.default_rng(7)
    src = volume.empty_level((6, 5, 4), (-0.6, 0.0, -0.4), 0.2)
    src.density[...] = rng.random(src.density.shape) * (rng.random(src.density.shape) > 0.33)
    src.albedo[...] = src.density[..., None] * rng.random(src.albedo.shape)
    src.surface[...] = 2 * src.density
    n = rng.normal(size=src.normal.shape)
    src.normal[...] = 0.8 * n / np.linalg.norm(n, axis=-1, keepdims=True)
    pos = rng.random((40, 3)) * [6.0, 1.0, 6.0] - [0.5, 0.0, 0.5]
    q = rng.normal(size=(40, 4))
    return src, pos, _rotations(q), 0.5 + 2.5 * rng.random(40)


GRID = ((12, 6, 12), (0.0, -0.5, 0.0), 0.5)


def test_the_kernel_equals_the_reference_for_any_work_group(cl_env, scene):
    src, pos, rot, scale = scene
    ref = np.zeros((8, 12 * 6 * 12), np.int64)
    reference.splat(*GRID, src, pos, rot, scale, ref)
    assert (ref[0] > 0).sum() > 100
    for local in (1, 7, 64, None):
        dev = splat.DeviceSplat(cl_env, *GRID, local=local)
        dev.add(src, pos[:25], rot[:25], scale[:25])  # two launches into one sector
        dev.add(src, pos[25:], rot[25:], scale[25:])
        got = dev.result()
        # a deposit may round one unit (2^-40) apart where the device's float64 differs in the last bit
        assert np.abs(got - ref).max() <= 2, local
        if local == 1:
            first = got.copy()
        else:
            assert np.array_equal(got, first), local  # integer sums: the same for every work-group size


def test_the_splat_keeps_each_instance_s_projected_area(cl_env, scene):
    src, pos, rot, scale = scene
    dev = splat.DeviceSplat(cl_env, (32, 32, 32), (-5.0, -8.0, -5.0), 0.5)  # holds every instance whole
    dev.add(src, pos, rot, scale)
    total = dev.result()[0].sum() / splat.FIXED * 0.5 ** 3
    expect = (scale ** 2).sum() * src.density.astype(np.float64).sum() * src.voxel_m ** 3
    assert total == pytest.approx(expect, rel=1e-9)
