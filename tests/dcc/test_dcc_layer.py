"""The DCC selection (stages/world/dcc_layer.py): the `lod` variant per
vegetation tile by distance, crowns beyond, and the layer a shot writes;
with usd-core only (no Blender)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.world import dcc_layer

LADDER = [(0.0, "LOD0"), (5.0, "LOD1"), (80.0, "LOD2"), (170.0, "impostor")]


def test_choose_follows_the_ladder_then_crowns_then_nothing():
    pick = [dcc_layer.choose(LADDER, 1000.0, d, 400.0) for d in (0.0, 4.9, 5.0, 100.0, 170.0, 399.0, 401.0, 1001.0)]
    assert pick == ["LOD0", "LOD0", "LOD1", "LOD2", "impostor", "impostor", dcc_layer.CROWN, None]


@pytest.mark.parametrize("eye,want", [((5.0, 0.0, 5.0), 0.0), ((-3.0, 0.0, 5.0), 3.0), ((13.0, 0.0, 14.0), 5.0),
                                      ((5.0, 30.0, 5.0), 10.0)])
def test_tile_distance_is_to_the_nearest_point_of_the_tile_box(eye, want):
    bounds = np.array([0.0, 0.0, 10.0, 10.0, 0.0, 20.0])
    assert dcc_layer.tile_distance(bounds, np.asarray(eye)) == pytest.approx(want)


def test_crown_pyramids_enclose_their_centres_and_face_outward():
    centre = np.array([[0.0, 0.0, 0.0], [100.0, 5.0, -3.0]])
    radius = np.array([1.0, 2.0])
    pts, counts, idx = dcc_layer.crown_mesh(centre, radius)
    assert pts.shape == (8, 3) and list(counts) == [3] * 6 and len(idx) == 18
    tri = pts[idx.reshape(-1, 3)].astype(np.float64)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    owner = np.repeat(centre, 3, axis=0)
    assert (np.einsum("ij,ij->i", normal, tri.mean(1) - owner) > 0).all(), "a crown face points inward"
    for k in range(2):  # the pyramid reaches about its sphere: not a speck, not a giant
        p = pts[4 * k:4 * k + 4]
        assert 1.0 * radius[k] <= np.linalg.norm(p - centre[k], axis=1).max() <= 2.0 * radius[k]
        base = p[:3, [0, 2]]  # seen from above: the base triangle covers the sphere's disc (the plant's cover)
        (ax, az), (bx, bz) = base[1] - base[0], base[2] - base[0]
        plan = 0.5 * abs(ax * bz - az * bx)
        assert plan == pytest.approx(np.pi * radius[k] ** 2, rel=1e-5)


def test_a_crown_covers_what_the_plant_s_view_atlas_covers(tmp_path):
    """crown_look reads the species' view atlas: the frames in the atlas's
    corner (the rest of a power-of-two atlas is empty), their covered
    texels' mean colour, and their cover as a share of the bounding disc
    (a frame is the disc's square): discs of half the frame's radius cover
    a quarter, whatever slices the species has."""
    import json

    from pxr import Sdf, Usd

    from worldlib import images

    frames, frame_px = 2, 32
    rgba = np.zeros((128, 128, 4), np.float32)  # a 128 atlas holding 2 x 2 frames of 32 texels
    yy, xx = np.mgrid[0:frame_px, 0:frame_px] + 0.5
    disc = (xx - 16) ** 2 + (yy - 16) ** 2 < 8 ** 2
    for i in range(frames):
        for j in range(frames):
            rgba[j * frame_px:(j + 1) * frame_px, i * frame_px:(i + 1) * frame_px][disc] = (0.05, 0.2, 0.03, 1.0)
    (tmp_path / "textures").mkdir()
    images.write_png(tmp_path / "textures" / "tree_atlas_albedo.png", rgba[..., :3], rgba[..., 3])
    info = {"files": {"atlas_png": "./textures/tree_atlas_albedo.png"}, "frames": frames, "frame_px": frame_px,
            "slice_files": {"slices": {"albedo": "./textures/none.png"}}}
    layer = Sdf.Layer.CreateNew(str(tmp_path / "impostors.usda"))
    stage = Usd.Stage.Open(layer)
    prim = stage.DefinePrim("/Plants/tree")
    prim.SetCustomDataByKey("worldbake:impostor", json.dumps(info))
    colour, share = dcc_layer.crown_look(prim, info)
    assert share == pytest.approx(disc.mean() * 4 / np.pi, rel=1e-6) and share == pytest.approx(0.25, abs=0.01)
    assert colour == pytest.approx([0.05, 0.2, 0.03], abs=0.004)  # through the 8-bit sRGB PNG


def test_terrain_lod_is_the_coarsest_within_the_error_on_screen():
    errors = {"full": 0.0, "half": 4.0, "quarter": 12.0}
    tiles = [(f"/T{k}", np.array([x, 0.0, x + 100.0, 100.0, 0.0, 10.0]), errors)
             for k, x in enumerate((0.0, 1000.0, 3000.0, 9000.0))]
    eye = np.array([50.0, 5.0, 50.0])
    px = dcc_layer.TERRAIN_ERROR_PX
    rho = 1000.0 * px / 4.0  # half's 4 m fits from 1000 m on, quarter's 12 m from 3000 m on
    got = dcc_layer.terrain_selection(tiles, eye, rho)
    assert [got[f"/T{k}"] for k in range(4)] == ["full", "full", "half", "quarter"]
    farther = dcc_layer.terrain_selection([(p, b + [60.0, 0, 60.0, 0, 0, 0], e) for p, b, e in tiles], eye, rho)
    assert farther["/T1"] == "half" and farther["/T2"] == "quarter"  # 1010 m, 3010 m: one step coarser each


def test_the_world_selects_terrain_tiles_by_distance_and_muting_gives_full(small_world):
    from pxr import Usd

    from stages.world.terrain_tiles import tile_prims

    world = small_world["folder"]
    stage = Usd.Stage.Open(str(world), Usd.Stage.LoadNone)
    muted = Usd.Stage.Open(str(world), Usd.Stage.LoadNone)
    muted.MuteLayer(str(world.parent / "world" / dcc_layer.LAYER))
    tiles = dcc_layer.terrain_tiles(stage)
    assert len(tiles) == 9  # the small world's 48 quads a side in tiles of 16
    veg = dcc_layer.vegetation_source(stage.GetPrimAtPath("/World/Vegetation"))
    from pathlib import Path

    eye = dcc_layer.default_eye(dcc_layer.leaf_tiles(Path(veg.realPath)))
    protos = {p.GetName(): str(p.GetPath()) for p in stage.GetPrimAtPath("/World/Vegetation/Prototypes").GetAllChildren()}
    rho = next(iter(dcc_layer.species_ladders(world, protos).values()))["px_per_rad"]
    want = dcc_layer.terrain_selection(tiles, eye, rho)
    for prim in tile_prims(stage):
        assert prim.GetVariantSets().GetVariantSet("lod").GetVariantSelection() == want[str(prim.GetPath())]
    for prim in tile_prims(muted):
        assert prim.GetVariantSets().GetVariantSet("lod").GetVariantSelection() == "full"
    # the tile holding the eye is at full detail
    inside = [p for p, b, _ in tiles if b[0] <= eye[0] <= b[2] and b[1] <= eye[2] <= b[3]]
    assert inside and all(want[p] == "full" for p in inside)


def test_the_world_selects_each_tile_by_its_distance(small_world):
    """The published world composes dcc.usdc first; every instancer tile's
    prototype selects what choose() gives for its distance from the eye
    the layer names, tiles beyond the crown distance are inactive and their
    plants are crowns."""
    from pathlib import Path

    from pxr import Sdf, Usd, UsdGeom

    world = small_world["folder"]
    root = Sdf.Layer.FindOrOpen(str(world.parent / "world" / "world.usda"))
    assert root.subLayerPaths[0] == "./" + dcc_layer.LAYER
    stage = Usd.Stage.Open(str(world))
    veg_layer = dcc_layer.vegetation_source(stage.GetPrimAtPath("/World/Vegetation"))
    tiles = dcc_layer.leaf_tiles(Path(veg_layer.realPath))
    protos = {p.GetName(): str(p.GetPath())  # class prims: GetChildren() passes over them
              for p in stage.GetPrimAtPath("/World/Vegetation/Prototypes").GetAllChildren()}
    muted = Usd.Stage.Open(str(world))
    muted.MuteLayer(str(world.parent / "world" / dcc_layer.LAYER))
    ladders = dcc_layer.species_ladders(world, protos)
    assert ladders, "no species carries the impostors' switch distances"
    eye = dcc_layer.default_eye(tiles)
    want = dcc_layer.selections(tiles, ladders, eye)
    assert want
    seen = set()
    for inst, variant in want.items():
        prim = stage.GetPrimAtPath(inst)
        if variant in (None, dcc_layer.CROWN):
            assert prim and not prim.IsActive(), f"{inst} should be off ({variant})"
            continue
        proto = prim.GetChild("Prototypes").GetChild(prim.GetName())
        assert proto.GetVariantSets().GetVariantSet("lod").GetVariantSelection() == variant, inst
        assert muted.GetPrimAtPath(inst).GetChild("Prototypes").GetChild(prim.GetName()).GetVariantSets() \
            .GetVariantSet("lod").GetVariantSelection() == "LOD0", "muting dcc.usdc gives the assets' own LOD0"
        seen.add(variant)
    assert seen, "no tile draws its plants as instances"
    crowns = {p.GetName(): p for p in stage.GetPrimAtPath(dcc_layer.CROWNS).GetChildren()
              if p.IsA(UsdGeom.Mesh)} if stage.GetPrimAtPath(dcc_layer.CROWNS) else {}
    far = {inst.rsplit("/", 1)[1] for inst, v in want.items() if v == dcc_layer.CROWN}
    assert set(crowns) == far
    for name, mesh in crowns.items():
        from pxr import UsdShade

        assert UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()[0], f"crowns of {name} have no material"


def test_a_shot_layer_puts_every_plant_back_at_lod0(small_world, tmp_path):
    from pxr import Usd, UsdGeom

    out = tmp_path / "full.usda"
    info = dcc_layer.write_shot_layer(small_world["folder"], out, lod="LOD0")
    assert list(info["tiles"]) == ["LOD0"]
    stage = Usd.Stage.Open(str(out))
    instancers = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer) and  # placeholders have no LODs
                  p.GetChild("Prototypes").GetChild(p.GetName()).GetVariantSets().HasVariantSet("lod")]
    assert sum(info["tiles"].values()) == len(instancers), "an instancer dcc.usdc switched off stays off"
    for p in instancers:
        sel = p.GetChild("Prototypes").GetChild(p.GetName()).GetVariantSets().GetVariantSet("lod").GetVariantSelection()
        assert sel == "LOD0", p.GetPath()
    crowns = stage.GetPrimAtPath(dcc_layer.CROWNS)
    assert not crowns or not crowns.IsActive(), "the world's crowns still drawn beside the plants they stand for"
    assert info["terrain_tiles"] == {"full": 9}  # and the terrain at full detail


def test_a_shot_layer_selects_the_terrain_for_its_eye(small_world, tmp_path):
    from pxr import Usd

    from stages.world.terrain_tiles import tile_prims

    stage = Usd.Stage.Open(str(small_world["folder"]), Usd.Stage.LoadNone)
    tiles = dcc_layer.terrain_tiles(stage)
    corner = tiles[0][1]  # the north-west tile: an eye over it
    eye = np.array([corner[0] + 1.0, corner[5] + 10.0, corner[1] + 1.0])
    out = tmp_path / "shot.usda"
    dcc_layer.write_shot_layer(small_world["folder"], out, eye=eye)
    shot = Usd.Stage.Open(str(out), Usd.Stage.LoadNone)
    protos = {p.GetName(): str(p.GetPath()) for p in stage.GetPrimAtPath("/World/Vegetation/Prototypes").GetAllChildren()}
    rho = next(iter(dcc_layer.species_ladders(small_world["folder"], protos).values()))["px_per_rad"]
    want = dcc_layer.terrain_selection(tiles, eye, rho)
    got = {str(p.GetPath()): p.GetVariantSets().GetVariantSet("lod").GetVariantSelection() for p in tile_prims(shot)}
    assert got == want and got[tiles[0][0]] == "full"


def test_our_renderer_composes_the_world_without_the_dcc_selection(small_world):
    """dcc.usdc sits two layers down (world.usda > the world stage's root >
    dcc.usdc); our renderer draws every instance itself and mutes it
    wherever it is: no crowns, every tile's instancer active."""
    from pxr import Usd, UsdGeom

    from worldlib.render.usd_asset import mute_dcc_selection

    stage = Usd.Stage.Open(str(small_world["folder"]))
    assert stage.GetPrimAtPath(dcc_layer.CROWNS).IsValid(), "the small world has no crowns to mute"
    mute_dcc_selection(stage)
    assert [layer for layer in stage.GetMutedLayers() if layer.endswith(dcc_layer.LAYER)]
    assert not stage.GetPrimAtPath(dcc_layer.CROWNS).IsValid()
    inactive = [p.GetPath() for p in stage.TraverseAll() if p.IsA(UsdGeom.PointInstancer) and not p.IsActive()]
    assert not inactive, inactive[:3]
