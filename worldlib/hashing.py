"""The numpy twin of worldlib/cl/worldbake_hash.h: counter-based random
numbers that kernels and references compute bit for bit alike.

mix32 is the header's; hash4 and unit are the vegetation kernels' (and the
host's draws: uniform), stream_key names one random stream of a seed."""
from __future__ import annotations

import zlib

import numpy as np

U32 = np.uint32
INV24 = np.float32(5.9604645e-08)  # 2^-24: a uniform from the top 24 bits of a hash


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


def hash4(k, a, b, c):
    """A hash of a key and three counters (arrays broadcast)."""
    return mix32(mix32(mix32(U32(k) ^ np.asarray(a).astype(U32)) ^ np.asarray(b).astype(U32))
                 ^ np.asarray(c).astype(U32))


def unit(h) -> np.ndarray:
    """A hash's top 24 bits as a float32 uniform in [0, 1)."""
    return (np.asarray(h, dtype=U32) >> U32(8)).astype(np.float32) * INV24


def stream_key(seed: int, *labels: str) -> int:
    """A uint32 key for one random stream: the seed and labels (e.g. a
    purpose and a species name) hashed together. Keyed by name, not by
    index, so adding or changing another stream leaves this one alone."""
    h = int(mix32(U32((seed & 0xFFFFFFFF) ^ 0x9E3779B9)))
    h = int(mix32(U32(h ^ ((seed >> 32) & 0xFFFFFFFF))))
    for label in labels:
        h = int(mix32(U32(h ^ zlib.crc32(label.encode()))))
    return h


def uniform(key: int, a, b, c) -> np.ndarray:
    """unit(hash4(key, a, b, c)) for host-side draws (the same numbers as a kernel)."""
    return unit(hash4(key, a, b, c))
