"""The ground types' detail textures and their blend (worldlib.ground_detail):
seamless tiling, determinism, the mean colour, the blend against a
reference, and triplanar sampling that does not streak on steep ground."""
from __future__ import annotations

import numpy as np
import pytest

from worldlib import ground_detail as gd
from worldlib.ground import GROUND_COLOURS, GROUND_TYPES

N = 128


@pytest.fixture(scope="module")
def textures():
    return gd.detail_textures(5, N)


def _seam_ratio(a: np.ndarray, axis: int) -> float:
    """Mean step across the wrap (last texel to first) over the largest mean
    step between any two neighbouring columns (rows) inside: at most 1 for a
    texture that tiles (its seam is one more pair of neighbours)."""
    steps = np.abs(np.diff(a, axis=axis))
    other = tuple(i for i in range(a.ndim) if i != axis)
    inner = steps.mean(axis=other).max()
    seam = np.abs(np.take(a, 0, axis) - np.take(a, -1, axis)).mean()
    return float(seam / max(inner, 1e-9))


def test_every_ground_type_has_a_detail_set():
    assert set(gd.DETAIL_SETS) == set(GROUND_TYPES)
    for s in gd.DETAIL_SETS.values():
        assert 2.0 <= s.tile_m <= 4.0  # a few mm per texel at 512


def test_the_textures_tile_seamlessly(textures):
    for t, (albedo, normal) in textures.items():
        for img in (albedo, normal):
            for axis in (0, 1):
                assert _seam_ratio(img, axis) <= 1.0, (t, axis)
    # the measure fails a texture that does not wrap: a crop of a larger one
    big = gd.fbm(2 * N, 8, 4, 3)[:N, :N]
    assert _seam_ratio(big, 1) > 3


def test_the_noise_wraps_its_lattice():
    """The last texels interpolate toward lattice point 0: the texture's
    right edge continues into its left edge."""
    a = gd.value_noise(64, 8, 11)
    lat = gd.lattice01(*np.meshgrid(np.arange(8), np.arange(8)), 11)  # [row, column]
    f = (63 + 0.5) * 8 / 64 - 7
    f = f * f * (3 - 2 * f)
    g = (0 + 0.5) * 8 / 64
    g = g * g * (3 - 2 * g)
    top = lat[0, 7] * (1 - f) + lat[0, 0] * f
    bottom = lat[1, 7] * (1 - f) + lat[1, 0] * f
    assert a[0, 63] == pytest.approx(top * (1 - g) + bottom * g, abs=1e-6)


def test_textures_are_deterministic_and_seeded():
    a1, n1 = gd.detail_texture("scree", 7, 64)
    a2, n2 = gd.detail_texture("scree", 7, 64)
    assert a1.tobytes() == a2.tobytes() and n1.tobytes() == n2.tobytes()
    a3, _ = gd.detail_texture("scree", 8, 64)
    assert np.abs(a3 - a1).mean() > 1e-3


def test_mean_albedo_is_the_ground_colour_and_normals_are_unit(textures):
    for k, t in enumerate(GROUND_TYPES):
        albedo, normal = textures[t]
        np.testing.assert_allclose(albedo.reshape(-1, 3).mean(0), GROUND_COLOURS[k], rtol=0.03, atol=2e-3)
        assert 0 <= albedo.min() and albedo.max() <= 1
        v = 2 * normal - 1
        np.testing.assert_allclose(np.linalg.norm(v, axis=-1), 1, atol=1e-5)
        assert v[..., 2].min() > 0.2  # tangent space: facing out
    # contrast: every type but snow has visible structure (relative spread of its brightness)
    for t in ("rock", "scree", "grass", "dry_grass", "mud"):
        lum = textures[t][0].mean(-1)
        assert lum.std() / lum.mean() > 0.1, t


def test_normal_from_height_on_a_ramp():
    # height rising east (columns) tilts the normal west (x < 0.5), rising south (rows) tilts it south: y > 0.5
    h = np.tile(np.arange(16.0), (16, 1)) * 0.01
    n = gd.normal_from_height(h, 0.01)[4:12, 4:12]
    np.testing.assert_allclose(n[..., 0], 0.5 - 0.5 / np.sqrt(2), atol=1e-6)
    np.testing.assert_allclose(n[..., 1], 0.5, atol=1e-6)
    n = gd.normal_from_height(h.T.copy(), 0.01)[4:12, 4:12]
    assert (n[..., 1] > 0.5).all()


def _constant_layer(colours, tile=2.0):
    tex = {t: (np.broadcast_to(np.asarray(colours[k], np.float32), (8, 8, 3)).copy(),
               np.broadcast_to(np.float32([0.5, 0.5, 1.0]), (8, 8, 3)).copy()) for k, t in enumerate(GROUND_TYPES)}
    return gd.DetailLayer.from_textures(tex, {t: tile for t in GROUND_TYPES})


