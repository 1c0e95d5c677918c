"""The ecosystem simulation: self-thinning as Deussen's sequential rule,
population plateau, species balance, shares of space."""
import math

import numpy as np

from stages.vegetation import device as dev
from stages.vegetation import ecosystem as eco
from stages.vegetation import reference as ref
from stages.vegetation.params import VegetationParams


def sequential_thinning(rec: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """Deussen's rule one plant at a time: strongest first (ties: larger cell
    index), a plant survives when it overlaps no survivor."""
    idx = np.nonzero(alive.ravel())[0]
    r = rec.reshape(-1, 4)[idx]
    order = np.lexsort((-idx, -r[:, 3].astype(np.float64)))
    keep = []
    for k in order:
        p = r[k]
        ok = True
        for j in keep:
            q = r[j]
            dxx, dz = np.float32(p[0] - q[0]), np.float32(p[1] - q[1])
            rr = np.float32(p[2] + q[2])
            if dxx * dxx + dz * dz < rr * rr:
                ok = False
                break
        if ok:
            keep.append(k)
    out = np.zeros(alive.size, bool)
    out[idx[keep]] = True
    return out.reshape(alive.shape)


def test_parallel_rounds_equal_the_sequential_rule():
    """With no shade tolerance the parallel rounds (local maxima win) keep
    exactly the plants the strongest-first sequential rule keeps."""
    p = VegetationParams(initial_density_per_ha=1e5)
    names = p.plant_species()
    rng = np.random.default_rng(0)
    suit = rng.random((len(names), 24, 30)).astype(np.float32)
    tab, nb = eco.species_table(p, names, 3.0, seed=5)  # 3 m cells: many overlaps
    tab = tab.reshape(len(names), ref.SPW)
    tab[:, 5] = 0.0  # shade tolerance off
    sp, birth = eco.initial_state(suit, p, names, 5, 3.0)
    sim = ref.Sim(sp, birth, suit, tab.ravel(), nb)
    sim.thin_init(0)
    rec, alive = sim.rec.copy(), sim.st == 1
    rounds = 0
    while sim.thin_round(0, rounds):
        rounds += 1
    assert rounds >= 2  # chains of domination needed more than one round
    want = sequential_thinning(rec, alive)
    np.testing.assert_array_equal(sim.sp >= 0, want)
    # the survivors' spheres do not overlap
    r = rec.reshape(-1, 4)[np.nonzero(want.ravel())[0]]
    d = np.hypot(r[:, None, 0] - r[None, :, 0], r[:, None, 1] - r[None, :, 1])
    np.fill_diagonal(d, np.inf)
    assert (d >= (r[:, None, 2] + r[None, :, 2]) * (1 - 1e-6)).all()


def test_population_reaches_a_plateau_and_species_coexist(cl_env):
    """Two identical species on a uniform suitable field: the population
    settles (self-thinning) and neither takes over."""
    base = VegetationParams().species["conifer"]
    twin = base.model_copy()
    p = VegetationParams(species={"a": base.model_dump(), "b": twin.model_dump()}, grow=["a", "b"],
                         years=300, step_years=10)
    suit = np.ones((2, 48, 48), np.float32)
    res = eco.simulate(suit, eco.SimGrid(48, 48, 8.0), p, ["a", "b"], 3, dev.on(cl_env))
    st = res.stats
    assert st["population_after_first_thinning"] < st["population_start"]  # it thins itself
    assert st["plateau_relative_std"] < 0.05
    assert abs(st["species_shares"]["a"] - 0.5) < 0.1
    assert st["share_evenness"] > 0.95


def test_relative_yield_follows_the_winner(cl_env):
    """Where one species is more suitable it wins (its strength scales with
    suitability): its relative yield is high and the other's low; alone, a
    species' relative yield is about 1."""
    p = VegetationParams(years=100, step_years=5)
    names = ["conifer", "broadleaf"]
    p = p.model_copy(update={"grow": names})
    suit = np.zeros((2, 40, 80), np.float32)
    suit[0, :, :40], suit[1, :, :40] = 1.0, 0.3
    suit[0, :, 40:], suit[1, :, 40:] = 0.3, 1.0
    res = eco.simulate(suit, eco.SimGrid(80, 40, 8.0), p, names, 11, dev.on(cl_env))
    alone = eco.alone_density(p, names, 8.0, 11, dev.on(cl_env))
    assert (np.diff(alone, axis=1) >= -0.05).all() and (alone[:, -1] > 0.3).all()  # more suitable, denser
    ry = eco.relative_yield(res, p, suit, alone, 8.0, (40, 80))
    assert ry.min() >= 0 and ry.max() <= 1
    assert ry[0, 5:35, 5:30].mean() > 0.7 > 0.4 > ry[1, 5:35, 5:30].mean()
    assert ry[1, 5:35, 50:75].mean() > 0.7 > 0.4 > ry[0, 5:35, 50:75].mean()
    solo = p.model_copy(update={"grow": ["conifer"]})
    one = eco.simulate(suit[:1], eco.SimGrid(80, 40, 8.0), solo, ["conifer"], 11, dev.on(cl_env))
    ry1 = eco.relative_yield(one, solo, suit[:1], alone[:1], 8.0, (40, 80))
    assert abs(ry1[0, 5:35, 5:75].mean() - 1.0) < 0.15
    assert math.isfinite(res.stats["plateau_relative_change"])


def test_simulation_grid_by_blocks_and_yield_by_window():
    """On 1 m cells the 8 m simulation cells are 8 x 8 blocks: their means
    (worldlib's, the same bits for a tile) equal the box filter's to
    round-off and have a tile's bits; the relative yield read back on a
    window of the terrain has the whole terrain's bits."""
    from pipeline.tiles import tiles_of
    from scipy import ndimage

    rng = np.random.default_rng(3)
    suit = rng.random((2, 64, 96)).astype(np.float32)
    grid = eco.sim_grid(96, 64, 1.0, 8.0)
    assert eco.block_factor(64, 96, 1.0, grid) == 8 and eco.block_factor(64, 96, 3.0, grid) == 0
    blocks = eco.to_sim_grid(suit, 1.0, grid)
    box = ndimage.uniform_filter(suit.astype(np.float64), size=(1, 8, 8), mode="nearest")[:, 4::8, 4::8]
    np.testing.assert_allclose(blocks, box, rtol=0, atol=1e-6)
    for tile in tiles_of((64, 96), 32):
        part = suit[:, tile.row0:tile.row0 + tile.rows, tile.col0:tile.col0 + tile.cols]
        np.testing.assert_array_equal(eco.to_sim_grid(part, 1.0, eco.sim_grid(tile.cols, tile.rows, 1.0, 8.0)),
                                      blocks[:, tile.row0 // 8:(tile.row0 + tile.rows) // 8,
                                             tile.col0 // 8:(tile.col0 + tile.cols) // 8])
    ry = rng.random((2, grid.nz, grid.nx))
    whole = eco.yield_on_terrain(ry, 8.0, 1.0, (64, 96))
    for first, cells in (((0, 0), (20, 30)), ((17, 41), (47, 55)), ((63, 95), (1, 1))):
        np.testing.assert_array_equal(eco.yield_on_terrain(ry, 8.0, 1.0, (64, 96), first, cells),
                                      whole[:, first[0]:first[0] + cells[0], first[1]:first[1] + cells[1]])
