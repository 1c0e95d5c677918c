"""The ground albedo kernel (ground.cl) on the OpenCL device, with
reference.tile_albedo's arguments: that numpy function is its reference."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .ground import GROUND_COLOURS, axis_taps, tile_positions

KERNELS = Path(__file__).with_name("ground.cl")
MAX_TYPES = 8  # ground.cl's


WINDOW_BYTES = 128 << 20  # most splat bytes on the device at once: a band of texel rows reads only its cells


class GroundAlbedo:
    """The detail tables uploaded once, then any number of tiles baked (the
    default world bakes 16 tiles of 2048^2), each in bands of texel rows
    whose splat cells are read by window: the world's splat is never whole."""

    def __init__(self, env, read_splat, shape: tuple[int, int, int], tables: np.ndarray,
                 local: tuple[int, int] | None = (16, 4), window_bytes: int | None = None):
        """`env`: the OpenCL device (pipeline.opencl.CL; the stage's ctx.cl);
        read_splat(row0, col0, rows, cols): that window of the splat weights
        (rows, cols, types) float32; shape: the whole splat's (rows, cols, types);
        window_bytes: WINDOW_BYTES unless given."""
        import pyopencl as cl

        from pipeline.clhost import Buffers, kernel
        from pipeline.opencl import load_program

        types = shape[2]
        if types > MAX_TYPES or tables.shape[0] != types or len(GROUND_COLOURS) != types:
            raise ValueError(f"ground: {types} splat channels, {tables.shape[0]} detail tables, "
                             f"{len(GROUND_COLOURS)} colours (at most {MAX_TYPES})")
        self.kernel = kernel(load_program(env, KERNELS), "tile_albedo")
        self.cl, self.buffers, self.local = cl, Buffers(env), local
        self.read_splat, self.shape = read_splat, tuple(shape)
        self.window_bytes = int(WINDOW_BYTES if window_bytes is None else window_bytes)
        self.period = int(tables.shape[1])
        self.tables = self.buffers.arr(np.asarray(tables, np.float32))
        self.colours = self.buffers.arr(GROUND_COLOURS)

    def tile(self, cell_m: float, origin_m: tuple[float, float], tiles: int, texels: int, u: int, v: int,
             texel_m: float) -> np.ndarray:
        """reference.tile_albedo(splat, cell_m, origin_m, tiles, texels, u, v, tables, texel_m)."""
        rows, cols, types = self.shape
        x, z = tile_positions(cell_m, (rows, cols), tiles, texels, u, v)
        col_taps, col_frac = axis_taps(x, origin_m[0], cell_m, cols, texel_m, self.period)
        row_taps, row_frac = axis_taps(z, origin_m[1], cell_m, rows, texel_m, self.period)
        c_lo, c_hi = int(col_taps[:, 0].min()), int(col_taps[:, 1].max()) + 1
        col_taps[:, :2] -= c_lo
        # texel rows per band: as many as keep the band's splat window within window_bytes (rows grow south)
        row_bytes = (c_hi - c_lo) * types * 4
        cells_per_texel = max((int(row_taps[-1, 1]) - int(row_taps[0, 0]) + 1) / texels, 1e-9)
        band = int(np.clip((self.window_bytes // row_bytes - 2) / cells_per_texel, 1, texels))
        b = self.buffers
        out = np.empty((texels, texels, 3), np.float32)
        result = b.empty(band * texels * 3 * 4)
        for j0 in range(0, texels, band):
            j1 = min(j0 + band, texels)
            r_lo, r_hi = int(row_taps[j0:j1, 0].min()), int(row_taps[j0:j1, 1].max()) + 1
            taps = row_taps[j0:j1].copy()
            taps[:, :2] -= r_lo
            splat = np.ascontiguousarray(self.read_splat(r_lo, c_lo, r_hi - r_lo, c_hi - c_lo), np.float32)
            b.run(self.kernel, (texels, j1 - j0), self.local, b.arr(splat), np.int32(c_hi - c_lo),
                  np.int32(types), self.tables, np.int32(self.period), self.colours, np.int32(texels),
                  np.int32(j1 - j0), b.arr(col_taps), b.arr(col_frac), b.arr(taps), b.arr(row_frac[j0:j1]), result)
            out[j0:j1] = b.get(result, (band, texels, 3), np.float32)[:j1 - j0]
        return out
