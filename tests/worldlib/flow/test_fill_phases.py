"""The plain fill's three kernels (fill_local, fill_levels, fill_combine)
each against its numpy reference, and the whole against Priority-Flood,
bit for bit; the hash-overflow fallback to relaxation."""
import numpy as np
import pytest

from worldlib.flow import device as dev
from worldlib.flow import reference as ref

from .worlds import fractal, random_small_worlds

pytestmark = pytest.mark.every_device  # kernels against their references on each runtime


def worlds():
    for trial, h, tile in random_small_worlds(2812, 12, 40):
        yield f"random{trial}", h, tile
    yield "fractal", ref.canonical(fractal(96, 5)), 16
    nested = np.full((45, 45), 10.0, np.float32)
    for k in range(1, 22):  # rings of alternating rims and moats across tile borders
        nested[k:-k, k:-k] = 10.0 - k * (0.5 if k % 2 else -0.3)
    yield "nested", nested, 8
    yield "flat", np.zeros((23, 31), np.float32), 7
    yy, xx = np.mgrid[0:40, 0:40]
    yield "bowl", (((xx - 20.0) ** 2 + (yy - 20.0) ** 2) * -0.01 + 50).astype(np.float32), 8


CASES = list(worlds())


@pytest.mark.parametrize("name,h,tile", CASES, ids=[c[0] for c in CASES])
def test_each_phase_equals_its_reference(cl_env, name, h, tile):
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    parts: dict = {}
    got = dev._fill_plain(cl_env, h, kind, tile, None, None, parts)
    assert got is not None  # no hash overflow on these worlds
    data = kind != ref.NODATA
    np.testing.assert_array_equal(parts["Wloc"][data], ref.fill_local(h, kind, tile)[data])
    label = np.where(data, parts["label"], -1)
    # every label is a node (perimeter slot) of the cell's own tile
    lab = label[label >= 0]
    cells = np.nonzero(label >= 0)
    pmax = 4 * tile
    tiles_x = -(-h.shape[1] // tile)
    assert (lab // pmax == (cells[0] // tile) * tiles_x + cells[1] // tile).all()
    level = ref.fill_levels(kind, parts["Wloc"], label)
    for node, want in level.items():
        if node >= 0:
            assert parts["level"][node] == np.float32(want), (node, parts["level"][node], want)
    np.testing.assert_array_equal(got, ref.fill_combine(h, kind, parts["Wloc"], label, level))
    np.testing.assert_array_equal(got, ref.priority_flood(h, False, kind))


@pytest.mark.parametrize("name,h,tile", CASES[::6], ids=[c[0] for c in CASES[::6]])
def test_hash_overflow_falls_back_to_relaxation(cl_env, monkeypatch, name, h, tile):
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    monkeypatch.setattr(dev, "_fill_hash", lambda tile: 1)  # no label pair fits, nor in 4 times that
    stats: dict = {}
    got = dev.fill(cl_env, h, kind, False, tile=tile, stats=stats)
    np.testing.assert_array_equal(got, ref.priority_flood(h, False, kind))


def test_overflowing_world_takes_the_relaxation(cl_env, monkeypatch):
    h = ref.canonical(fractal(64, 9))
    kind = ref.cell_kinds(h)
    stats: dict = {}
    dev.fill(cl_env, h, kind, False, tile=16, stats=stats)
    assert stats["method"] == "labels"
    monkeypatch.setattr(dev, "_fill_hash", lambda tile: 1)
    stats = {}
    got = dev.fill(cl_env, h, kind, False, tile=16, stats=stats)
    assert "method" not in stats and stats["passes"] > 1
    np.testing.assert_array_equal(got, ref.priority_flood(h, False, kind))
