"""The octahedral grids, the per-frame padding and mip levels, the atlas
EXR, and the impostor sampler against the frames it was made from."""
import numpy as np
import pytest

from stages.impostors import atlas, images, octahedral, sampler


@pytest.mark.parametrize("layout", octahedral.LAYOUTS)
def test_encode_decode_round_trip(layout):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    if layout == "hemi":
        d[:, 1] = np.abs(d[:, 1])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    back = octahedral.decode(octahedral.encode(d, layout), layout)
    np.testing.assert_allclose(back, d, atol=1e-12)


def test_hemi_views_from_below_use_the_horizon():
    below = octahedral.view_direction(40.0, -30.0)
    horizon = octahedral.view_direction(40.0, 0.0)
    np.testing.assert_allclose(octahedral.encode(below, "hemi"), octahedral.encode(horizon, "hemi"), atol=1e-12)


@pytest.mark.parametrize("layout", octahedral.LAYOUTS)
def test_a_frame_direction_selects_that_frame_alone(layout):
    n = 7
    dirs = octahedral.frame_directions(n, layout)
    for j in range(n):
        for i in range(n):
            idx, w = octahedral.select_frames(dirs[j, i], n, layout)
            assert w.sum() == pytest.approx(1.0)
            k = int(np.argmax(w))
            assert w[k] == pytest.approx(1.0, abs=1e-9)
            # the grid's duplicate directions (octahedral border) may name a twin frame
            np.testing.assert_allclose(dirs[idx[k][1], idx[k][0]], dirs[j, i], atol=1e-9)


def test_views_between_frames_blend_three_neighbours():
    n = 9
    rng = np.random.default_rng(1)
    d = octahedral.view_direction(rng.uniform(0, 360, 200), rng.uniform(0, 85, 200))
    idx, w = octahedral.select_frames(d, n, "hemi")
    np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-12)
    assert (w >= 0).all()
    span = np.abs(idx[..., None, :] - idx[..., None, :, :]).max((-1, -2, -3))
    assert (span <= 1).all()  # the three frames are grid neighbours


def _frame_stack(frames, f):
    """Frames of a distinct constant per channel (frame number + channel / 10),
    each with a covered blob in one corner (alpha 1) and alpha 0 elsewhere."""
    n = frames * frames
    tiles = np.zeros((n, f, f, len(atlas.CHANNELS)), np.float32)
    for k in range(n):
        tiles[k] = k + np.arange(len(atlas.CHANNELS)) / 10.0
        tiles[k, ..., 3] = 0.0
        tiles[k, :3, :3, 3] = 1.0  # covered
    return tiles


def test_padding_takes_values_from_the_same_frame_only():
    frames, f = 3, 16
    tiles = _frame_stack(frames, f)
    values = tiles[..., atlas.PADDED].copy()
    values[tiles[..., 3] <= 0] = -99.0  # what padding must replace
    filled = atlas.pad_frames(tiles[..., 3], values, padding_px=f)
    for k in range(frames * frames):
        np.testing.assert_allclose(filled[k], tiles[k, ..., atlas.PADDED], rtol=1e-6)


def test_every_mip_level_sampled_at_every_frame_border_reads_its_own_frame():
    """No frame's mip level reads texels of another frame: each frame holds
    its own constants, and sampling just inside, on and past each border of
    every frame at every per-frame level returns exactly them (colour and
    alpha averaged within the frame only)."""
    frames, atlas_px = 4, 128
    f, frame_levels = atlas.frame_layout(atlas_px, frames)
    tiles = _frame_stack(frames, f)
    tiles[..., 3] = 1.0  # opaque frames: every level's values are the frame's constants exactly
    levels = atlas.mip_chain(tiles, frames, atlas_px, frame_levels)
    assert len(levels) == int(np.log2(atlas_px)) + 1
    assert frame_levels >= 4
    for level in range(frame_levels):
        fl = f >> level
        border = np.array([-0.75, -0.5, 0.0, 0.3, fl - 1.3, fl - 1.0, fl - 0.5, fl - 0.25])
        x, y = np.meshgrid(border, np.linspace(-1.0, fl, 7))
        for j in range(frames):
            for i in range(frames):
                k = j * frames + i
                for xs, ys in ((x, y), (y, x)):
                    s = atlas.sample_frame(levels[level], fl, i, j, xs, ys)
                    np.testing.assert_allclose(s[..., 0:3], np.broadcast_to(k + np.arange(3) / 10.0, s[..., 0:3].shape), atol=1e-5)
                    np.testing.assert_allclose(s[..., 7:9], np.broadcast_to([k + 0.7, k + 0.8], s[..., 7:9].shape), atol=1e-5)