def test_blend_against_reference_at_points():
    rng = np.random.default_rng(0)
    colours = rng.random((6, 3))
    layer = _constant_layer(colours)
    w = rng.random((50, 6)) ** 2
    pos = rng.random((50, 3)) * 100
    n = rng.normal(size=(50, 3))
    n[:, 1] = np.abs(n[:, 1]) + 0.1
    albedo, normal = gd.blend(layer, w, pos, n, np.full(50, 0.01), min_weight=0.0)
    np.testing.assert_allclose(albedo, (w / w.sum(1, keepdims=True)) @ colours, rtol=1e-5)
    np.testing.assert_allclose(normal, n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-6)
    # a real texture on flat ground, one type, a texel centre at MIP 0: that texel
    tex = gd.detail_textures(1, 32)
    layer = gd.DetailLayer.from_textures(tex)
    k = GROUND_TYPES.index("rock")
    tile = gd.DETAIL_SETS["rock"].tile_m
    i, j = 5, 19  # column, row
    p = np.array([[(i + 0.5) * tile / 32 + 3 * tile, 123.0, (j + 0.5) * tile / 32 - 2 * tile]])
    one = np.zeros((1, 6))
    one[0, k] = 1
    a, nrm = gd.blend(layer, one, p, np.array([[0.0, 1.0, 0.0]]), np.array([1e-4]))
    np.testing.assert_allclose(a[0], tex["rock"][0][j, i], atol=1e-6)
    # its normal: the texel's tangent normal, s east and t north (world -z)
    tn = 2 * tex["rock"][1][j, i] - 1
    want = np.array([tn[0] / tn[2], 1.0, -tn[1] / tn[2]])
    np.testing.assert_allclose(nrm[0], want / np.linalg.norm(want), atol=2e-3)


def test_small_weights_are_skipped_without_changing_the_level():
    layer = _constant_layer(np.full((6, 3), 0.4))
    w = np.array([[0.9995, 0.0005, 0, 0, 0, 0]])
    albedo, _ = gd.blend(layer, w, np.zeros((1, 3)), np.array([[0.2, 1.0, 0.1]]), np.array([0.01]))
    np.testing.assert_allclose(albedo, 0.4, rtol=1e-6)


def _plane_normals(slope_deg, aspects):
    s = np.radians(slope_deg)
    a = np.radians(aspects)
    return np.stack([np.sin(s) * np.sin(a), np.full_like(a, np.cos(s)), np.sin(s) * np.cos(a)], -1)


def test_triplanar_does_not_streak_on_steep_ground():
    """A planar top projection stretches texels 1 / cos(slope) along the
    fall line: 2x at 60 degrees, 5.8x at 80, without bound towards cliffs.
    The triplanar blend stays within sqrt(3) (the stretch of every
    projection on a plane facing (1, 1, 1), the worst case) on every plane."""
    aspects = np.linspace(0, 360, 73)
    worst = 0.0
    for slope in np.arange(0, 91, 5):
        worst = max(worst, gd.weighted_stretch(_plane_normals(slope, aspects)).max())
    assert worst <= np.sqrt(3) + 1e-9
    assert gd.weighted_stretch(np.ones((1, 3)) / np.sqrt(3))[0] == pytest.approx(np.sqrt(3))
    # 60 and 80 degree slopes facing a side axis: close to 1, where the top projection gives 2 and 5.8
    assert gd.weighted_stretch(_plane_normals(60, np.array([0.0, 90.0])))[0] < 1.25
    assert gd.weighted_stretch(_plane_normals(80, np.array([0.0, 90.0])))[0] < 1.05


def test_sampled_detail_on_a_60_degree_plane_is_isotropic():
    """The blended albedo along the fall line of a 60 degree plane varies as
    fast as across it (a streak: much slower along); a top-only projection,
    the control, streaks 2x."""
    tex = gd.detail_textures(2, 128)
    layer = gd.DetailLayer.from_textures(tex)
    s = np.radians(60)
    n = np.array([np.sin(s), np.cos(s), 0.0])  # facing east, falling east
    fall = np.array([np.cos(s), -np.sin(s), 0.0])
    across = np.array([0.0, 0.0, 1.0])
    step = 0.01
    u, v = np.meshgrid(np.arange(160) * step, np.arange(160) * step)
    pos = u.ravel()[:, None] * fall + v.ravel()[:, None] * across
    w = np.zeros((len(pos), 6))
    w[:, GROUND_TYPES.index("scree")] = 1
    albedo, _ = gd.blend(layer, w, pos, np.tile(n, (len(pos), 1)), np.full(len(pos), step))
    lum = albedo.mean(1).reshape(160, 160)  # rows along `across`, columns along `fall`

    def ratio(img):
        return np.abs(np.diff(img, axis=0)).mean() / np.abs(np.diff(img, axis=1)).mean()

    r = ratio(lum)
    assert 0.7 < r < 1.35, r
    # the control: the top projection alone at the same points
    t = gd.DETAIL_SETS["scree"].tile_m
    top = layer.albedo[GROUND_TYPES.index("scree")].sample(pos[:, 0] / t, pos[:, 2] / t, np.zeros(len(pos)))
    assert ratio(top.mean(1).reshape(160, 160)) > 1.6


def test_mip_level_follows_the_footprint():
    tex = gd.detail_textures(3, 64)
    layer = gd.DetailLayer.from_textures(tex)
    k = GROUND_TYPES.index("grass")
    one = np.zeros((400, 6))
    one[:, k] = 1
    rng = np.random.default_rng(1)
    pos = rng.random((400, 3)) * 50
    up = np.tile([0.0, 1.0, 0.0], (400, 1))
    near, _ = gd.blend(layer, one, pos, up, np.full(400, 0.001))
    far, _ = gd.blend(layer, one, pos, up, np.full(400, 100.0))
    assert near.std(0).mean() > 5 * far.std(0).mean()  # far away: the texture's mean, no sparkle
    np.testing.assert_allclose(far, np.broadcast_to(tex["grass"][0].reshape(-1, 3).mean(0), far.shape), atol=2e-3)
