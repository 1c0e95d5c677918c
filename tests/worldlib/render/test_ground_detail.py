"""The renderer's ground detail layer (worldlib.render.ground_detail) on a
world the world stage writes: read from USD, applied to terrain pixels only,
and a view from 2 m shows texture where the 1 m bake is a smear."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib.render import Camera, Prepared, Settings


@pytest.fixture(scope="module")
def detail_world(tmp_path_factory):
    from pxr import Usd, UsdGeom, Vt

    from pipeline.contract import RunContext
    from pipeline.grid import Grid
    from pipeline.opencl import get_cl
    from stages.world import STAGE
    from worldlib.ground import SPLAT_CHANNELS

    out_dir = tmp_path_factory.mktemp("render_detail")
    r, c = np.mgrid[0:40, 0:40]
    h = (500 + 6 * np.sin(c / 5.0) + 4 * np.cos(r / 7.0)).astype(np.float32)
    h[15:23, 16:24] = h[19, 20]  # a flat bed under the water
    w = np.zeros((40, 40, 6), np.float32)
    w[:, :20, SPLAT_CHANNELS.index("splat.grass")] = 1  # grass west, scree east
    w[:, 20:, SPLAT_CHANNELS.index("splat.scree")] = 1
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="k", out_dir=out_dir, seed=0,
                     provenance={"stage": "world", "key": "k"}, project_root=out_dir)
    out = STAGE.run(ctx, {"terrain": Grid(h, 10.0), "splat": Grid(w, 10.0, SPLAT_CHANNELS)},
                    STAGE.params(mesh_max_vertices=41, texture_size=64, ground_texel_m=1.0, ground_tile_texels=512,
                                 ground_detail_texels=128, ground_near_m=0.0))
    # a wall (not ground) standing in the view
    stage = Usd.Stage.Open(str(out["world.root"]))
    wall = UsdGeom.Mesh.Define(stage, "/World/Wall")
    x, z = 200.0, 196.0
    y = float(h[20, 20])
    wall.CreatePointsAttr(Vt.Vec3fArray([(x - 1, y - 1, z), (x + 1, y - 1, z), (x + 1, y + 3, z), (x - 1, y + 3, z)]))
    wall.CreateFaceVertexCountsAttr([4])
    wall.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    wall.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([(0.8, 0.1, 0.1)]))
    # water lying just above the ground (as a river on its bed): not ground, though as low and as flat
    water = UsdGeom.Mesh.Define(stage, "/World/Water")
    wy = float(h[19, 20]) + 0.01
    water.CreatePointsAttr(Vt.Vec3fArray([(196, wy, 196), (204, wy, 196), (204, wy, 188), (196, wy, 188)]))
    water.CreateFaceVertexCountsAttr([4])
    water.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    water.CreateNormalsAttr(Vt.Vec3fArray([(0, 1, 0)] * 4))
    water.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([(0.05, 0.2, 0.9)]))
    # and a water mesh under the ground (a river's ribbon below its bank): the ground above it keeps its detail
    hidden = UsdGeom.Mesh.Define(stage, "/World/Hidden")
    hy = float(h[19, 20]) - 0.5
    hidden.CreatePointsAttr(Vt.Vec3fArray([(185, hy, 204), (215, hy, 204), (215, hy, 197), (185, hy, 197)]))
    hidden.CreateFaceVertexCountsAttr([4])
    hidden.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    hidden.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([(0.05, 0.2, 0.9)]))
    stage.GetRootLayer().Save()
    cam = Camera((200.0, y + 2.0, 204.0), (0.0, -0.35, -1.0), fov_y_deg=50.0)
    return out["world.root"], cam


def _renders(cl_env, world, cam, width=160, height=120):
    from worldlib.render import world_view
    from worldlib.render.ground_detail import with_ground_detail

    scene, _ = world_view.build_world_scene(cl_env, world, progress=lambda *a: None)
    img = Prepared(cl_env, scene).render(cam, Settings(width, height, samples=1))
    return img, with_ground_detail(img, world, cam, width, height)


def test_detail_view_is_read_from_usd(detail_world):
    from worldlib import ground_detail
    from worldlib.render.ground_detail import load_detail_view

    view = load_detail_view(detail_world[0])
    assert view is not None
    np.testing.assert_allclose(view.layer.tile_m, [ground_detail.DETAIL_SETS[t].tile_m
                                                   for t in ground_detail.GROUND_TYPES])
    # the splat weights as the stage wrote them: grass west of x = 200 m, scree east (half floats)
    w = view.weights(np.array([50.0, 350.0]), np.array([200.0, 200.0]))
    np.testing.assert_allclose(w[0], [0, 0, 1, 0, 0, 0], atol=1e-3)
    np.testing.assert_allclose(w[1], [0, 1, 0, 0, 0, 0], atol=1e-3)


def test_near_ground_shows_texture_and_only_ground_changes(cl_env, detail_world):
    world, cam = detail_world
    plain, detailed = _renders(cl_env, world, cam)
    changed = np.abs(detailed.albedo - plain.albedo).max(-1) > 1e-6
    sky = plain.alpha == 0
    assert not changed[sky].any()
    # the wall (red, displayColor) keeps its albedo
    red = (plain.albedo[..., 0] > 0.5) & (plain.albedo[..., 1] < 0.2)
    assert red.sum() > 50 and not changed[red].any()
    blue = (plain.albedo[..., 2] > 0.5) & (plain.albedo[..., 0] < 0.2)
    assert blue.sum() > 50 and not changed[blue].any()
    ground = plain.alpha.astype(bool) & ~red & ~blue
    assert changed[ground].mean() > 0.9
    assert changed[100:, 40:120].all()  # the near ground over the hidden mesh
    # a view from 2 m: texture (neighbouring pixels differ) where the bake is smooth, in the lower half (near)
    lower = slice(60, 120)

    def contrast(a):
        lum = a[lower].mean(-1)
        m = ground[lower][:, 1:] & ground[lower][:, :-1]
        return np.abs(np.diff(lum, axis=1))[m].mean() / lum[ground[lower]].mean()

    assert contrast(detailed.albedo) > 4 * contrast(plain.albedo)
    # the normals are tilted by the detail, still unit and facing up
    n = detailed.normal[ground]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-4)
    assert (n[:, 1] > 0.3).all() and np.abs(detailed.normal[ground] - plain.normal[ground]).max() > 0.05


def test_grass_and_scree_sides_have_their_colours(cl_env, detail_world):
    from worldlib.ground import GROUND_COLOURS, GROUND_TYPES

    world, _ = detail_world
    grass, scree = GROUND_COLOURS[GROUND_TYPES.index("grass")], GROUND_COLOURS[GROUND_TYPES.index("scree")]
    for x, colour in ((150.0, grass), (250.0, scree)):  # looking straight down, west and east of the border
        down = Camera((x, 513.0, 150.0), (0.0, -1.0, 0.0), up=(0.0, 0.0, -1.0), fov_y_deg=30.0)  # above the hills
        _, img = _renders(cl_env, world, down, 96, 96)
        np.testing.assert_allclose(img.albedo.reshape(-1, 3).mean(0), colour, rtol=0.25)
