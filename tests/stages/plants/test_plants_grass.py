"""Grass: Bezier blades (seed 000, its lean bug fixed) and the slice tuft (seed 001)."""
import numpy as np
import pytest

from stages.plants import grass, lod
from stages.plants.mesh import Part
from stages.plants.species import GrassSpec


def test_lean_is_symmetric_the_seed_000_bug_is_fixed():
    """Seed 000's code computed g (b (2 r1) - 1) with r1 in [-1, 1]: every blade
    leaned toward -x/-z. Ours leans evenly in every direction."""
    g = GrassSpec(blades=20000, bend=0.3, outward=0.0)
    rec = grass.blade_records(g, np.random.default_rng(0))
    off = rec[:, 6:9] - rec[:, 0:3]
    h = rec[:, 7] - rec[:, 1]
    lean = off[:, [0, 2]] / h[:, None]
    se = lean.std(0) / np.sqrt(len(lean))
    assert np.all(np.abs(lean.mean(0)) < 4 * se)
    assert lean.min() < -0.25 and lean.max() > 0.25  # both signs, up to b
    assert np.abs(lean).max() <= 0.3 + 1e-6


def test_control_point_sits_above_the_root():
    g = GrassSpec(blades=2000)
    rec = grass.blade_records(g, np.random.default_rng(1))
    h = rec[:, 7] - rec[:, 1]
    ctrl = rec[:, 3:6] - rec[:, 0:3]
    assert np.all(ctrl[:, 1] >= g.control_y_min * h - 1e-6) and np.all(ctrl[:, 1] <= g.control_y_max * h + 1e-6)
    off = rec[:, 6:9] - rec[:, 0:3]
    assert np.all(np.abs(ctrl[:, [0, 2]]) <= g.control_xz * np.abs(off[:, [0, 2]]) + 1e-6)


@pytest.mark.parametrize("n", range(1, 11))
def test_blades_have_2n_minus_1_good_triangles(cl_env, n):
    g = GrassSpec(blades=50, segments=n)
    rec = grass.blade_records(g, np.random.default_rng(2))
    part = grass.blades(cl_env, rec, n, g.taper)
    assert part.n_tris == 50 * (2 * n - 1)
    pos, f = part.welded()
    tri = pos[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.min() > 1e-9
    # normals agree with the triangles' winding
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    cn = part.verts[part.tris][:, :, 3:6]
    assert np.all(np.einsum("fcj,fj->fc", cn, fn) > 0)
    v = part.verts
    roots = v[:, 7] == 0.0
    tips = v[:, 7] == 1.0
    assert np.all(v[roots, 9] == 0) and np.all(v[tips, 9] == 1)  # flutter: 0 at the root, 1 at the tip
    assert tips.sum() == 50


def test_rows_follow_curvature_and_beat_uniform_rows(cl_env):
    g = GrassSpec(blades=48)
    rec = grass.blade_records(g, np.random.default_rng(3))
    rows = grass.row_parameters(rec, 2)
    assert np.all(rows[:, 0] == 0) and np.all(rows[:, -1] == 1) and np.all(np.diff(rows, axis=1) > 0)
    ref = grass.blades(cl_env, rec, 32, g.taper).welded()
    adaptive = lod.hausdorff(ref, grass.blades(cl_env, rec, 2, g.taper).welded(), 5000)["max"]
    from stages.plants import geometry
    uniform_rows = np.tile(np.linspace(0, 1, 3, dtype=np.float32), (len(rec), 1))
    uni = Part(geometry.grass_blades(cl_env, rec, uniform_rows, g.taper), grass.blade_triangles(len(rec), 2), np.arange(len(rec) * 5))
    assert adaptive < lod.hausdorff(ref, uni.welded(), 5000)["max"]


def test_slice_tuft_is_seed_001_five_quads():
    g = GrassSpec(blades=30)
    rec = grass.blade_records(g, np.random.default_rng(4))
    cards = grass.slice_cards(rec)
    assert cards.n_tris == 10
    pos, _ = cards.welded()
    ext = np.abs(np.concatenate([rec[:, 0:3], rec[:, 6:9]])[:, [0, 2]]).max()
    assert np.isclose(np.abs(pos[:, [0, 2]]).max(), ext, rtol=1e-5)


@pytest.mark.parametrize("segments,levels", [(8, 4), (10, 5), (1, 3), (3, 2)])
def test_grass_plan_halves_triangles(segments, levels):
    plan = grass.grass_plan(segments, levels, 0.5)
    tris = []
    for kind, n, keep in plan:
        tris.append(10 if kind == "cards" else max(1, int(np.floor(keep * 100))) * (2 * n - 1))
    assert len(plan) == levels
    assert all(b <= 0.5 * a for a, b in zip(tris, tris[1:])), (plan, tris)
