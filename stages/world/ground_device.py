"""The ground albedo kernel (ground.cl) on the OpenCL device, with
reference.tile_albedo's arguments: that numpy function is its reference."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .ground import GROUND_COLOURS, axis_taps, tile_positions

KERNELS = Path(__file__).with_name("ground.cl")
MAX_TYPES = 8  # ground.cl's


class GroundAlbedo:
    """The splat weights and detail tables uploaded once, then any number of
    tiles baked from them (the default world bakes 16 tiles of 2048^2)."""

    def __init__(self, env, splat: np.ndarray, tables: np.ndarray, local: tuple[int, int] | None = (16, 4)):
        """`env`: the OpenCL device (pipeline.opencl.CL; the stage's ctx.cl)."""
        import pyopencl as cl

        from pipeline.clhost import Buffers, kernel
        from pipeline.opencl import load_program

        rows, cols, types = splat.shape
        if types > MAX_TYPES or tables.shape[0] != types or len(GROUND_COLOURS) != types:
            raise ValueError(f"ground: {types} splat channels, {tables.shape[0]} detail tables, "
                             f"{len(GROUND_COLOURS)} colours (at most {MAX_TYPES})")
        self.kernel = kernel(load_program(env, KERNELS), "tile_albedo")
        self.cl, self.buffers, self.local = cl, Buffers(env), local
        self.shape = (rows, cols, types)
        self.period = int(tables.shape[1])
        self.splat = self.buffers.arr(np.asarray(splat, np.float32))
        self.tables = self.buffers.arr(np.asarray(tables, np.float32))
        self.colours = self.buffers.arr(GROUND_COLOURS)
        self._out, self._out_texels = None, 0

    def tile(self, cell_m: float, origin_m: tuple[float, float], tiles: int, texels: int, u: int, v: int,
             texel_m: float) -> np.ndarray:
        """reference.tile_albedo(splat, cell_m, origin_m, tiles, texels, u, v, tables, texel_m)."""
        rows, cols, types = self.shape
        x, z = tile_positions(cell_m, (rows, cols), tiles, texels, u, v)
        col_taps, col_frac = axis_taps(x, origin_m[0], cell_m, cols, texel_m, self.period)
        row_taps, row_frac = axis_taps(z, origin_m[1], cell_m, rows, texel_m, self.period)
        if self._out_texels != texels:
            self._out, self._out_texels = self.buffers.empty(texels * texels * 3 * 4), texels
        b = self.buffers
        b.run(self.kernel, (texels, texels), self.local, self.splat, np.int32(cols), np.int32(types), self.tables,
              np.int32(self.period), self.colours, np.int32(texels), b.arr(col_taps), b.arr(col_frac),
              b.arr(row_taps), b.arr(row_frac), self._out)
        return b.get(self._out, (texels, texels, 3), np.float32)
