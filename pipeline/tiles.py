"""Tiled runs: a stage's work on a world split into square tiles, each tile
a task (on a Dask worker when the bake runs on Dask) and a unit in the store.

A world's tiling is set by the config (`[tiling] tile_cells`), not by a
stage: it is how the work is done, not what it makes, so it is in no key and
a tiled bake writes the same files as an untiled one (a stage that runs
tiled promises that; tests/pipeline/test_tiled_bake.py checks it).

A stage that can run tiled declares `run_tiled` beside `run`. It gets its
grid inputs as handles (GridFile: an input artifact's EXR, read by window)
and a TileRunner (ctx.tiles) whose `map` runs one function on every tile:

    height, summaries = ctx.tiles.map(height_tile, "height", shape, {}, params,
                                      grids={"height": ("height",)})

The function (a module-level function, so a Dask worker can import it) gets
a TileContext (the tile, the seed, the OpenCL device), its inputs as
handles it reads windows from (with whatever halo it needs), the params and
a `shared` value (what an earlier global pass computed), and returns a
TileOutput: tile-sized arrays and a small summary. The arrays stay in the
tile's unit folder (build/units/<stage>/<unit key>/, .npy); map returns
them as TileArrays handles, which later passes read windows of and the
engine writes into the artifact's EXR tile by tile (pipeline.exr.GridWriter).
The summaries (perimeter data, partial sums) come back to the stage's
process, which holds only those: no process holds the whole world.

A tile's unit key is the run's key, the pass name and the tile: a bake
that stopped part way (a killed worker, a full disk) resumes from the tiles
it finished.
"""
from __future__ import annotations

import dataclasses
import pickle
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import exr
from .errors import StageError
from .grid import Grid, content_digest

DIGEST_BAND_ROWS = 256  # rows a grid file's content digest reads at once (GridFile.content_hash)
SUMMARY_ARRAYS = "summary.npz"  # a tile's summary arrays in its unit (the rest is the unit's JSON result)


@dataclass(frozen=True)
class Tile:
    """One tile of a world grid: cells [row0, row0 + rows) x [col0, col0 + cols)."""

    row: int  # the tile's place in the grid of tiles
    col: int
    row0: int
    col0: int
    rows: int
    cols: int
    world_shape: tuple[int, int]

    @property
    def name(self) -> str:
        return f"y{self.row}x{self.col}"

    def window(self, halo: int = 0) -> tuple[int, int, int, int]:
        """(row0, col0, rows, cols) of the tile grown by `halo` cells on each
        side, clipped to the world."""
        r0, c0 = max(0, self.row0 - halo), max(0, self.col0 - halo)
        r1 = min(self.world_shape[0], self.row0 + self.rows + halo)
        c1 = min(self.world_shape[1], self.col0 + self.cols + halo)
        return r0, c0, r1 - r0, c1 - c0

    def inner(self, halo: int = 0) -> tuple[slice, slice]:
        """Where the tile's own cells sit in an array of window(halo)."""
        r0, c0, _, _ = self.window(halo)
        return slice(self.row0 - r0, self.row0 - r0 + self.rows), slice(self.col0 - c0, self.col0 - c0 + self.cols)


def tiles_of(shape: tuple[int, int], tile_cells: int) -> list[Tile]:
    """The tiles of a rows x cols world, row by row (the last row and column
    of tiles take what is left); tile_cells 0: one tile."""
    rows, cols = int(shape[0]), int(shape[1])
    t = int(tile_cells) or max(rows, cols)
    return [Tile(i, j, r0, c0, min(t, rows - r0), min(t, cols - c0), (rows, cols))
            for i, r0 in enumerate(range(0, rows, t)) for j, c0 in enumerate(range(0, cols, t))]


def _padded(source, tile: Tile, halo: int, fill: float, channel: str | None) -> np.ndarray:
    """A tile and `halo` cells around it, `fill` beyond the world's border."""
    r0, c0, rows, cols = tile.window(halo)
    part = source.read(r0, c0, rows, cols, channel=channel)
    out = np.full((tile.rows + 2 * halo, tile.cols + 2 * halo) + part.shape[2:], fill, part.dtype)
    top, left = r0 - (tile.row0 - halo), c0 - (tile.col0 - halo)
    out[top:top + rows, left:left + cols] = part
    return out