def test_a_partly_covered_frame_keeps_its_coverage_in_its_mips():
    frames, atlas_px = 2, 64
    f, frame_levels = atlas.frame_layout(atlas_px, frames)
    tiles = _frame_stack(frames, f)
    tiles[..., 0:3] *= tiles[..., 3:4]  # premultiplied colour
    tiles[..., atlas.PADDED] = atlas.pad_frames(tiles[..., 3], tiles[..., atlas.PADDED], f)
    levels = atlas.mip_chain(tiles, frames, atlas_px, frame_levels)
    for level in range(frame_levels):
        fl = f >> level
        for j in range(frames):
            for i in range(frames):
                a = levels[level][j * fl:(j + 1) * fl, i * fl:(i + 1) * fl, 3]
                assert a.mean() == pytest.approx(9.0 / f ** 2, rel=1e-5)


def test_atlas_exr_has_layer_channels_and_every_level(tmp_path):
    frames, atlas_px = 2, 32
    f, frame_levels = atlas.frame_layout(atlas_px, frames)
    levels = atlas.mip_chain(_frame_stack(frames, f), frames, atlas_px, frame_levels)
    path = tmp_path / "a.exr"
    images.write_exr(path, levels, atlas.CHANNELS, {"species": "x", "impostor": {"frames": 2}}, ("depth.Z",))
    back, names, attrs = images.read_exr_levels(path)
    assert sorted(names) == sorted(atlas.CHANNELS)
    assert {"albedo.R", "albedo.A", "normal.X", "depth.Z", "ao.Y"} <= set(names)
    assert [lv.shape[0] for lv in back] == [32, 16, 8, 4, 2, 1]
    order = [names.index(c) for c in atlas.CHANNELS]
    np.testing.assert_allclose(back[1][..., order], levels[1], atol=2e-2)
    assert attrs["worldbake:species"] == "x"


def test_the_sampler_at_a_frame_direction_reproduces_that_frame():
    """Seen exactly from a baked direction, the impostor is that frame:
    weight 1, the ray meets the frame's plane at the texel it came from."""
    rng = np.random.default_rng(3)
    frames, f = 5, 24
    tiles = rng.uniform(0.1, 0.9, (frames * frames, f, f, len(atlas.CHANNELS))).astype(np.float32)
    img = atlas._from_frames(tiles, frames)
    dirs = octahedral.frame_directions(frames, "hemi")
    at = atlas.Atlas("hemi", frames, f, frames * f, np.array([0.0, 1.0, 0.0]), 1.5, [img], 1, None, dirs)
    for (i, j) in ((0, 0), (2, 2), (4, 1), (1, 3)):
        view = sampler.render_view(at, dirs[j, i], f, depth_steps=0)
        frame = at.frame(i, j)
        np.testing.assert_allclose(view.rgba, frame[..., 0:4], atol=1e-5)


