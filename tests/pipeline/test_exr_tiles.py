"""Grid EXRs are tiled and written window by window: any order of windows
gives the bytes of a whole write; windows read back only what they cover;
scanline grids from before tiling stay readable."""
import json
import random
import tracemalloc

import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline import exr
from pipeline.errors import InputError
from pipeline.grid import Grid

NAMES6 = ("splat.rock", "height", "b", "a", "flow.x", "z")


def field(shape, nchan, seed=0):
    """Random float32 with the values a lossless file must keep bit for bit."""
    rng = np.random.default_rng(seed)
    a = (rng.standard_normal((*shape, nchan)) * 1000).astype(np.float32)
    flat = a.reshape(-1)
    special = np.array([np.nan, -0.0, 0.0, np.inf, -np.inf, 1e-45, -3.4e38], np.float32)
    idx = rng.choice(flat.size, size=min(flat.size, 40), replace=False)
    flat[idx] = special[np.arange(idx.size) % special.size]
    return a if nchan > 1 else a[:, :, 0]


def windows(shape, step_rows, step_cols):
    return [(r, c) for r in range(0, shape[0], step_rows) for c in range(0, shape[1], step_cols)]


def write_windows(path, data, names, order, step_rows, step_cols, tile, provenance=None):
    with exr.GridWriter(path, data.shape[:2], names, 4.0, (100.0, -50.0), provenance, tile=tile) as out:
        for r, c in order:
            out.write_window(r, c, data[r:r + step_rows, c:c + step_cols])
    return out


def file_bytes(path):
    return path.read_bytes()