class GridFile:
    """An input grid artifact read by window (pipeline.exr.read_window), not whole."""

    def __init__(self, path: Path | str):
        self.path = Path(path)
        info = exr.grid_info(self.path)
        self.shape, self.channels = info.shape, info.channels
        self.cell_size_m, self.origin_m = info.cell_size_m, info.origin_m

    def read(self, row0: int, col0: int, rows: int, cols: int, channel: str | None = None) -> np.ndarray:
        data = exr.read_window(self.path, row0, col0, rows, cols)
        return data.channel(channel) if channel is not None else data.data

    def read_tile(self, tile: Tile, halo: int = 0, channel: str | None = None) -> np.ndarray:
        return self.read(*tile.window(halo), channel=channel)

    def read_padded(self, tile: Tile, halo: int, fill: float = np.nan, channel: str | None = None) -> np.ndarray:
        """The tile with `halo` cells on every side, `fill` beyond the world."""
        return _padded(self, tile, halo, fill, channel)

    def content_hash(self, band_rows: int | None = None) -> str:
        """The file's grid's Grid.content_hash, read band by band (DIGEST_BAND_ROWS)."""
        band_rows = band_rows or DIGEST_BAND_ROWS
        rows, cols = self.shape
        shape = (rows, cols) if len(self.channels) == 1 else (rows, cols, len(self.channels))
        bands = (self.read(r0, 0, min(band_rows, rows - r0), cols) for r0 in range(0, rows, band_rows))
        return content_digest(self.channels, shape, np.float32, self.cell_size_m, self.origin_m, bands)


class GridArray(GridFile):
    """A grid in memory read by window like a GridFile: a whole run's input
    handed to code written for windows, so a stage's whole and tiled runs
    share one path (and give the same bytes)."""

    def __init__(self, grid: Grid):
        self.grid = grid
        self.shape, self.channels = grid.shape, tuple(grid.channels)
        self.cell_size_m, self.origin_m = grid.cell_size_m, tuple(grid.origin_m)

    def read(self, row0: int, col0: int, rows: int, cols: int, channel: str | None = None) -> np.ndarray:
        if not (0 <= row0 and 0 <= col0 and rows >= 1 and cols >= 1 and row0 + rows <= self.shape[0]
                and col0 + cols <= self.shape[1]):
            raise ValueError(f"window rows {row0}..{row0 + rows - 1}, cols {col0}..{col0 + cols - 1} is outside "
                             f"the grid's {self.shape[0]} x {self.shape[1]} cells")
        data = self.grid.channel(channel) if channel is not None else self.grid.data
        return np.array(data[row0:row0 + rows, col0:col0 + cols], np.float32)

    def content_hash(self, band_rows: int | None = None) -> str:
        return self.grid.content_hash()


