"""The depressions' merge sweep on the sparse depression cells: the
kernel against reference.merge_tree_reference, node for node."""
import numpy as np
import pytest

from worldlib.flow import device as dev
from worldlib.flow import reference as ref

from .worlds import fractal

pytestmark = pytest.mark.every_device  # the kernel against its reference on each runtime

FIELDS = ("parent", "child_a", "child_b", "birth", "entry_a", "entry_b", "cell_node")


def sparse_inputs(cl_env, h):
    """The sweep's inputs as the lakes build them: depression cells (interior,
    fill above the terrain) in (height, index) order, each one's pit on the
    steepest descent (sparse), and the 8-neighbour lists."""
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    F = dev.fill(cl_env, h, kind, False)
    cells = np.flatnonzero(((kind == ref.INTERIOR) & (F > h)).ravel())
    rcv = ref.receivers(dev.d8(cl_env, np.nan_to_num(h, nan=0.0), kind, 2.0))[cells]
    term = np.where(rcv < 0, np.arange(cells.size), np.searchsorted(cells, rcv))  # a lower neighbour stays in D
    assert (cells[term] == np.where(rcv < 0, cells, rcv)).all()
    while not np.array_equal(term[term], term):
        term = term[term]
    hs = h.ravel()[cells]
    order = np.lexsort((np.arange(cells.size), hs.astype(np.float64)))
    return order, hs, term, ref.sparse_neighbours(cells, h.shape[1], h.size)


def cases():
    rng = np.random.default_rng(11)
    two = np.full((20, 40), 10.0, np.float32)
    two[5:15, 3:15] = 6.0
    two[5:15, 22:37] = 0.0
    two[9, 15:22] = 8.0
    yield "two_basins", two
    yield "noise", (rng.random((45, 38)) * 20).astype(np.float32)
    nested = np.full((33, 33), 10.0, np.float32)
    for k in range(1, 16):
        nested[k:-k, k:-k] = 10.0 - k * (0.5 if k % 2 else -0.3)
    yield "nested", nested
    yield "ties", np.round(rng.random((40, 40)) * 3).astype(np.float32)  # many equal heights: ties by index
    yield "flat", np.zeros((10, 12), np.float32)  # no depression cells
    holes = fractal(150, 3, 1.8)
    holes[rng.random(holes.shape) < 0.02] = np.nan
    holes[40:52, 60:70] = np.inf
    yield "fractal_holes", holes


def assert_same_tree(got, want):
    for f in FIELDS:
        a, b = getattr(got, f), getattr(want, f)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f


@pytest.mark.parametrize("name,h", list(cases()), ids=[c[0] for c in cases()])
def test_merge_sweep_kernel_equals_reference(cl_env, name, h):
    args = sparse_inputs(cl_env, h)
    want = ref.merge_tree_reference(*args)
    assert_same_tree(dev.merge_sweep(cl_env, *args), want)
    assert want.cell_node.size == args[0].size and (want.cell_node >= 0).all()


def test_merge_sweep_on_arbitrary_sparse_sets(cl_env):
    """Random cell subsets of a map (its border included), heights with ties,
    terminals anywhere or -1 (a path leaving the set: no entry node)."""
    rng = np.random.default_rng(5)
    for trial in range(12):
        rows, cols = (int(x) for x in rng.integers(1, 30, 2))
        cells = np.flatnonzero(rng.random(rows * cols) < rng.uniform(0.2, 1.0))
        m = cells.size
        hs = np.round(rng.random(m) * (3 if trial % 2 else 100)).astype(np.float32)
        term = rng.integers(-1, max(m, 1), m)
        order = np.lexsort((np.arange(m), hs.astype(np.float64)))
        args = (order, hs, term, ref.sparse_neighbours(cells, cols, rows * cols))
        assert_same_tree(dev.merge_sweep(cl_env, *args), ref.merge_tree_reference(*args))


def test_sparse_neighbours_match_the_grid():
    rng = np.random.default_rng(8)
    rows, cols = 13, 17
    member = rng.random((rows, cols)) < 0.5
    cells = np.flatnonzero(member)
    nbr = ref.sparse_neighbours(cells, cols, rows * cols)
    assert nbr.dtype == np.int32 and nbr.shape == (cells.size, 8)
    for i, c in enumerate(cells.tolist()):
        r, cc = divmod(c, cols)
        for k in range(8):
            rr, c2 = r + int(ref.DR[k]), cc + int(ref.DC[k])
            inside = 0 <= rr < rows and 0 <= c2 < cols and member[rr, c2]
            assert nbr[i, k] == (np.searchsorted(cells, rr * cols + c2) if inside else -1)
    assert ref.sparse_neighbours(np.zeros(0, np.int64), cols, rows * cols).shape == (0, 8)
