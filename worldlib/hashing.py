"""The numpy twin of worldlib/cl/worldbake_hash.h: counter-based random
numbers that kernels and references compute bit for bit alike."""
from __future__ import annotations

import numpy as np

U32 = np.uint32


def mix32(h):
    """lowbias32 (Chris Wellons) on uint32 arrays or scalars, wrapping."""
    h = np.asarray(h, dtype=U32)
    with np.errstate(over="ignore"):
        h = h ^ (h >> U32(16))
        h = h * U32(0x7FEB352D)
        h = h ^ (h >> U32(15))
        h = h * U32(0x846CA68B)
        h = h ^ (h >> U32(16))
    return h
