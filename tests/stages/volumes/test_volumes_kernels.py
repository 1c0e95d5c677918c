"""The volume kernels against their numpy references on tiny scenes and
grids: equal, deterministic, independent of the work-group size; and the
voxelization's physics: the alpha test, the solid's volume, the mips."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib.volumes import dense as volume
from worldlib.render import Camera
from stages.volumes import device, error, reference
from stages.volumes.samples import sample_table
from stages.volumes.voxelize import plant_grid, voxelize

from .scenes import trunk_and_card

pytestmark = pytest.mark.every_device


@pytest.fixture(scope="module")
def tiny():
    scene, parts = trunk_and_card()
    return scene, parts, plant_grid(scene, 16, 3)


def test_surface_samples_equal_the_reference_for_any_work_group(cl_env, tiny):
    scene, _, grid = tiny
    table = sample_table(scene, np.arange(scene.n_triangles), grid.voxel)
    ref = reference.surface_samples(table, grid, scene.textures, 0.5)
    for local in (None, 1, 7, 64):
        dev = device.surface_samples(cl_env, table, grid, scene.textures, 0.5, local=local)
        assert np.array_equal(dev.voxel, ref.voxel)
        for name in ("weight", "rgb", "normal"):
            np.testing.assert_allclose(getattr(dev, name), getattr(ref, name), rtol=1e-12, atol=1e-15)


def test_surface_sums_equal_the_reference_s_samples_summed_for_any_work_group(cl_env, tiny):
    from stages.volumes.samples import SurfaceSums

    scene, _, grid = tiny
    table = sample_table(scene, np.arange(scene.n_triangles), grid.voxel / 2)
    ref = SurfaceSums.zeros(grid.count)
    ref.add(reference.surface_samples(table, grid, scene.textures, 0.5))
    first = None
    for local in (1, 7, 64, None):
        got = device.surface_sums(cl_env, table, grid, scene.textures, 0.5, local=local)
        for name in ("area", "rgb", "normal"):
            # each sample rounds to 2^-40 m^2; the samples of a triangle share one weight, so they round alike
            np.testing.assert_allclose(getattr(got, name), getattr(ref, name), rtol=1e-7, atol=1e-12)
        if first is None:
            first = got
        for name in ("area", "rgb", "normal"):  # integer sums: the same bits for every work-group size
            assert np.array_equal(getattr(got, name), getattr(first, name)), (local, name)
    assert (ref.area > 0).sum() > 20


def test_voxelization_is_deterministic_and_equals_the_reference(cl_env, tiny):
    scene, parts, _ = tiny
    a = voxelize(cl_env, scene, parts, 8, 2, samples_per_voxel=1.5)
    b = voxelize(cl_env, scene, parts, 8, 2, samples_per_voxel=1.5)
    r = voxelize(None, scene, parts, 8, 2, samples_per_voxel=1.5)
    for name in ("density", "albedo", "normal", "surface"):
        assert np.array_equal(getattr(a.level, name), getattr(b.level, name))
        np.testing.assert_allclose(getattr(a.level, name), getattr(r.level, name), rtol=1e-6, atol=1e-6)


def test_the_alpha_test_keeps_only_the_opaque_half_of_the_card(cl_env, tiny):
    scene, _, grid = tiny
    table = sample_table(scene, np.array([12, 13]), grid.voxel / 3)
    s = device.surface_samples(cl_env, table, grid, scene.textures, 0.5)
    assert s.weight.sum() == pytest.approx(0.25, rel=1e-9)  # half of the 0.5 m^2 card
    kept = s.voxel >= 0
    centres_x = grid.origin[0] + ((s.voxel[kept] % grid.shape[0]) + 0.5) * grid.voxel
    assert (centres_x > -grid.voxel).all()  # nothing on the transparent left half


def test_the_solid_volume_matches_the_box(cl_env):
    scene, parts = trunk_and_card()
    v = voxelize(cl_env, scene, parts, 64, 1, solid_sub=4)
    assert v.wood_volume_m3 == pytest.approx(0.2 * 0.2 * 1.0, rel=0.03)


def test_mips_keep_mean_coverage_premultiplication_and_short_normals(cl_env, tiny):
    scene, parts, _ = tiny
    chain = volume.mip_chain(voxelize(cl_env, scene, parts, 16, 3).level, 3)
    mean0 = chain[0].mean_density()
    for lv in chain:
        assert abs(lv.mean_density() - mean0) <= 1e-6 * mean0
        assert (lv.albedo >= 0).all() and (lv.albedo <= lv.density[..., None] * (1 + 1e-6) + 1e-9).all()
        assert (np.linalg.norm(lv.normal, axis=-1) <= 1 + 1e-6).all()


def test_composite_equals_the_reference_for_any_work_group(cl_env, tiny):
    scene, parts, _ = tiny
    lv = voxelize(cl_env, scene, parts, 16, 3).level
    grid = error.composite_grid(lv)
    for cam in error.view_cameras(lv.origin, lv.bbox_max)[:2] + [Camera((0, 0.7, 3.0), (0, 0, -1), fov_y_deg=30)]:
        rec = cam.frame(20, 16)
        ra, rc = reference.composite(rec, 20, 16, grid, lv.origin, lv.voxel_m, 0.5 * lv.voxel_m)
        for local in (None, (1, 1), (8, 8)):
            da, dc = device.composite(cl_env, rec, 20, 16, grid, lv.origin, lv.voxel_m, 0.5 * lv.voxel_m, local=local)
            np.testing.assert_allclose(da, ra, atol=1e-6)
            np.testing.assert_allclose(dc, rc, atol=1e-6)
        assert ra.max() > 0.5


def test_a_card_seen_face_on_is_opaque_in_its_texture_and_clear_beside_it(cl_env, tiny):
    """The composite of the card alone, straight on: the opaque half blocks
    the view, the alpha-tested half lets it through."""
    scene, parts, _ = tiny
    lv = voxelize(cl_env, scene, parts, 16, 3).level
    cam = Camera((0.0, 0.75, 3.0), (0, 0, -1), ortho_height_m=0.5, ortho_width_m=1.0)
    a, _ = device.composite(cl_env, cam.frame(32, 16), 32, 16, error.composite_grid(lv), lv.origin, lv.voxel_m, 0.5 * lv.voxel_m)
    assert a[:, 20:30].mean() > 0.5  # x in 0.125 .. 0.44: opaque texels
    assert a[:, 2:10].mean() < 0.05  # x in -0.44 .. -0.19: alpha-tested away, no trunk
