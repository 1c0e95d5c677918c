"""OpenVDB files of volume levels, through Debian's `python3-openvdb`.

No maintained OpenVDB writer installs from PyPI (`pip index versions
openvdb` finds none; the old `pyopenvdb` wheels are gone), and Debian's
`pyopenvdb` module is built against the system's numpy 1.x, which the
project's environment (numpy 2) cannot load. So the grids travel as a .npz
file to the system Python that has the module (WORLDBAKE_VDB_PYTHON, else
/usr/bin/python3), which writes or reads the .vdb. `available()` says
whether that works here; a stage that writes VDB checks it before any work.

A level's voxel (i, j, k) centred at origin + (i + 1/2, j + 1/2, k + 1/2) h
is the VDB voxel (i, j, k) under the linear transform scale h, translation
origin + h/2; grids: density (float, fog volume), albedo (vec3s,
premultiplied by density), normal (vec3s), surface (float).
"""
from __future__ import annotations

import functools
import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from .dense import VolumeLevel

_WRITE = r"""
import sys, numpy as np, pyopenvdb as vdb
d = np.load(sys.argv[1])
h, o = float(d["voxel"]), d["origin"]
m = [[h, 0, 0, 0], [0, h, 0, 0], [0, 0, h, 0], [o[0] + h / 2, o[1] + h / 2, o[2] + h / 2, 1]]
grids = []
for name in ("density", "albedo", "normal", "surface"):
    a = d[name]
    g = vdb.FloatGrid() if a.ndim == 3 else vdb.Vec3SGrid()
    g.copyFromArray(np.ascontiguousarray(a.transpose(2, 1, 0, *range(3, a.ndim))), (0, 0, 0))
    g.name = name
    g.transform = vdb.createLinearTransform(m)
    if name == "density":
        g.gridClass = vdb.GridClass.FOG_VOLUME
    grids.append(g)
vdb.write(sys.argv[2], grids=grids)
"""

_READ = r"""
import sys, numpy as np, pyopenvdb as vdb
nx, ny, nz = map(int, sys.argv[3:6])
out = {}
for g in vdb.readAllGridMetadata(sys.argv[1]):
    grid = vdb.read(sys.argv[1], g.name)
    a = np.zeros((nx, ny, nz) if isinstance(grid, vdb.FloatGrid) else (nx, ny, nz, 3), np.float32)
    grid.copyToArray(a, (0, 0, 0))
    out[g.name] = a.transpose(2, 1, 0, *range(3, a.ndim))
    out[g.name + "_voxel"] = np.array(grid.transform.voxelSize())
np.savez(sys.argv[2], **out)
"""


def _python() -> str:
    return os.environ.get("WORLDBAKE_VDB_PYTHON", "/usr/bin/python3")


@functools.lru_cache(maxsize=1)
def available() -> str | None:
    """None when the OpenVDB writer works, else why not."""
    try:
        proc = subprocess.run([_python(), "-c", "import pyopenvdb"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"{_python()}: {e}"
    if proc.returncode:
        return f"{_python()} cannot import pyopenvdb ({proc.stderr.strip().splitlines()[-1] if proc.stderr else 'no output'})"
    return None


def _run(script: str, *args: str) -> None:
    proc = subprocess.run([_python(), "-c", script, *args], capture_output=True, text=True, timeout=600)
    if proc.returncode:
        raise OSError(f"OpenVDB through {_python()} failed: {proc.stderr.strip()[-2000:]}")


def write_vdb(path: Path | str, level: VolumeLevel) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "level.npz"
        np.savez(npz, density=level.density, albedo=level.albedo, normal=level.normal, surface=level.surface,
                 voxel=np.float64(level.voxel_m), origin=np.asarray(level.origin, np.float64))
        _run(_WRITE, str(npz), str(path))


def read_vdb(path: Path | str, shape_xyz: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """The grids of a .vdb as dense arrays indexed [z, y, x] over shape_xyz
    from voxel (0, 0, 0), with each grid's voxel size under <name>_voxel."""
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "grids.npz"
        _run(_READ, str(path), str(npz), *map(str, shape_xyz))
        with np.load(npz) as d:
            return {k: d[k] for k in d.files}