def test_the_sampler_reads_the_mip_level_of_its_view_size():
    """A view smaller than the frames reads the per-frame mip level a GPU's
    trilinear filter would (half size: level 1 exactly; 3/4 size: between
    levels 0 and 1), never level 0 point-sampled."""
    rng = np.random.default_rng(5)
    frames, f = 4, 32
    tiles = rng.uniform(0.1, 0.9, (frames * frames, f, f, len(atlas.CHANNELS))).astype(np.float32)
    levels = atlas.mip_chain(tiles, frames, frames * f, 4)
    dirs = octahedral.frame_directions(frames, "hemi")
    at = atlas.Atlas("hemi", frames, f, frames * f, np.array([0.0, 1.0, 0.0]), 1.5, levels, 4, None, dirs)
    assert sampler.mip_lod(f, f // 2, 4) == 1.0 and sampler.mip_lod(f, 2 * f, 4) == 0.0
    assert sampler.mip_lod(f, 1, 4) == 3.0  # clamped to the per-frame levels
    i, j = 2, 1
    half = sampler.render_view(at, dirs[j, i], f // 2, depth_steps=0)
    np.testing.assert_allclose(half.rgba, at.frame(i, j, 1)[..., 0:4], atol=1e-5)
    between = sampler.render_view(at, dirs[j, i], 24, depth_steps=0)
    level0 = sampler.render_view(at, dirs[j, i], 24, depth_steps=0, lod=0.0)
    level1 = sampler.render_view(at, dirs[j, i], 24, depth_steps=0, lod=1.0)
    frac = float(np.log2(f / 24))
    np.testing.assert_allclose(between.rgba, (1 - frac) * level0.rgba + frac * level1.rgba, atol=1e-5)


def test_the_cutout_polygon_holds_every_covered_texel_in_at_most_8_corners():
    rng = np.random.default_rng(11)
    f = 48
    yy, xx = np.mgrid[0:f, 0:f]
    crown = ((xx - 22) ** 2 / 300.0 + (yy - 20) ** 2 / 380.0 < 1.0)
    trunk = (np.abs(xx - 22) <= 1) & (yy > 30)
    frames = np.stack([crown | trunk, rng.random((f, f)) < 0.003, np.zeros((f, f), bool)]).astype(np.float32)
    poly = atlas.cutout_polygon(frames)
    assert 3 <= len(poly) <= 8 and (poly >= -1e-9).all() and (poly <= 1 + 1e-9).all()
    rows, cols = np.nonzero((frames > 0).any(0))
    corners = np.concatenate([np.stack([cols + dx, rows + dy], 1) for dx in (0, 1) for dy in (0, 1)]) / f
    for a, b in zip(poly, np.roll(poly, -1, 0)):  # every corner on the inner side of every edge
        cross = (b[0] - a[0]) * (corners[:, 1] - a[1]) - (b[1] - a[1]) * (corners[:, 0] - a[0])
        assert (cross >= -1e-9).all()
    area = 0.5 * abs(np.dot(poly[:, 0], np.roll(poly[:, 1], -1)) - np.dot(np.roll(poly[:, 0], -1), poly[:, 1]))
    assert area < 1.0
    only_crown = atlas.cutout_polygon(crown[None].astype(np.float32))
    area = 0.5 * abs(np.dot(only_crown[:, 0], np.roll(only_crown[:, 1], -1)) -
                     np.dot(np.roll(only_crown[:, 0], -1), only_crown[:, 1]))
    assert area < 0.75  # an ellipse in its frame: a quarter or more of the square is not drawn


def test_slicing_blend_weights_and_slab_spacing():
    from stages.impostors import slices

    for az in np.arange(0.0, 360.0, 7.5):
        w = slices.slicing_weights(octahedral.view_direction(az, 30.0))
        assert sum(x for _, x in w) == pytest.approx(1.0)
        assert all(0.0 <= x <= 1.0 for _, x in w)
    facing = slices.slicing_weights(octahedral.view_direction(120.0, 0.0))
    assert max(facing, key=lambda rw: rw[1]) == (2, pytest.approx(1.0))  # orientation 1, front
    back = slices.slicing_weights(octahedral.view_direction(300.0, 0.0))
    assert max(back, key=lambda rw: rw[1]) == (3, pytest.approx(1.0))  # orientation 1, back
    # from above the horizontal slicing seen from above (row 6), from below the one seen from below
    assert slices.slicing_weights(octahedral.view_direction(10.0, 80.0)) == [(6, 1.0)]
    assert slices.slicing_weights(octahedral.view_direction(10.0, -80.0)) == [(7, 1.0)]
    between = dict(slices.slicing_weights(octahedral.view_direction(120.0, 45.0)))
    assert between[6] == pytest.approx(0.5) and between[2] == pytest.approx(0.5)
    for el in np.arange(-90.0, 90.1, 5.0):
        w = slices.slicing_weights(octahedral.view_direction(37.0, el))
        assert sum(x for _, x in w) == pytest.approx(1.0) and all(x >= 0.0 for _, x in w)
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(200, 3))
    for d in rng.normal(size=(50, 3)):  # seed 002's sanity check: spacing = extent / N along any direction, > 0
        proj = pts @ (d / np.linalg.norm(d))
        assert slices.slab_spacing(pts, d, 5) == pytest.approx((proj.max() - proj.min()) / 5) and np.ptp(proj) > 0


def test_frame_sizes_halve_exactly_and_fit_their_atlas():
    for target in (1.0, 14.4, 41.0, 53.9, 64.7, 200.0, 5000.0):
        f = atlas.frame_size(target, 16, 2048, 32)
        assert f >= min(max(target, 32), 128) and f <= 128
        assert f in {32, 48, 64, 96, 128}  # 2^k or 3 2^k: per-frame mips halve to integers
        side = atlas.atlas_side(16, f)
        assert side & (side - 1) == 0 and 16 * f <= side < 2 * 16 * f


def test_the_frame_follows_the_plants_screen_size():
    from stages.impostors.stage import ImpostorsParams, plant_frame_px

    p = ImpostorsParams()
    # 1080 px over 60 degrees: a pixel is 1.07 mm at 1 m, 12.8 cm at 120 m
    assert plant_frame_px(3.46, 8.0, p) == 64  # a 6.9 m crown is 54 px there
    assert plant_frame_px(0.9, 1.5, p) == p.min_frame_px  # a shrub: 14 px
    assert plant_frame_px(0.3, 0.5, p) == p.small_plant_frame_px  # a flower under small_plant_m
    assert plant_frame_px(50.0, 90.0, p) == p.atlas_px // p.frames  # a giant: the largest frame


def test_the_held_out_lattice_is_stratified():
    from collections import Counter

    from stages.impostors import heldout

    full = heldout.lattice("hemi", 1)
    assert len(full) == 72 * 9
    nine = heldout.lattice("hemi", 9)
    assert sorted({a for a, _ in nine}) == sorted({a for a, _ in full})  # every azimuth once
    assert len(nine) == 72 and set(Counter(e for _, e in nine).values()) == {8}
    eighteen = heldout.lattice("hemi", 18)
    assert len(eighteen) == 36 and set(Counter(e for _, e in eighteen).values()) == {4}
    assert set(eighteen) <= set(full)