@pytest.mark.parametrize("shape", [(64, 64), (100, 90), (17, 33), (1, 1), (16, 200)])
@pytest.mark.parametrize("nchan", [1, 6])
def test_any_order_of_windows_gives_the_bytes_of_a_whole_write(tmp_path, shape, nchan):
    tile = 16
    names = ("height",) if nchan == 1 else NAMES6
    data = field(shape, nchan, seed=shape[0] * 7 + nchan)
    prov = {"stage": "toy", "key": "abc", "params": {"b": 1, "a": [2, 3]}}
    whole = tmp_path / "whole.exr"
    write_windows(whole, data, names, [(0, 0)], *shape, tile, prov)
    n_tiles = [-(-s // tile) for s in shape]
    quarter = [-(-n // 4) * tile for n in n_tiles]  # a 4 x 4 split into world tiles of whole file tiles
    cases = {
        "tiles shuffled": (windows(shape, tile, tile), tile, tile),
        "4x4 windows shuffled": (windows(shape, *quarter), *quarter),
        "rows of tiles shuffled": (windows(shape, tile, shape[1]), tile, shape[1]),
        "tiles backwards": (windows(shape, tile, tile)[::-1], tile, tile),
    }
    for i, (name, (order, sr, sc)) in enumerate(cases.items()):
        if "shuffled" in name:
            random.Random(i).shuffle(order)
        path = tmp_path / f"{i}.exr"
        out = write_windows(path, data, names, order, sr, sc, tile, prov)
        assert file_bytes(path) == file_bytes(whole), name
        assert out.content_hash() == Grid(data, 4.0, names, (100.0, -50.0)).content_hash(), name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0.exr", "1.exr", "2.exr", "3.exr", "whole.exr"]


@pytest.mark.parametrize("shape", [(300, 520), (256, 256), (513, 257)])
@pytest.mark.parametrize("nchan", [1, 6])
def test_write_grid_is_a_tiled_file_equal_to_its_windows(tmp_path, shape, nchan):
    names = ("height",) if nchan == 1 else NAMES6
    data = field(shape, nchan, seed=3)
    grid = Grid(data, 8.0, names, (-4096.0, 12.5))
    prov = {"stage": "toy", "units": {"height": "m"}}
    exr.write_grid(tmp_path / "whole.exr", grid, prov)
    t = exr.TILE
    order = windows(shape, t, t)
    random.Random(5).shuffle(order)
    with exr.GridWriter(tmp_path / "tiles.exr", shape, names, 8.0, (-4096.0, 12.5), prov) as out:
        for r, c in order:
            out.write_window(r, c, data[r:r + t, c:c + t])
    assert file_bytes(tmp_path / "tiles.exr") == file_bytes(tmp_path / "whole.exr")

    back = exr.read_grid(tmp_path / "whole.exr")
    assert back.shape == shape and back.cell_size_m == 8.0 and back.origin_m == (-4096.0, 12.5)
    for name in names:
        want = data if nchan == 1 else data[:, :, names.index(name)]
        assert np.array_equal(back.channel(name).view(np.uint32), want.view(np.uint32)), name  # NaN, -0.0 kept

    inp = oiio.ImageInput.open(str(tmp_path / "whole.exr"))
    spec = inp.spec()
    inp.close()
    assert (spec.tile_width, spec.tile_height) == (t, t)
    assert spec.getattribute("compression") == "zip"
    assert spec.getattribute("openexr:lineOrder") == "increasingY"
    attrs = exr.read_attributes(tmp_path / "whole.exr")
    assert json.loads(attrs["worldbake:origin_m"]) == [-4096.0, 12.5]
    assert attrs["worldbake:cell_size_m"] == 8.0
    assert attrs["worldbake:stage"] == "toy" and json.loads(attrs["worldbake:units"]) == {"height": "m"}
    assert exr.grid_info(tmp_path / "whole.exr") == (shape, back.channels, 8.0, (-4096.0, 12.5), t)


def write_scanline_grid(path, grid):
    """A grid as the engine wrote it before tiling (scanline EXR)."""
    data = np.ascontiguousarray(grid.data, np.float32)
    rows, cols = grid.shape
    spec = oiio.ImageSpec(cols, rows, len(grid.channels), oiio.FLOAT)
    spec.channelnames = tuple(grid.channels)
    spec.attribute("compression", "zip")
    spec.attribute("worldbake:cell_size_m", float(grid.cell_size_m))
    spec.attribute("worldbake:origin_m", json.dumps(list(grid.origin_m)))
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(data.reshape(rows, cols, len(grid.channels)))
    assert out.close()


@pytest.mark.parametrize("tiled", [True, False], ids=["tiled", "scanline"])
@pytest.mark.parametrize("nchan", [1, 6])
def test_windows_read_back_the_cells_they_cover(tmp_path, tiled, nchan):
    names = ("height",) if nchan == 1 else NAMES6
    shape = (300, 520)
    grid = Grid(field(shape, nchan, seed=9), 2.0, names, (1000.0, 2000.0))
    path = tmp_path / "g.exr"
    (exr.write_grid if tiled else write_scanline_grid)(path, grid)
    assert exr.grid_info(path).tile == (exr.TILE if tiled else 0)
    whole = exr.read_grid(path)
    assert sorted(whole.channels) == sorted(names) and whole.origin_m == (1000.0, 2000.0)
    for name in names:  # the file's channel order is OpenEXR's, read by name
        assert np.array_equal(whole.channel(name).view(np.uint32), grid.channel(name).view(np.uint32))
    for r0, c0, rows, cols in [(0, 0, 300, 520), (0, 0, 1, 1), (299, 519, 1, 1), (250, 200, 50, 100),
                               (255, 255, 2, 2), (0, 256, 300, 264), (17, 3, 270, 511)]:
        w = exr.read_window(path, r0, c0, rows, cols)
        assert w.shape == (rows, cols) and w.channels == whole.channels and w.cell_size_m == 2.0
        assert w.origin_m == (1000.0 + 2.0 * c0, 2000.0 + 2.0 * r0)
        want = whole.data[r0:r0 + rows, c0:c0 + cols]
        assert np.array_equal(w.data.view(np.uint32), want.view(np.uint32)), (r0, c0, rows, cols)


@pytest.mark.parametrize("window", [(-1, 0, 5, 5), (0, 0, 301, 10), (0, 515, 10, 6), (10, 10, 0, 4),
                                    (300, 0, 1, 1)])
def test_a_window_outside_the_map_is_an_input_error_naming_the_file(tmp_path, window):
    path = tmp_path / "height.exr"
    exr.write_grid(path, Grid(np.zeros((300, 520), np.float32), 1.0))
    with pytest.raises(InputError, match=r"height\.exr: window .* outside the map's 300 x 520 cells"):
        exr.read_window(path, *window)


def test_the_writer_refuses_bad_windows_and_leaves_no_partial_file(tmp_path):
    path = tmp_path / "g.exr"
    data = np.ones((40, 40), np.float32)
    with exr.GridWriter(path, (40, 40), ("height",), 1.0, tile=16) as out:
        with pytest.raises(ValueError, match="whole 16x16 file tiles"):
            out.write_window(8, 0, data[:16, :16])  # not on a tile boundary
        with pytest.raises(ValueError, match="whole 16x16 file tiles"):
            out.write_window(0, 0, data[:10, :16])  # a part of a tile
        with pytest.raises(ValueError, match="does not match channels"):
            out.write_window(0, 0, np.ones((16, 16, 2), np.float32))
        out.write_window(32, 0, data[:8, :40])  # the last row of tiles, short
        with pytest.raises(ValueError, match="overlaps cells already written"):
            out.write_window(32, 32, data[:8, :8])
        out.write_window(0, 0, data[:32])
        out.close()  # closing twice (here and leaving the block) is closing once
        with pytest.raises(ValueError, match="after close"):
            out.write_window(0, 0, data[:16, :16])
    assert exr.read_grid(path).data.shape == (40, 40)

    with pytest.raises(ValueError, match="3 of 9 file tiles never written, the first at row 16, col 0"):
        with exr.GridWriter(path, (40, 40), ("height",), 1.0, tile=16) as out:
            out.write_window(0, 0, data[:16])
            out.write_window(32, 0, data[:8])
    assert not path.exists()
    with pytest.raises(RuntimeError):
        with exr.GridWriter(path, (40, 40), ("height",), 1.0, tile=16) as out:
            out.write_window(16, 0, data[:16])
            raise RuntimeError("a stage failed mid-write")
    assert list(tmp_path.iterdir()) == []


def test_a_tile_by_tile_write_holds_one_row_of_tiles_not_the_map(tmp_path):
    """2048^2 (16 MB) written tile by tile, last tile first, each tile made
    on the fly: the writer's numpy memory peaks at about one row of file
    tiles (2 MB), never the map."""
    n, t = 2048, exr.TILE
    order = windows((n, n), t, t)[::-1]
    tracemalloc.start()
    try:
        with exr.GridWriter(tmp_path / "big.exr", (n, n), ("height",), 1.0) as out:
            for r, c in order:
                out.write_window(r, c, np.full((t, t), r * n + c, np.float32))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * t * n * 4 + 2 * t * t * 4, peak  # one row buffer, a tile and its spool copy
    w = exr.read_window(tmp_path / "big.exr", 1024, 1792, 256, 256)
    assert np.all(w.data == 1024 * n + 1792)
