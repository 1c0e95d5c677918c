"""Each kernel against its numpy / pure-Python reference, exactly."""
import numpy as np
import pytest

from worldlib.flow import device as dev
from worldlib.flow import reference as ref

pytestmark = pytest.mark.every_device  # kernels against their references on each runtime


def terrains():
    rng = np.random.default_rng(7)
    yield "noise", (rng.random((37, 53)) * 50 + 100).astype(np.float32)
    hi = (rng.random((41, 29)) * 3 + 4000).astype(np.float32)  # float32 at 4000 m: ulp 2.4e-4 m
    yield "high", hi
    nd = (rng.random((30, 30)) * 10).astype(np.float32)
    nd[rng.random((30, 30)) < 0.08] = np.nan
    nd[10:14, 10:14] = np.inf
    yield "nodata", nd
    yield "flat", np.zeros((23, 31), np.float32)
    yy, xx = np.mgrid[0:40, 0:40]
    yield "bowl", ((xx - 20.0) ** 2 + (yy - 20.0) ** 2).astype(np.float32) * -0.01 + 50
    nested = np.full((33, 33), 10.0, np.float32)
    for k in range(1, 16):
        nested[k:-k, k:-k] = 10.0 - k * (0.5 if k % 2 else -0.3)
    yield "nested", nested
    yield "1x1", np.array([[5.0]], np.float32)
    yield "1xN", (rng.random((1, 17)) * 5).astype(np.float32)
    yield "Nx2", (rng.random((19, 2)) * 5).astype(np.float32)
    yield "negative", (rng.random((20, 20)) * 2 - 1).astype(np.float32)


CASES = list(terrains())


