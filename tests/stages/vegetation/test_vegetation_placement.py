"""Poisson-disk placement: saturation constant, density against the target
over 64 x 64-cell windows, minimum distances, nothing where nothing may grow,
determinism, independence between species, heights on the terrain mesh."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from stages.vegetation import device as dev
from stages.vegetation import placement as pl
from stages.vegetation import reference as ref
from stages.vegetation.params import KAPPA, VegetationParams
from worldlib.terrain.mesh import build_terrain_mesh, height_on_mesh
from pipeline.grid import Grid

from .conftest import synthetic_height
from pipeline.opencl import get_cl

DX = 4.0
N = 192
NAMES = ["conifer", "broadleaf", "shrub"]


def targets(p: VegetationParams) -> np.ndarray:
    """Smoothly varying targets with empty zones (plants per m^2)."""
    z, x = np.meshgrid(np.arange(N) / N, np.arange(N) / N, indexing="ij")
    out = []
    for s, name in enumerate(NAMES):
        d = p.species[name].density_per_ha / 1e4
        f = 0.55 + 0.45 * np.sin(2 * np.pi * (x + 0.3 * s)) * np.cos(2 * np.pi * z)
        f[(x - 0.2 - 0.3 * s) ** 2 + (z - 0.6) ** 2 < 0.01] = 0.0  # a hole each
        out.append(d * f)
    t = np.stack(out)
    t[:, 0, :] = t[:, -1, :] = 0
    t[:, :, 0] = t[:, :, -1] = 0
    return t


@pytest.fixture(scope="module")
def placed():
    cl_env = get_cl()  # the device a bake would use (an every_device test's, when it runs)
    p = VegetationParams()
    dom = pl.Domain(N, N, DX, (100.0, 200.0))
    n_t = targets(p)
    return p, dom, n_t, pl.place_species(p, NAMES, n_t, dom, 42, dev.on(cl_env))


def test_saturation_constant(cl_env):
    """A saturated set of constant radius r holds at least KAPPA / r^2 points
    per m^2 after the default passes (the radius rule relies on it)."""
    p = VegetationParams()
    dom = pl.Domain(151, 151, 4.0, (0.0, 0.0))
    r = 5.0
    pts, _, _ = pl.poisson_sample(np.full((151, 151), r, np.float32), r, dom, p.poisson_passes, 3, dev.on(cl_env))
    kappa = len(pts) * r * r / (dom.width * dom.depth)
    assert KAPPA <= kappa < KAPPA + 0.05


def test_density_matches_target(placed):
    p, dom, n_t, done = placed
    for s, name in enumerate(NAMES):
        err = pl.density_error(done[name].x, done[name].z, n_t[s], dom, window=64)
        assert err["windows"] >= 6
        assert err["max_relative_error"] <= 0.05, (name, err)
        assert done[name].stats["shortfall_plants"] <= 0.002 * done[name].stats["target_plants"]


def test_minimum_distances(placed):
    p, dom, n_t, done = placed
    for name in NAMES:
        q = done[name]
        xy = np.stack([q.x, q.z], 1).astype(np.float64)
        pairs = cKDTree(xy).query_pairs(2 * float(q.r.max()), output_type="ndarray")
        d = np.hypot(*(xy[pairs[:, 0]] - xy[pairs[:, 1]]).T)
        need = np.maximum(q.r[pairs[:, 0]], q.r[pairs[:, 1]])
        assert (d >= need).all(), name
        assert q.r.min() >= p.species[name].min_spacing_m
    for a in NAMES:
        for b in NAMES:
            if a >= b:
                continue
            pa = np.stack([done[a].x, done[a].z], 1)
            pb = np.stack([done[b].x, done[b].z], 1)
            clear = p.species[a].collision_radius_m + p.species[b].collision_radius_m
            d, _ = cKDTree(pa).query(pb, k=1)
            assert d.min() >= clear, (a, b)


def test_nothing_where_the_target_is_zero(placed):
    p, dom, n_t, done = placed
    for s, name in enumerate(NAMES):
        tr, tc = dom.cell_of(done[name].x, done[name].z)
        assert (n_t[s][tr, tc] > 0).all()


def test_deterministic_and_seeded(cl_env, placed):
    p, dom, n_t, done = placed
    again = pl.place_species(p, NAMES, n_t, dom, 42, dev.on(cl_env), local=(8, 8))
    other = pl.place_species(p, NAMES, n_t, dom, 43, dev.on(cl_env))
    for name in NAMES:
        np.testing.assert_array_equal(again[name].x, done[name].x)
        np.testing.assert_array_equal(again[name].z, done[name].z)
        assert not np.array_equal(other[name].x[:100], done[name].x[:100])


def test_other_species_do_not_move(cl_env, placed):
    """Species are placed in order of collision radius (broadleaf, conifer,
    shrub): a change to a later species never moves an earlier one; a change
    to an earlier one moves a later one only near the earlier one's plants
    (trunk clearance) and the dart cascade around them."""
    p, dom, n_t, done = placed
    assert pl.placement_order(p, NAMES) == ["broadleaf", "conifer", "shrub"]
    n2 = n_t.copy()
    n2[2] *= 0.7  # shrubs thinner
    a = pl.place_species(p, NAMES, n2, dom, 42, dev.on(cl_env))
    for name in ("broadleaf", "conifer"):
        np.testing.assert_array_equal(a[name].x, done[name].x)
    n3 = n_t.copy()
    n3[0][:, : N // 2] = 0.0  # conifers gone from the west half
    b = pl.place_species(p, NAMES, n3, dom, 42, dev.on(cl_env))
    np.testing.assert_array_equal(b["broadleaf"].x, done["broadleaf"].x)
    # shrubs far from every old conifer kept their places
    old_conifer = np.stack([done["conifer"].x, done["conifer"].z], 1)
    shrub_old = set(zip(done["shrub"].x.tolist(), done["shrub"].z.tolist()))
    shrub_new = set(zip(b["shrub"].x.tolist(), b["shrub"].z.tolist()))
    changed = np.array(sorted(shrub_old ^ shrub_new))
    d, _ = cKDTree(old_conifer).query(changed, k=1)
    far = d > 6 * p.species["shrub"].min_spacing_m * 2
    # changes happen near the removed conifers, or through the per-block selection of the blocks they touch
    block = p.density_block_m
    in_changed_half = changed[:, 0] < N // 2 * DX + block
    assert (~far | in_changed_half).all()
    assert len(shrub_old & shrub_new) > 0.4 * len(shrub_old)


def test_instances_lie_on_the_terrain_mesh(placed):
    p, dom, n_t, done = placed
    h = synthetic_height(N, N, DX, seed=1)
    mesh = build_terrain_mesh(Grid(h, DX, ("height",), dom.origin_m), 97)  # a coarser lattice than the grid
    for s, name in enumerate(NAMES):
        inst = pl.instances(done[name], s, p, dom, mesh, None, 42)
        pos = inst.positions.astype(np.float64)
        want = height_on_mesh(mesh, pos[:, 0], pos[:, 2])
        assert np.abs(pos[:, 1] - want).max() <= 1e-3
        q = inst.orientations.astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=2e-3)
        s0, s1 = p.species[name].scale_range
        assert (inst.scales > 0.9 * s0).all() and (inst.scales < 1.1 * s1).all()


def test_nothing_stands_in_a_river_wider_than_its_cells():
    """A river one cell wide but 12 m across (half width 6 m) on 8 m cells,
    straight then diagonal: every instance within 6 m + the margin of its
    centre line goes, wherever along the line, and every other stays."""
    from stages.vegetation.placement import Domain, Instances, keep_out_of_water

    rows = cols = 9
    dom = Domain(rows, cols, 8.0, (0.0, 0.0))
    water = np.zeros((rows, cols), bool)
    water[:5, 4] = True  # the centre line at x = 36 m down to z = 36 m, then south-east at 45 degrees
    for k in range(1, 4):
        water[4 + k, 4 + k] = True
    half = np.where(water, 6.0, 0.0)
    rng = np.random.default_rng(3)
    z = rng.uniform(8.0, 64.0, 400)
    off = rng.uniform(-20.0, 20.0, 400)
    pos = np.stack([36.0 + off, np.zeros_like(z), z], 1).astype(np.float32)
    n = len(z)
    inst = Instances("tree", pos, np.zeros((n, 4), np.float16), np.ones((n, 3), np.float32), np.ones(n, np.float32),
                     np.zeros(n, np.float32), np.arange(n), np.ones(n, np.float32))
    kept, dropped = keep_out_of_water(inst, water, half, dom, margin_m=0.5)
    def from_line(p):
        x, z = p[:, 0].astype(np.float64), p[:, 2].astype(np.float64)
        straight = np.where(z <= 36.0, np.abs(x - 36.0), np.hypot(x - 36.0, z - 36.0))
        t = np.clip(((x - 36.0) + (z - 36.0)) / 2.0, 0.0, 24.0)  # along the diagonal to (60, 60)
        return np.minimum(straight, np.hypot(x - 36.0 - t, z - 36.0 - t))

    assert from_line(kept.positions).min() >= 6.5, "an instance stands in the river"
    assert len(kept) == (from_line(pos) >= 6.5).sum(), "an instance off the river was dropped"
    assert dropped == n - len(kept) and len(inst) == n  # the input is not modified


def test_select_counts_of_block_windows_is_the_whole_worlds():
    """Windows of whole blocks (the last ones cut by the world's edge) keep
    the candidates the whole world keeps, and their exact targets add up to
    the world's; a window cutting a block is refused."""
    dom = pl.Domain(90, 110, 4.0, (0.0, 0.0))
    rng = np.random.default_rng(2)
    n_t = (rng.random((90, 110)) * 0.02).astype(np.float64)
    rad = np.full((90, 110), 5.0, np.float32)
    pts, cells, _ = pl.poisson_sample(rad, 5.0, dom, 2, 17, ref)
    block = 16
    kept, stats, target = pl.select_counts(pts, cells, n_t, dom, block, 23)
    assert 0 < kept.sum() < len(kept)
    tr, tc = dom.cell_of(pts[:, 0], pts[:, 1])
    total = 0
    for r0, r1 in ((0, 48), (48, 90)):
        for c0, c1 in ((0, 32), (32, 96), (96, 110)):
            mine = (tr >= r0) & (tr < r1) & (tc >= c0) & (tc < c1)
            k, _, t = pl.select_counts(pts[mine], cells[mine], n_t[r0:r1, c0:c1], dom, block, 23, (r0, c0))
            np.testing.assert_array_equal(k, kept[mine])
            total += t
    assert total == target
    with pytest.raises(ValueError, match="cuts blocks"):
        pl.select_counts(pts[:0], cells[:0], n_t[:40, :32], dom, block, 23)
