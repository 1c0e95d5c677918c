"""A raster on the terrain grid, with its geometry in metres."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """Values on a regular grid of square cells.

    data has shape (rows, cols) for one channel or (rows, cols, channels).
    Row 0 is the north edge; x grows east with the column, and the sample of
    cell (r, c) sits at its centre: x = origin_x + (c + 0.5) * cell_size_m,
    z = origin_z + (r + 0.5) * cell_size_m (z grows south, so Y is up in a
    right-handed frame).
    """

    data: np.ndarray
    cell_size_m: float
    channels: tuple[str, ...] = ("height",)
    origin_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        nchan = 1 if self.data.ndim == 2 else self.data.shape[2]
        if self.data.ndim not in (2, 3) or nchan != len(self.channels):
            raise ValueError(f"grid of shape {self.data.shape} does not match channels {self.channels}")
        if not self.cell_size_m > 0:
            raise ValueError(f"cell size must be positive, got {self.cell_size_m}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape[0], self.data.shape[1]

    def content_hash(self) -> str:
        """sha256 of the values the grid holds and its geometry (not of a
        file's header, which names the producer's key: equal pixels would
        never compare equal)."""
        return content_digest(self.channels, self.data.shape, self.data.dtype, self.cell_size_m, self.origin_m,
                              [self.data])

    @property
    def size_m(self) -> tuple[float, float]:
        """(width east-west, depth north-south) in metres."""
        return self.data.shape[1] * self.cell_size_m, self.data.shape[0] * self.cell_size_m

    def channel(self, name: str) -> np.ndarray:
        if self.data.ndim == 2:
            if name != self.channels[0]:
                raise KeyError(name)
            return self.data
        return self.data[:, :, self.channels.index(name)]


def content_digest(channels, shape, dtype, cell_size_m: float, origin_m, row_blocks) -> str:
    """Grid.content_hash of a grid given as blocks of whole rows, north to
    south (a grid file read by window gives the same digest as read whole)."""
    import hashlib
    import json

    h = hashlib.sha256()
    h.update(json.dumps([list(channels), list(shape), np.dtype(dtype).str, cell_size_m, list(origin_m)]).encode())
    for block in row_blocks:
        h.update(np.ascontiguousarray(block).tobytes())
    return h.hexdigest()
