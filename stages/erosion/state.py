"""Diagnostics of a simulation state, the same for the device and the reference."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Diag:
    """Sums over the grid in float64, summed per row and then over rows in a
    fixed order (values in metres times cells; multiply by dx^2 for m^3)."""

    water: float
    dT: float
    sediment: float
    evaporated: float  # since the previous diag (the accumulator is reset)
    abs_dT: float
    wave: float  # max |u| + sqrt(g h), m/s
    wmin: float
    wmax: float
    smin: float
    nonfinite: int
    out_water: float  # cumulative water out through open boundaries
    out_sediment: float  # cumulative sediment out through open boundaries

    @classmethod
    def from_rows(cls, sums: np.ndarray, mx: np.ndarray, bnd: np.ndarray) -> "Diag":
        """sums (rows, 5) float64, mx (rows, 5) float32, bnd (2, faces) float64 of
        water and sediment let out through each boundary face."""
        tot = [float(np.sum(sums[:, k])) for k in range(5)]  # numpy's pairwise sum: fixed order
        return cls(
            water=tot[0], dT=tot[1], sediment=tot[2], evaporated=tot[3], abs_dT=tot[4],
            wave=float(np.max(mx[:, 0])) if len(mx) else 0.0,
            wmin=float(np.min(mx[:, 1])), smin=float(np.min(mx[:, 2])),
            nonfinite=int(np.sum(mx[:, 3])), wmax=float(np.max(mx[:, 4])) if len(mx) else 0.0,
            out_water=float(np.sum(bnd[0])), out_sediment=float(np.sum(bnd[1])),
        )