class TileArrays:
    """A grid held as one .npy per tile (the output of a TileRunner.map pass),
    read by window across tiles without loading the others."""

    def __init__(self, name: str, shape: tuple[int, int], channels: tuple[str, ...], cell_size_m: float,
                 origin_m: tuple[float, float], tile_cells: int, files: dict[tuple[int, int], str]):
        self.name, self.shape, self.channels = name, tuple(shape), tuple(channels)
        self.cell_size_m, self.origin_m = cell_size_m, tuple(origin_m)
        self.tile_cells, self.files = int(tile_cells) or max(shape), dict(files)

    def tiles(self) -> list[Tile]:
        return tiles_of(self.shape, self.tile_cells)

    def tile_array(self, tile: Tile) -> np.ndarray:
        return np.load(self.files[(tile.row, tile.col)], mmap_mode="r")

    def read(self, row0: int, col0: int, rows: int, cols: int, channel: str | None = None) -> np.ndarray:
        t = self.tile_cells
        out = None
        for i in range(row0 // t, (row0 + rows - 1) // t + 1):
            for j in range(col0 // t, (col0 + cols - 1) // t + 1):
                part = np.load(self.files[(i, j)], mmap_mode="r")
                r0, c0 = max(row0, i * t), max(col0, j * t)
                r1, c1 = min(row0 + rows, i * t + part.shape[0]), min(col0 + cols, j * t + part.shape[1])
                if out is None:
                    out = np.empty((rows, cols) + part.shape[2:], part.dtype)
                out[r0 - row0:r1 - row0, c0 - col0:c1 - col0] = part[r0 - i * t:r1 - i * t, c0 - j * t:c1 - j * t]
        if channel is not None and out.ndim == 3:
            return out[:, :, self.channels.index(channel)]
        return out

    def read_tile(self, tile: Tile, halo: int = 0, channel: str | None = None) -> np.ndarray:
        return self.read(*tile.window(halo), channel=channel)

    def read_padded(self, tile: Tile, halo: int, fill: float = np.nan, channel: str | None = None) -> np.ndarray:
        """The tile with `halo` cells on every side, `fill` beyond the world."""
        return _padded(self, tile, halo, fill, channel)


@dataclass
class TileContext:
    """What a per-tile function may use besides its inputs and params."""

    tile: Tile
    seed: int
    stage: str
    project_root: Path
    cl: Any = None  # the OpenCL device of the process running the tile (each Dask worker its own)


@dataclass
class TileOutput:
    """A tile's result: arrays of the tile's own cells (no halo) and a small
    summary for the stage's process (JSON values, and numpy arrays)."""

    grids: dict[str, np.ndarray] = field(default_factory=dict)
    summary: dict[str, Any] = field(default_factory=dict)
    # arrays of any shape that stay in files: the summary holds their paths, for a later pass's tasks to read
    # what they need of them (state too big to gather in the stage's process)
    files: dict[str, np.ndarray] = field(default_factory=dict)


def _in_dask_worker() -> bool:
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


@dataclass(frozen=True)
class _TileJob:
    """Everything one tile task needs, picklable: no open files, no device."""

    fn: Callable
    pass_name: str
    tile: Tile
    inputs: dict[str, Any]
    params: Any
    shared: Any
    seed: int
    stage: str
    uses_opencl: bool
    project_root: str
    unit_root: str | None
    unit_tmp: str | None
    work: str
    code_material: dict
    run_key: str
    keep: bool = True


SHARED_FOLDER = "_shared"  # in a pass's work folder: the values its tasks read (TileRunner._dask)


@dataclass(frozen=True)
class _SharedFile:
    """A tile task's `shared` value, pickled to a file of the run's work folder
    (by cloudpickle, as Dask would have pickled it into the task)."""

    path: str

    @classmethod
    def write(cls, path: Path, value: Any) -> "_SharedFile":
        import cloudpickle

        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
        tmp.replace(path)
        return cls(str(path))

    def read(self) -> Any:
        return pickle.loads(Path(self.path).read_bytes())


def _split_summary(summary: dict[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays = {k: v for k, v in summary.items() if isinstance(v, np.ndarray)}
    return arrays, {k: v for k, v in summary.items() if k not in arrays}


def _tile_unit_id(run_key: str, pass_name: str, t: Tile) -> tuple[str, dict]:
    """The name and material of one tile's unit of one pass: the run's key, the pass, the tile."""
    return f"{pass_name}-{t.name}", {"run": run_key, "pass": pass_name, "tile": [t.row0, t.col0, t.rows, t.cols]}


def _tile_unit(units, job: _TileJob):
    return units.unit(*_tile_unit_id(job.run_key, job.pass_name, job.tile))


def _run_tile(job: _TileJob) -> tuple[dict[str, str], dict[str, Any], float]:
    """One tile: restored from its unit, or run and kept as a unit. Returns
    the files of its grids, its summary and the seconds it took (0 reused)."""
    from .units import Units

    units = Units(Path(job.unit_root) if job.unit_root else None, Path(job.unit_tmp) if job.unit_tmp else None,
                  job.stage, job.code_material)
    unit = _tile_unit(units, job)
    work = Path(job.work) / job.pass_name / job.tile.name
    saved = unit.restore(work) if unit.folder is not None and job.keep else None
    if saved is not None:
        return _files_and_summary(unit.folder, saved)
    t0 = time.perf_counter()
    cl = None
    if job.uses_opencl:
        from .opencl import get_cl

        cl = get_cl()
    tctx = TileContext(job.tile, job.seed, job.stage, Path(job.project_root), cl)
    shared = job.shared.read() if isinstance(job.shared, _SharedFile) else job.shared
    out = job.fn(tctx, job.inputs, job.params, shared)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    files = []
    for name, arr in out.grids.items():
        arr = np.asarray(arr)
        if arr.shape[:2] != (job.tile.rows, job.tile.cols):
            raise StageError(f"stage {job.stage}: pass {job.pass_name} tile {job.tile.name}: grid {name} has shape "
                             f"{arr.shape}, the tile is {job.tile.rows} x {job.tile.cols}")
        np.save(work / f"{name}.npy", np.ascontiguousarray(arr), allow_pickle=False)
        files.append(f"{name}.npy")
    for name, arr in out.files.items():
        np.save(work / f"{name}.npy", np.ascontiguousarray(arr), allow_pickle=False)
        files.append(f"{name}.npy")
    arrays, values = _split_summary(out.summary)
    if arrays:
        np.savez(work / SUMMARY_ARRAYS, **arrays)
        files.append(SUMMARY_ARRAYS)
    result = {"grids": sorted(out.grids), "summary": values, "files": sorted(out.files)}
    seconds = time.perf_counter() - t0
    if job.keep:
        unit.save(work, files, result, {"seconds": round(seconds, 4)})
    folder = unit.folder if unit.folder is not None and unit.folder.is_dir() else work
    files_out, summary, _ = _files_and_summary(folder, result)
    return files_out, summary, seconds


def _files_and_summary(folder: Path, result: dict) -> tuple[dict[str, str], dict[str, Any], float]:
    files = {name: str(folder / f"{name}.npy") for name in result["grids"]}
    summary = dict(result["summary"])
    summary.update({name: str(folder / f"{name}.npy") for name in result.get("files", ())})
    if (folder / SUMMARY_ARRAYS).is_file():
        with np.load(folder / SUMMARY_ARRAYS, allow_pickle=False) as z:
            summary.update({k: z[k] for k in z.files})
    return files, summary, 0.0


class TileRunner:
    """Runs a per-tile function on every tile of a world (ctx.tiles of a
    tiled run): in this process one tile after another, or, inside a Dask
    worker, as Dask tasks of the same cluster."""

    def __init__(self, tile_cells: int, *, stage: Any, run_key: str, seed: int, project_root: Path,
                 units: Any, work: Path, progress: Callable[[float, str], None] = lambda f, m: None):
        self.tile_cells = int(tile_cells)
        self.stage, self.run_key, self.seed, self.project_root = stage, run_key, seed, Path(project_root)
        self.units, self.work, self.progress = units, Path(work), progress
        self.passes: list[dict[str, Any]] = []  # per pass: tiles, reused, seconds (the run's metrics)
        self.tile_units: dict[str, Path | None] = {}  # the kept passes' tile units: name -> folder

    def drop_units(self) -> None:
        """Remove the run's tile units from the store: once its artifacts are
        written they would only resume a run that is already whole."""
        for folder in self.tile_units.values():
            if folder is not None:
                shutil.rmtree(folder, ignore_errors=True)

    def tiles(self, shape: tuple[int, int]) -> list[Tile]:
        return tiles_of(shape, self.tile_cells)

    def discard(self, arrays: TileArrays | None) -> None:
        """Delete the files of a pass not kept as units (keep=False) once no
        later pass reads them: rounds of a pass would otherwise pile up in
        the work folder. Files in the store (kept units) stay."""
        if arrays is None:
            return
        self.discard_files(arrays.files.values())

    def discard_files(self, paths) -> None:
        """discard for the paths of TileOutput.files."""
        work = self.work.resolve()
        for path in paths:
            if Path(path).resolve().is_relative_to(work):
                Path(path).unlink(missing_ok=True)

    def kept(self, pass_name: str, shape: tuple[int, int]) -> bool:
        """Whether every tile of a kept pass is in the store: a resumed run
        may skip the passes that only led to it."""
        return self.units is not None and all(self.units.saved(*_tile_unit_id(self.run_key, pass_name, t))
                                              for t in self.tiles(shape))

    def map(self, fn: Callable, pass_name: str, shape: tuple[int, int], inputs: dict[str, Any], params: Any,
            shared: Any = None, *, grids: dict[str, tuple[str, ...]] | None = None, cell_size_m: float = 1.0,
            origin_m: tuple[float, float] = (0.0, 0.0), keep: bool = True, per_tile: dict[str, Any] | None = None
            ) -> tuple[dict[str, TileArrays], list[dict[str, Any]]]:
        """fn(TileContext, inputs, params, shared) -> TileOutput on every tile
        of a `shape` world. per_tile: tile name -> the `shared` value of that
        tile alone (a global pass's answer per tile, not sent to every task).
        grids: the arrays fn returns, name -> channels.
        keep: each tile a unit in the store (False: a cheap pass whose arrays
        only the run needs, remade on a resume). Returns the grids as
        TileArrays and the tiles' summaries in tile order."""
        tiles = self.tiles(shape)
        root = self.units.root if self.units is not None else None
        tmp = self.units.tmp if self.units is not None else None
        code = self.units.code_material if self.units is not None else {"stage": self.stage.name}
        jobs = [_TileJob(fn, pass_name, t, inputs, params, per_tile[t.name] if per_tile is not None else shared,
                         self.seed, self.stage.name,
                         self.stage.uses_opencl, str(self.project_root), str(root) if root else None,
                         str(tmp) if tmp else None, str(self.work), code, self.run_key, keep) for t in tiles]
        t0 = time.perf_counter()
        results = self._dask(jobs) if _in_dask_worker() else self._local(jobs, pass_name)
        for job in jobs:  # the unit keys the run used (its manifest keeps them from gc)
            if self.units is not None and keep:
                unit = _tile_unit(self.units, job)
                self.tile_units[unit.name] = unit.folder
        self.passes.append({"pass": pass_name, "tiles": len(tiles), "kept": keep,
                            "reused": sum(1 for _, _, s in results if s == 0.0),
                            "tile_seconds": round(sum(s for _, _, s in results), 3),
                            "wall_s": round(time.perf_counter() - t0, 3)})
        out = {name: TileArrays(name, shape, chans, cell_size_m, origin_m, self.tile_cells,
                                {(t.row, t.col): files[name] for t, (files, _, _) in zip(tiles, results)})
               for name, chans in (grids or {}).items()}
        return out, [summary for _, summary, _ in results]

    def _local(self, jobs: list[_TileJob], pass_name: str) -> list:
        results = []
        for i, job in enumerate(jobs):
            self.progress(i / len(jobs), f"{pass_name}: tile {job.tile.name} ({i + 1} of {len(jobs)})")
            results.append(_run_tile(job))
        return results

    def _dask(self, jobs: list[_TileJob]) -> list:
        from distributed import worker_client

        # The tasks' `shared` values reach the workers as files in the work folder (which every worker reads,
        # as it reads the tiles' grids), not inside the task graph: a value sent to every task would be in the
        # graph once per tile (tens of MiB at 256 tiles, held by the scheduler, and Dask warns of it), and the
        # tiles' own parts add up to the world's. Scattering them instead would lose them with a worker that
        # dies; a file stays for the task's retry. One file per distinct value: a value all tiles read is one.
        if not jobs:
            return []
        folder = self.work / jobs[0].pass_name / SHARED_FOLDER
        files: dict[int, _SharedFile] = {}
        for job in jobs:
            if id(job.shared) not in files:
                files[id(job.shared)] = _SharedFile.write(folder / f"{len(files)}.pkl", job.shared)
        sent = [files[id(job.shared)] for job in jobs]
        try:
            with worker_client() as client:  # this task leaves its slot to the tiles while it waits
                # ahead of queued stage runs: a stage holding a world's state waits on these
                futures = client.map(_run_tile, [dataclasses.replace(job, shared=f) for job, f in zip(jobs, sent)],
                                     pure=False, priority=1,
                                     key=[f"{self.stage.name}-{self.run_key}-{j.pass_name}-{j.tile.name}" for j in jobs])
                return client.gather(futures)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