@pytest.mark.parametrize("name,h", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("eps", [False, True])
def test_fill_equals_priority_flood(cl_env, name, h, eps):
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    want = ref.priority_flood(h, eps, kind)
    for tile, local in ((64, None), (8, 4), (5, 1)):
        got = dev.fill(cl_env, h, kind, eps, tile=tile, local=local)
        np.testing.assert_array_equal(got, want)  # bit-exact, NaN where no-data
    data = kind != ref.NODATA
    assert (got[data] >= h[data]).all()


@pytest.mark.parametrize("name,h", CASES, ids=[c[0] for c in CASES])
def test_epsilon_fill_drains_everything(cl_env, name, h):
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    R = dev.fill(cl_env, h, kind, True)
    code = dev.d8(cl_env, np.nan_to_num(R, nan=0.0), kind, 8.0)
    np.testing.assert_array_equal(code, ref.d8(np.nan_to_num(R, nan=0.0), kind, 8.0))
    assert not (code == ref.PIT).any()  # every interior cell has a strictly lower neighbour
    acc = dev.accumulate(cl_env, code)
    data = kind != ref.NODATA
    assert int(acc[kind == ref.EDGE].astype(np.int64).sum()) == int(data.sum())  # all water reaches an edge


@pytest.mark.parametrize("name,h", CASES[:6], ids=[c[0] for c in CASES[:6]])
def test_d8_and_accumulation_match_reference(cl_env, name, h):
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    raw = np.nan_to_num(h, nan=0.0, posinf=0.0)
    code = dev.d8(cl_env, raw, kind, 3.0, local=(4, 4))
    np.testing.assert_array_equal(code, ref.d8(raw, kind, 3.0))  # raw terrain: pits (-3) allowed
    want = ref.accumulate(code)
    np.testing.assert_array_equal(want, ref.accumulate_sweeps(code))  # seed 003 algorithm 1 agrees
    rng = np.random.default_rng(3)
    w = rng.integers(0, 10**12, code.shape)
    want_w = ref.accumulate(code, w)
    for tile, local in ((64, None), (7, 2), (1, 1), (16, 3)):
        np.testing.assert_array_equal(dev.accumulate(cl_env, code, tile=tile, local=local), want)
        np.testing.assert_array_equal(dev.accumulate(cl_env, code, w, tile=tile, local=local), want_w)


def test_accumulation_through_many_tiles_matches_reference(cl_env):
    """Paths that cross many tiles and merge in other tiles than they
    entered (acc_final walks each entry's path once, in segments that end
    where they join an earlier one): every tile and work-group size, random pits."""
    rng = np.random.default_rng(11)
    rows, cols = 300, 257
    h = np.add.outer(np.linspace(0, 60, rows), np.linspace(0, 40, cols)) + rng.normal(size=(rows, cols)) * 3.0
    kind = ref.cell_kinds(h)
    code = dev.d8(cl_env, h, kind, 1.0, local=(4, 4))
    assert (code == ref.PIT).any()
    want = ref.accumulate(code)
    w = rng.integers(0, 10**12, code.shape)
    want_w = ref.accumulate(code, w)
    for tile, local in ((128, 16), (127, 3), (3, 5)):
        np.testing.assert_array_equal(dev.accumulate(cl_env, code, tile=tile, local=local), want)
        np.testing.assert_array_equal(dev.accumulate(cl_env, code, w, tile=tile, local=local), want_w)


def test_quantized_weights_sum_exactly():
    w = np.array([[1e-3, 2.5, 0.0], [np.nan, 7.0, 1e6]])
    q, scale = dev.quantize(w)
    assert q.dtype == np.int64 and q.sum() < 2**62
    np.testing.assert_allclose(q / scale, np.nan_to_num(w), rtol=1e-12, atol=1e6 * 2.0**-50)


def test_wetness_matches_reference(cl_env):
    rng = np.random.default_rng(5)
    h = ref.canonical((rng.random((24, 33)) * 20).astype(np.float32))
    h[3, 4] = np.nan
    kind = ref.cell_kinds(h)
    acc = rng.random(h.shape).astype(np.float32) * 1e5 + 64
    water = rng.random(h.shape).astype(np.float32)
    ext = rng.random(h.shape).astype(np.float32) * 0.5
    args = (h, kind, acc, water, ext, 8.0, 1e-3, 3.0, 12.0)
    t, m = dev.wetness(cl_env, *args)
    tr, mr = ref.wetness(*args)
    np.testing.assert_allclose(t, tr, rtol=2e-6, atol=2e-6)  # OpenCL log: a few ulps
    np.testing.assert_allclose(m, mr, rtol=2e-6, atol=2e-6)
    assert np.isnan(t[3, 4]) and np.isnan(m[3, 4])
    assert (m[kind != ref.NODATA] >= 0).all() and (m[kind != ref.NODATA] <= 1).all()


@pytest.mark.parametrize("name,h", CASES, ids=[c[0] for c in CASES])
def test_breach_kernel_equals_reference(cl_env, name, h):
    h = ref.canonical(h)
    kind = ref.cell_kinds(h)
    np.testing.assert_array_equal(dev.breach(cl_env, h, kind), ref.breach(h, kind))  # bit-exact, NaN where no-data


def test_breach_drains_without_filling(cl_env):
    h = np.full((21, 21), 10.0, np.float32)
    h[5:16, 5:16] = 2.0  # a pit ringed by a 10 m rim
    h[10, 10] = 1.0
    kind = ref.cell_kinds(h)
    b = dev.breach(cl_env, h, kind)
    assert (b <= h).all() and b[10, 10] == 1.0  # carved, never raised
    np.testing.assert_array_equal(dev.fill(cl_env, b, kind, False), b)  # no depression left (non-ascending paths)
    assert (b < h).sum() >= 5  # a channel was cut through the rim
    # with the epsilon step on top (the stage's routing surface), the pit drains to an edge
    code = ref.d8(dev.fill(cl_env, b, kind, True), kind, 1.0)
    rcv = ref.receivers(code)
    c = 10 * 21 + 10
    hops = 0
    while rcv[c] >= 0 and hops < 100:
        c, hops = rcv[c], hops + 1
    assert kind.ravel()[c] == ref.EDGE


def test_pysheds_agreement(cl_env):
    """D8 alignment with pysheds: we use pysheds' neighbour order (N, NE, E,
    SE, S, SW, W, NW), the first steepest neighbour, edge cells as outlets.
    pysheds' fill_depressions equals our fill bit for bit; its flowdir on our
    epsilon-filled DEM agrees except on float32/float64 slope ties; its
    accumulation of our directions equals ours exactly."""
    np.in1d = getattr(np, "in1d", np.isin)
    pytest.importorskip("affine")
    sg = pytest.importorskip("pysheds.sgrid")
    from affine import Affine
    from pysheds.sview import Raster, ViewFinder

    rng = np.random.default_rng(11)
    yy, xx = np.mgrid[0:64, 0:80]
    h = ref.canonical((np.sin(xx / 7.0) * 20 + np.cos(yy / 5.0) * 15 + rng.random((64, 80)) * 8 + 1000).astype(np.float32))
    kind = ref.cell_kinds(h)
    vf = ViewFinder(affine=Affine(8.0, 0, 0, 0, -8.0, 0), shape=h.shape, nodata=np.nan)
    grid = sg.sGrid(viewfinder=vf)
    filled = np.asarray(grid.fill_depressions(Raster(h.astype(np.float64), viewfinder=vf)))
    np.testing.assert_array_equal(dev.fill(cl_env, h, kind, False), filled.astype(np.float32))
    R = dev.fill(cl_env, h, kind, True)
    code = dev.d8(cl_env, R, kind, 8.0)
    dirmap = np.array([64, 128, 1, 2, 4, 8, 16, 32])
    pfd = np.asarray(grid.flowdir(Raster(R.astype(np.float64), viewfinder=vf)))
    interior = kind == ref.INTERIOR
    agree = (pfd[interior] == dirmap[code[interior]]).mean()
    assert agree > 0.999
    ours = np.where(code >= 0, dirmap[np.clip(code, 0, 7)], 0).astype(np.int64)
    pacc = np.asarray(grid.accumulation(Raster(ours, viewfinder=ViewFinder(affine=vf.affine, shape=h.shape, nodata=0))))
    mine = dev.accumulate(cl_env, code).astype(np.float64)
    # pysheds counts a cell with no direction (our edge outlets, fdir 0 = its nodata) as weighing 0
    np.testing.assert_array_equal(pacc[interior], mine[interior])
    np.testing.assert_array_equal(pacc[~interior], mine[~interior] - 1)
