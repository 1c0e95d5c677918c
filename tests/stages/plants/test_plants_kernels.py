"""Each kernel of kernels.cl against its numpy reference (reference.py)."""
import numpy as np
import pytest

from stages.plants import geometry, grass, leaves
from stages.plants import reference as ref
from stages.plants.species import GrassSpec, LeafSpec

pytestmark = pytest.mark.every_device  # kernels against their references on each runtime


def _frames(rng, n):
    t = rng.normal(size=(n, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    a = np.where(np.abs(t[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 0, 1.0]])
    nrm = a - t * (a * t).sum(1, keepdims=True)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return t, nrm, np.cross(t, nrm)


def test_tube_rings_kernel_matches_reference(cl_env):
    rng = np.random.default_rng(1)
    n = 700
    t, nrm, b = _frames(rng, n)
    ring = np.zeros((n, ref.RING))
    ring[:, 0:3] = rng.normal(size=(n, 3)) * 5
    ring[:, 3:6], ring[:, 6:9], ring[:, 9:12] = nrm, b, t
    ring[:, 12] = rng.random(n) * 0.3
    ring[:, 13] = rng.normal(size=n) * 0.2
    ring[:, 14:] = rng.random((n, 6))
    sides = rng.integers(3, 17, n).astype(np.int32)
    a = geometry.tube_rings(cl_env, ring.astype(np.float32), sides)
    r = geometry.tube_rings(None, ring.astype(np.float32), sides)
    assert a.shape == r.shape == (int((sides + 1).sum()), ref.VERT)
    np.testing.assert_allclose(a, r, atol=2e-5, rtol=1e-5)
    # the seam vertex repeats the first exactly (the union welds them)
    first, seam = 0, int(sides[0])
    assert np.array_equal(a[first, 0:6], a[seam, 0:6]) and a[seam, 6] == 1.0


def test_leaf_instances_kernel_matches_reference(cl_env):
    rng = np.random.default_rng(2)
    tmpl = leaves.make_template(LeafSpec(shape="ellipse", segments=5, length=0.1, width=0.05, petiole=0.01))
    n = 500
    h, l_, u = _frames(rng, n)
    rec = np.zeros((n, ref.LEAF))
    rec[:, 0:3] = rng.normal(size=(n, 3))
    rec[:, 3:6], rec[:, 6:9], rec[:, 9:12] = h, l_, u
    rec[:, 12] = 0.5 + rng.random(n)
    rec[:, 14:] = rng.random((n, 3))
    a = geometry.leaf_instances(cl_env, rec.astype(np.float32), tmpl.rows)
    r = geometry.leaf_instances(None, rec.astype(np.float32), tmpl.rows)
    np.testing.assert_allclose(a, r, atol=2e-6, rtol=1e-5)


@pytest.mark.parametrize("segments", [1, 2, 5, 10])
def test_grass_blades_kernel_matches_reference(cl_env, segments):
    g = GrassSpec(blades=300)
    rec = grass.blade_records(g, np.random.default_rng(3))
    rows = grass.row_parameters(rec, segments)
    a = geometry.grass_blades(cl_env, rec, rows, g.taper)
    r = geometry.grass_blades(None, rec, rows, g.taper)
    assert a.shape == (300 * (2 * segments + 1), ref.VERT)
    np.testing.assert_allclose(a, r, atol=2e-6, rtol=1e-5)


def test_kernels_are_deterministic(cl_env):
    g = GrassSpec(blades=200)
    rec = grass.blade_records(g, np.random.default_rng(4))
    rows = grass.row_parameters(rec, 6)
    a = geometry.grass_blades(cl_env, rec, rows, g.taper)
    assert np.array_equal(a, geometry.grass_blades(cl_env, rec, rows, g.taper))


def test_empty_inputs(cl_env):
    assert geometry.tube_rings(cl_env, np.zeros((0, ref.RING), np.float32), np.zeros(0, np.int32)).shape == (0, ref.VERT)
    assert geometry.leaf_instances(cl_env, np.zeros((0, ref.LEAF), np.float32), np.zeros((4, ref.TMPL), np.float32)).shape == (0, ref.VERT)
