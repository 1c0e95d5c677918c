"""What the voxelization kernel reads and writes: a table of triangles with
their subdivision counts and sample offsets, the grid, the samples; and the
fixed-order reduction of samples into voxel sums (np.bincount adds in sample
order, so the sums are deterministic and the same for both backends)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worldlib.render import Scene


@dataclass(frozen=True)
class Grid3:
    origin: np.ndarray  # (3,) float64, min corner (x, y, z), m
    voxel: float  # m
    shape: tuple[int, int, int]  # (nx, ny, nz)

    @property
    def count(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]


@dataclass
class SampleTable:
    pos: np.ndarray  # (m, 9) float64 corner positions
    nrm: np.ndarray  # (m, 9) float64 corner normals
    uv: np.ndarray  # (m, 6) float64 corner uv
    tint: np.ndarray  # (m, 3) float64
    tex: np.ndarray  # (m,) int32 texture index or -1
    m: np.ndarray  # (m,) int32 subdivisions per edge
    offset: np.ndarray  # (m + 1,) int64 first sample of each triangle

    def take(self, lo: int, hi: int) -> "SampleTable":
        off = self.offset[lo:hi + 1] - self.offset[lo]
        return SampleTable(self.pos[lo:hi], self.nrm[lo:hi], self.uv[lo:hi], self.tint[lo:hi], self.tex[lo:hi],
                           self.m[lo:hi], off)


@dataclass
class Samples:
    voxel: np.ndarray  # (n,) int32 voxel index (x fastest) or -1 (alpha-tested away)
    weight: np.ndarray  # (n,) float64 area, m^2
    rgb: np.ndarray  # (n, 3) float64 linear albedo
    normal: np.ndarray  # (n, 3) float64 unit normal


def sample_table(scene: Scene, triangles: np.ndarray, spacing_m: float, max_per_edge: int = 64) -> SampleTable:
    """The triangles of `scene` (indices) with m = ceil(longest edge / spacing)
    subdivisions per edge (at most max_per_edge): samples about spacing_m apart."""
    tri = scene.triangles[triangles]
    p = scene.positions.astype(np.float64)[tri]  # (m, 3, 3)
    edges = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).max(1)
    m = np.clip(np.ceil(edges / spacing_m), 1, max_per_edge).astype(np.int32)
    offset = np.concatenate([[0], np.cumsum(m.astype(np.int64) ** 2)])
    return SampleTable(p.reshape(-1, 9), scene.normals.astype(np.float64)[tri].reshape(-1, 9),
                       scene.uv.astype(np.float64)[tri].reshape(-1, 6), scene.tint.astype(np.float64)[triangles],
                       scene.texture[triangles].astype(np.int32), m, offset)


@dataclass
class SurfaceSums:
    """Per voxel (flattened, x fastest): area, area x albedo, area x normal."""

    area: np.ndarray
    rgb: np.ndarray  # (n, 3)
    normal: np.ndarray  # (n, 3)

    @staticmethod
    def zeros(count: int) -> "SurfaceSums":
        return SurfaceSums(np.zeros(count), np.zeros((count, 3)), np.zeros((count, 3)))

    def add(self, s: Samples) -> None:
        keep = s.voxel >= 0
        v, w = s.voxel[keep], s.weight[keep]
        n = len(self.area)
        self.area += np.bincount(v, w, n)
        for c in range(3):
            self.rgb[:, c] += np.bincount(v, w * s.rgb[keep, c], n)
            self.normal[:, c] += np.bincount(v, w * s.normal[keep, c], n)
