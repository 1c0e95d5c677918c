"""The turtle: segments, frames, tropism, Lparser commands, pipe-model radii."""
import numpy as np
import pytest

from stages.plants.lsystem import compile_lsystem
from stages.plants.species import SpeciesShape
from stages.plants.turtle import interpret, path_length, pipe_radii


def skeleton(axiom, angle=90.0, seed=0, **ls):
    spec = SpeciesShape.model_validate({"kind": "lsystem", "lsystem": {"axiom": axiom, "angle": angle, "length": 1.0, **ls}})
    mods = compile_lsystem(spec.lsystem, "t").derive(0, 0, 1000)
    return interpret(mods, spec, seed)


def test_forward_and_turns():
    sk = skeleton("F + F & F")
    assert sk.n_segments == 3
    np.testing.assert_allclose(sk.p1[0], [0, 1, 0], atol=1e-12)
    # + turns toward L = -x, & pitches toward -U = -z
    np.testing.assert_allclose(sk.p1[1], [-1, 1, 0], atol=1e-12)
    np.testing.assert_allclose(sk.p1[2], [-1, 1, -1], atol=1e-12)
    for h, l_, u in zip(sk.heading, sk.left, sk.up):  # orthonormal right-handed frames
        np.testing.assert_allclose(np.cross(h, l_), u, atol=1e-12)


def test_angles_0_and_180():
    sk0 = skeleton("F + F - F", angle=0.0)
    np.testing.assert_allclose(sk0.p1[-1], [0, 3, 0], atol=1e-12)
    sk180 = skeleton("F + F", angle=180.0)
    np.testing.assert_allclose(sk180.p1[-1], [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(skeleton("F | F").p1[-1], [0, 0, 0], atol=1e-12)


def test_branches_and_continuation_flags():
    sk = skeleton("F [ + F ] F")
    assert list(sk.parent) == [-1, 0, 0]
    assert list(sk.cont) == [False, False, True]
    assert list(sk.order) == [0, 1, 0]


def test_cut_polygon_leaf_and_end():
    sk = skeleton("F [ + F % F F ] F [ { . + f + f } ] L(2) @ F")
    assert sk.n_segments == 3  # % cut two F, @ ended the string
    assert len(sk.polygons) == 1 and len(sk.polygons[0]) == 3
    assert sk.n_leaves == 1 and sk.leaf_scale[0] == 2.0 and sk.leaf_parent[0] == 2


def test_width_length_angle_modifiers():
    sk = skeleton("F ! F ' F", width_ratio=0.5, length_ratio=0.5)
    r = sk.radius
    assert r[1] == pytest.approx(0.5 * r[0]) and r[2] == pytest.approx(r[1])
    assert np.linalg.norm(sk.p1[2] - sk.p0[2]) == pytest.approx(0.5)


def test_tropism_bends_toward_gravity():
    flat = skeleton("+ F F F F")
    bent = skeleton("+ F F F F", tropism=[0, -1, 0], tropism_strength=0.3)
    assert bent.p1[-1][1] < flat.p1[-1][1] - 0.1
    # a vertical stem is parallel to gravity: no bend
    np.testing.assert_allclose(skeleton("F F", tropism=[0, -1, 0], tropism_strength=0.3).p1[-1], [0, 2, 0], atol=1e-9)


def test_roll_to_horizontal():
    sk = skeleton("& (30) < (40) $ F", angle=30)
    assert abs(sk.left[0][1]) < 1e-9  # L horizontal


def test_random_turn_is_seeded():
    a = skeleton("~(30) F ~(30) F", seed=1).p1[-1]
    assert np.array_equal(a, skeleton("~(30) F ~(30) F", seed=1).p1[-1])
    assert not np.allclose(a, skeleton("~(30) F ~(30) F", seed=2).p1[-1])


def test_pipe_model_conserves_area_at_branch_points():
    sk = skeleton("F [ + F [ - F ] F ] [ - F ] F")
    e = 2.5
    r = pipe_radii(sk, 0.01, e, 0.0)
    children = {}
    for s, p in enumerate(sk.parent):
        if p >= 0:
            children.setdefault(int(p), []).append(s)
    for p, ch in children.items():
        assert r[p] ** e == pytest.approx(sum(r[c] ** e for c in ch))
    assert r.min() == pytest.approx(0.01)


def test_path_length_runs_on_through_branches():
    sk = skeleton("F [ + F F ] F")
    start, end = path_length(sk)
    np.testing.assert_allclose(start, [0, 1, 2, 1])
    np.testing.assert_allclose(end, [1, 2, 3, 2])
