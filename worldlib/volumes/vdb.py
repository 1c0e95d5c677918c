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
origin + h/2: the .vdb and the EXR place every voxel at the same point.
Grids: density (float, fog volume, extinction 1/m: what Blender's and
Houdini's volume shaders take as density), albedo (vec3s, linear RGB, NOT
premultiplied: the scattering colour a volume shader takes, albedo / density
of the EXR form, which premultiplies so that mips average; stored as half
floats, as the EXR stores it). The normal and surface channels stay in the
EXR form only: no DCC volume shader reads them, and every grid of a .vdb
is loaded with it. Colours are one vec3 grid, not three floats: Blender's
Principled Volume reads a colour from one attribute name (Color Attribute =
albedo), Houdini treats a vec3 VDB as one vector (Cd-like) field, and
UsdVol's OpenVDBAsset names one field per grid (fieldDataType float3,
vectorDataRoleHint Color). Only the occupied voxels are active (zero is the
background), so a sparse forest sector stays sparse in its .vdb.

OpenVDB writes a random UUID into every file's header; the writer replaces
it by one derived from the rest of the file (`_content_uuid`), so a bake
writes the same bytes every time (the files' hashes are the store's).

Writing is batched: `write_vdbs` hands every level of a call to one run of
the system Python (a forest's hundreds of sector levels cost one process
start, not one each).
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import subprocess
import tempfile
import uuid
from pathlib import Path
from typing import Union

import numpy as np

from .dense import VolumeLevel
from .sparse import SparseLevel, from_dense

UNITS = {"density": "1/m", "albedo": "1"}  # the grids of a .vdb, in file order, and their units (grid metadata)
GRIDS = tuple(UNITS)

# The writer, run by the system Python. A level's box (clipped to its occupied voxels) is copied dense:
# measured as fast as copying only its occupied 8^3 to 32^3 blocks. copyFromArray's tolerance 0 leaves every voxel
# equal to the background (0) inactive, so only the occupied voxels are stored. (No comments inside the script:
# its text is code for the stage's key.)
_WRITE = r"""
import json, sys, numpy as np, pyopenvdb as vdb
units = json.loads(sys.argv[2])
for npz, out in json.load(open(sys.argv[1])):
    d = np.load(npz)
    h, o = float(d["voxel"]), d["origin"]
    nx, ny, nz = (int(v) for v in d["shape_xyz"])
    i, j, k = d["ijk"].T
    m = [[h, 0, 0, 0], [0, h, 0, 0], [0, 0, h, 0], [o[0] + h / 2, o[1] + h / 2, o[2] + h / 2, 1]]
    grids = []
    for name in units:
        v = d[name]
        a = np.zeros((nx, ny, nz) + v.shape[1:], np.float32)
        a[i, j, k] = v
        g = vdb.FloatGrid() if v.ndim == 1 else vdb.Vec3SGrid()
        g.copyFromArray(a, (0, 0, 0))
        g.name = name
        g.transform = vdb.createLinearTransform(m)
        g["units"] = units[name]
        if name == "density":
            g.gridClass = vdb.GridClass.FOG_VOLUME
        else:
            g.saveFloatAsHalf = True
        grids.append(g)
    vdb.write(out, grids=grids)
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
    out[g.name + "_world0"] = np.array(grid.transform.indexToWorld((0, 0, 0)))
    out[g.name + "_active"] = np.array(grid.evalActiveVoxelBoundingBox())
    out[g.name + "_class"] = np.array(str(grid.gridClass))
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


def require_writer(without: str) -> None:
    """Refuses (ParamError on `vdb`) a bake that asks for .vdb files where no
    writer runs; `without` says what the world would lack."""
    from pipeline.contract import ParamError

    why = available()
    if why is not None:
        raise ParamError("vdb", f"no OpenVDB writer: {why}; install Debian's python3-openvdb "
                         f"(apt-get install python3-openvdb) or set WORLDBAKE_VDB_PYTHON, or set vdb = false ({without})")


def _run(script: str, *args: str) -> None:
    proc = subprocess.run([_python(), "-c", script, *args], capture_output=True, text=True, timeout=3600)
    if proc.returncode:
        raise OSError(f"OpenVDB through {_python()} failed: {proc.stderr.strip()[-2000:]}")


Level = Union[VolumeLevel, SparseLevel]


def occupied_grids(level: Level) -> dict[str, np.ndarray]:
    """The level's occupied voxels as the .vdb holds them: ijk (n, 3) int32
    (x, y, z), and per grid its values there (albedo divided by density)."""
    sparse = from_dense(level) if isinstance(level, VolumeLevel) else level
    nx, ny, _ = sparse.shape_xyz
    z, rest = np.divmod(sparse.index, nx * ny)
    y, x = np.divmod(rest, nx)
    d = sparse.density.astype(np.float32)
    plain = np.divide(sparse.albedo, d[:, None], out=np.zeros_like(sparse.albedo, np.float32), where=d[:, None] > 0)
    return {"ijk": np.stack([x, y, z], 1).astype(np.int32), "density": d, "albedo": plain.astype(np.float32)}


def write_vdbs(files: list[tuple[Path | str, Level]]) -> None:
    """Every (path, level) as a .vdb, in one run of the system Python."""
    if not files:
        return
    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for n, (path, level) in enumerate(files):
            npz = Path(tmp) / f"{n}.npz"
            np.savez(npz, voxel=np.float64(level.voxel_m), origin=np.asarray(level.origin, np.float64),
                     shape_xyz=np.asarray(level.shape_xyz, np.int64), **occupied_grids(level))
            jobs.append((str(npz), str(path)))
        (Path(tmp) / "jobs.json").write_text(json.dumps(jobs))
        _run(_WRITE, str(Path(tmp) / "jobs.json"), json.dumps(UNITS))
    for path, _ in files:
        _content_uuid(Path(path))


VDB_MAGIC = (0x56444220).to_bytes(8, "little")  # the first 8 bytes of an OpenVDB file
UUID_AT = slice(21, 57)  # magic, file version, library major and minor, the grid offsets flag: then 36 characters


def _content_uuid(path: Path) -> None:
    """The file's header UUID replaced by one made from the rest of its
    bytes (same grids, same file)."""
    data = bytearray(path.read_bytes())
    if data[:8] != VDB_MAGIC or not re.fullmatch(rb"[0-9a-f]{8}(-[0-9a-f]{4}){3}-[0-9a-f]{12}", bytes(data[UUID_AT])):
        raise OSError(f"{path}: not an OpenVDB file with a UUID where the format puts it")
    digest = hashlib.sha256(bytes(data[:UUID_AT.start] + data[UUID_AT.stop:])).digest()[:16]
    data[UUID_AT] = str(uuid.UUID(bytes=digest, version=4)).encode()
    path.write_bytes(bytes(data))


def write_vdb(path: Path | str, level: Level) -> None:
    write_vdbs([(path, level)])


def read_vdb(path: Path | str, shape_xyz: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """The grids of a .vdb as dense arrays indexed [z, y, x] over shape_xyz
    from voxel (0, 0, 0); per grid its voxel size (<name>_voxel), the world
    position of voxel (0, 0, 0)'s centre (<name>_world0), its active voxels'
    index box ((min ijk, max ijk), <name>_active) and class (<name>_class)."""
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "grids.npz"
        _run(_READ, str(path), str(npz), *map(str, shape_xyz))
        with np.load(npz) as d:
            return {k: d[k] for k in d.files}
