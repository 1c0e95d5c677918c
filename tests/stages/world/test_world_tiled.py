"""The world stage reads its grids by window (run_tiled, a tiled bake's
GridFile handles) and writes the bytes of the whole run: the ground
textures, normal map, splat textures, near bake, mesh and layers."""
from __future__ import annotations

import numpy as np

from pipeline import exr
from pipeline.contract import RunContext
from pipeline.grid import Grid
from pipeline.opencl import get_cl
from pipeline import tiles
from pipeline.tiles import GridArray, GridFile
from stages.world import STAGE, ground_device
from stages.world import stage as world_stage
from worldlib.ground import SPLAT_CHANNELS

PARAMS = dict(mesh_max_vertices=41, terrain_tile_quads=16, texture_size=48, ground_texel_m=4.0,
              ground_tile_texels=128, ground_detail_texels=32, ground_near_m=200.0, ground_near_texels=64,
              ground_near_east_m=130.0)


def _grids(rows=150, cols=133, cell=5.0):
    r, c = np.mgrid[0:rows, 0:cols]
    h = (400 + 60 * np.sin(c / 9.0) * np.cos(r / 13.0) + 0.8 * r).astype(np.float32)
    w = np.random.default_rng(7).random((rows, cols, len(SPLAT_CHANNELS))).astype(np.float32) ** 3
    w /= w.sum(axis=-1, keepdims=True)
    # the splat's channels stored in another order than SPLAT_CHANNELS: the stage reads them by name
    order = list(reversed(SPLAT_CHANNELS))
    splat = Grid(np.ascontiguousarray(w[..., [SPLAT_CHANNELS.index(k) for k in order]]), cell, tuple(order),
                 (-300.0, 120.0))
    return Grid(h, cell, ("height",), (-300.0, 120.0)), splat


def _bake(out, run, inputs):
    out.mkdir()
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="k", out_dir=out, seed=3, provenance={"stage": "world", "key": "k"},
                     project_root=out)
    run(ctx, inputs, STAGE.params(**PARAMS))
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def test_the_world_from_windows_is_the_whole_run_byte_for_byte(tmp_path, monkeypatch):
    terrain, splat = _grids()
    exr.write_grid(tmp_path / "height.exr", terrain)
    exr.write_grid(tmp_path / "splat.exr", splat)
    # the whole run as a bake has it: the grids read whole from the files (channels in the file's order)
    whole = _bake(tmp_path / "whole", STAGE.run, {"terrain": exr.read_grid(tmp_path / "height.exr"),
                                                   "splat": exr.read_grid(tmp_path / "splat.exr")})
    reads = []
    real_read = GridFile.read

    def counted(self, row0, col0, rows, cols, channel=None):
        reads.append((self.path.name, rows, cols))
        return real_read(self, row0, col0, rows, cols, channel)

    # bands of 64 rows and splat windows of a few rows: every band edge and window seam is crossed
    monkeypatch.setattr(world_stage, "BAND_ROWS", 64)
    monkeypatch.setattr(ground_device, "WINDOW_BYTES", 6 * 4 * 140 * 12)
    monkeypatch.setattr(GridFile, "read", counted)
    monkeypatch.setattr(tiles, "DIGEST_BAND_ROWS", 64)
    files = {"terrain": GridFile(tmp_path / "height.exr"), "splat": GridFile(tmp_path / "splat.exr")}
    windowed = _bake(tmp_path / "windowed", STAGE.run_tiled, files)
    assert sorted(windowed) == sorted(whole)
    assert [k for k in whole if whole[k] != windowed[k]] == []
    assert {"normal.exr", "splat_a.exr", "ground.1001.exr", "near_albedo.png", "terrain.usdc"} <= set(whole)
    # no read was of a whole grid (the content digests read bands too)
    assert reads and max(rows for _, rows, _ in reads) <= 66
    assert not any(rows * cols == terrain.data.size for _, rows, cols in reads)


def test_a_grid_files_digest_is_its_grids(tmp_path):
    terrain, splat = _grids(70, 51)
    for name, grid in (("h.exr", terrain), ("s.exr", splat)):
        exr.write_grid(tmp_path / name, grid)
        # the grid as a whole bake reads it (a file's channels are in the file's order)
        assert GridFile(tmp_path / name).content_hash(band_rows=16) == exr.read_grid(tmp_path / name).content_hash()
        assert GridArray(grid).content_hash() == grid.content_hash()

