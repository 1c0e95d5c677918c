"""Skeleton to mesh: closed tubes with smooth joints, the manifold3d union,
continuous UVs, normals, the stress cases (angles 0 and 180, zero radius)."""
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from pipeline.errors import InputError
from stages.plants import lod, mesh
from stages.plants.lsystem import compile_lsystem
from stages.plants.plant import Settings, build_plant
from stages.plants.species import SpeciesShape
from stages.plants.turtle import interpret, pipe_radii

SMALL = Settings(hausdorff_samples=2000)


def species(axiom="F(1) A", rules=({"pred": "A", "succ": "F(0.5) [+A] [-A] [&L] ~(10) A"},), iterations=3, angle=30.0, **kw):
    d = {"kind": "lsystem", "lsystem": {"axiom": axiom, "rules": list(rules), "iterations": iterations, "angle": angle},
         "leaf": {"shape": "ellipse"}, "wood": {"tip_radius": 0.01}}
    for k, v in kw.items():
        d.setdefault(k, {}).update(v) if isinstance(v, dict) else d.__setitem__(k, v)
    return SpeciesShape.model_validate(d)


def tubes_of(spec, seed=0):
    mods = compile_lsystem(spec.lsystem, "t").derive(spec.lsystem.iterations, seed, 10**6)
    sk = interpret(mods, spec, seed)
    r = pipe_radii(sk, spec.wood.tip_radius, spec.wood.pipe_exponent, spec.wood.leaf_weight)
    return sk, r, mesh.build_tubes(sk, r, spec.wood, 0.0005, np.random.default_rng(0))


def assert_solid(part):
    c = mesh.check_solid(part)
    assert c["watertight"] and c["manifold"] and c["winding_consistent"], c
    assert c["degenerate"] == 0 and c["min_area"] > 0, c
    assert c["volume"] > 0 and c["manifold_volume"] == pytest.approx(c["volume"], rel=1e-6)
    assert c["normals_agree"] == 1.0, c
    return c


def test_a_bent_chain_is_one_closed_tube_without_cracks(cl_env):
    spec = species(axiom="F(1) + F(1) & F(1) + F(1)", rules=(), iterations=0, angle=40.0)
    sk, r, tubes = tubes_of(spec)
    assert tubes.n_tubes == 1  # turns under max_joint_angle keep one tube
    (part,) = mesh.tube_parts(cl_env, tubes, 0.5)
    assert_solid(part)
    # joint rings lie in the bisector plane: the ring at a node is shared by both segments
    pos, faces = part.welded()
    assert len(pos) == 5 * tubes.tube_rings[0][2] + 2


def test_sharp_turn_starts_a_new_tube():
    spec = species(axiom="F(1) + F(1)", rules=(), iterations=0, angle=120.0)
    assert tubes_of(spec)[2].n_tubes == 2


def test_union_of_a_small_tree_is_watertight_and_manifold(cl_env):
    spec = species()
    sk, r, tubes = tubes_of(spec)
    parts = mesh.tube_parts(cl_env, tubes, 0.5)
    for p in parts:
        assert_solid(p)
    u, info = mesh.union(parts)
    u, _ = mesh.collapse_short_edges(u, 1e-6)
    u, _ = mesh.flip_needles(u, 1e-6)
    u, _ = mesh.fix_corner_normals(u)
    c = assert_solid(u)
    assert info["genus"] >= 0
    # trimesh, processed independently, agrees
    pos, faces = u.welded()
    tm = trimesh.Trimesh(pos, faces)
    assert tm.is_watertight and tm.is_volume


def test_uv_runs_on_along_a_branch(cl_env):
    spec = species(axiom="F(1) F(0.5) F(0.25)", rules=(), iterations=0, wood={"bark_uv_length": 0.5})
    sk, r, tubes = tubes_of(spec)
    v = tubes.ring[:, 14]
    np.testing.assert_allclose(np.diff(v), [1 / 0.5, 0.5 / 0.5, 0.25 / 0.5], rtol=1e-6)
    (part,) = mesh.tube_parts(cl_env, tubes, 0.5)
    u = part.verts[: len(tubes.ring) * (tubes.tube_rings[0][2] + 1), 6]
    assert u.min() == 0.0 and u.max() == 1.0


@pytest.mark.parametrize("angle", [0.0, 180.0])
def test_angles_0_and_180_still_give_a_closed_solid(cl_env, angle):
    res = build_plant("stress", species(angle=angle), 1, replace(SMALL, cl=cl_env))
    c = res.metrics["wood_check"]
    assert c["watertight"] and c["manifold"] and c["degenerate"] == 0
    assert res.lod_info[0]["triangles"] > 0


def test_zero_iterations_build_the_axiom(cl_env):
    res = build_plant("stick", species(iterations=0), 1, replace(SMALL, cl=cl_env))
    assert res.metrics["segments"] == 1 and res.metrics["wood_check"]["watertight"]


def test_zero_radius_draws_no_wood_and_nothing_is_an_error(cl_env):
    res = build_plant("ghost", species(wood={"tip_radius": 0.0}), 1, replace(SMALL, cl=cl_env))
    assert res.lods[0]["Wood"].n_tris == 0 and res.lods[0]["Leaves"].n_tris > 0
    with pytest.raises(InputError, match="produced no geometry"):
        build_plant("ghost", species(wood={"tip_radius": 0.0}, leaf={"shape": "none"}), 1, replace(SMALL, cl=cl_env))


def test_turtle_radius_model_and_the_bang_operator(cl_env):
    spec = species(axiom="F(1) ! F(1) ! F(1)", rules=(), iterations=0, wood={"radius_model": "turtle", "radius": 0.1})
    res = build_plant("taper", spec, 1, replace(SMALL, cl=cl_env))
    pos, _ = res.lods[0]["Wood"].welded()
    top = pos[pos[:, 1] > 2.5]
    assert np.abs(top[:, [0, 2]]).max() < 0.06  # 0.1 * 0.7^2 = 0.049 near the top


def test_decimated_wood_stays_closed(cl_env):
    spec = species(iterations=4)
    res = build_plant("lodtest", spec, 2, replace(SMALL, cl=cl_env))
    for chk in res.metrics["wood_lod_checks"]:
        assert chk["watertight"] and chk["manifold"] and chk["degenerate"] == 0


def test_hausdorff_is_deterministic_and_symmetric(cl_env):
    spec = species(iterations=3)
    res = build_plant("h", spec, 3, replace(SMALL, cl=cl_env))
    a, b = res.lods[0]["Wood"].welded(), res.lods[2]["Wood"].welded()
    h1, h2 = lod.hausdorff(a, b, 3000), lod.hausdorff(b, a, 3000)
    assert h1 == lod.hausdorff(a, b, 3000)
    assert h1["max"] == pytest.approx(h2["max"])
    assert lod.hausdorff(a, a, 3000)["max"] < 1e-6
