"""worldlib.terrain.blocks: block sums in their one fixed order, whichever
way (strided adds or a cumulative sum, in strips) computes them."""
import numpy as np
import pytest

from worldlib.terrain import blocks
from worldlib.terrain.blocks import block_sum, coarse_factor


def in_order(a: np.ndarray, f: int) -> np.ndarray:
    """Each block's cells added one by one from 0, its rows top first, each left to right."""
    nr, nc = a.shape[0] // f, a.shape[1] // f
    out = np.zeros((nr, nc))
    for br in range(nr):
        for bc in range(nc):
            total = 0.0
            for v in a[br * f:(br + 1) * f, bc * f:(bc + 1) * f].ravel():
                total += float(v)
            out[br, bc] = total
    return out


@pytest.mark.parametrize("shape, f", [((12, 9), 1), ((30, 45), 3), ((130, 131), 65), ((256, 200), 100)])
def test_a_block_sum_is_its_cells_added_in_order_bit_for_bit(shape, f, monkeypatch):
    rng = np.random.default_rng(f)
    a = rng.standard_normal(shape) * 10.0 ** rng.uniform(-8, 8, shape)  # magnitudes where the order shows
    want = in_order(a, f)
    assert np.array_equal(block_sum(a, f), want)
    monkeypatch.setattr(blocks, "BLOCK_ROWS_AT_ONCE", 1)  # one row of blocks at a time
    assert np.array_equal(block_sum(a, f), want)
    assert np.array_equal(block_sum(a.astype(np.float32), f), in_order(a.astype(np.float32), f))


def test_a_tiles_blocks_are_the_whole_maps():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((300, 400)) * 1e6
    for f in (4, 100):
        whole = block_sum(a, f)
        assert np.array_equal(block_sum(a[100:300, 200:400], f), whole[100 // f:, 200 // f:])


def test_coarse_factor_divides_the_sides():
    assert coarse_factor(8192, 8192, 1.0, 8.0) == 8
    assert coarse_factor(1000, 1000, 1.0, 8.0) == 8 and coarse_factor(1001, 1001, 1.0, 8.0) == 7
    assert coarse_factor(64, 64, 8.0, 8.0) == 1 and coarse_factor(64, 64, 1.0, 0.0) == 1
