"""Tiled runs ([tiling] tile_cells, pipeline.tiles): a tiled bake writes the
same files as the untiled bake of the same config, under the same keys, in
this process and on Dask; its tiles are store units a later run resumes
from; bad tilings are refused before any stage runs."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import exr
from pipeline.tiles import GridFile, TileArrays, TileOutput, TileRunner, tiles_of

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def project(tmp_path):
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    return tmp_path


def bake(project: Path, build: str, *sets: str, executor: str = "local", check: bool = True):
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", build, "bake", "configs/default.toml", "--json",
           "--executor", executor, "--set", 'outputs=["heightmap"]', *[a for s in sets for a in ("--set", s)]]
    proc = subprocess.run(cmd, cwd=project, capture_output=True, text=True, env={**os.environ, "WORLDBAKE_REPORT": "0"})
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def stage_files(build: Path, stage: str) -> dict[str, str]:
    """Every file of the stage's run but its manifest (a run record), by sha256."""
    (folder,) = (build / "artifacts" / stage).iterdir()
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())
            if p.name != "manifest.json"}


def manifest(build: Path, stage: str) -> dict:
    (folder,) = (build / "artifacts" / stage).iterdir()
    return json.loads((folder / "manifest.json").read_text())


def test_tiles_cover_the_world_once():
    for shape, t in (((640, 384), 256), ((512, 512), 256), ((100, 700), 256), ((300, 300), 0)):
        seen = np.zeros(shape, int)
        for tile in tiles_of(shape, t):
            seen[tile.row0:tile.row0 + tile.rows, tile.col0:tile.col0 + tile.cols] += 1
            r0, c0, rows, cols = tile.window(3)
            assert r0 >= 0 and c0 >= 0 and r0 + rows <= shape[0] and c0 + cols <= shape[1]
            inner = tile.inner(3)
            assert (inner[0].stop - inner[0].start, inner[1].stop - inner[1].start) == (tile.rows, tile.cols)
        assert (seen == 1).all()


def test_tile_arrays_read_windows_across_tiles(tmp_path):
    shape, t = (600, 520), 256
    whole = np.random.default_rng(3).random(shape).astype(np.float32)
    files = {}
    for tile in tiles_of(shape, t):
        path = tmp_path / f"{tile.name}.npy"
        np.save(path, whole[tile.row0:tile.row0 + tile.rows, tile.col0:tile.col0 + tile.cols])
        files[(tile.row, tile.col)] = str(path)
    arrays = TileArrays("h", shape, ("height",), 8.0, (0.0, 0.0), t, files)
    for window in ((0, 0, 600, 520), (250, 250, 10, 10), (255, 1, 300, 519), (599, 519, 1, 1)):
        r0, c0, rows, cols = window
        assert np.array_equal(arrays.read(*window), whole[r0:r0 + rows, c0:c0 + cols])


def _state_of_tile(tctx, inputs, params, shared):
    t = tctx.tile
    return TileOutput(summary={"n": t.rows * t.cols}, files={"state": np.full((3, t.col0 + 1), t.row0, np.int32)})


def test_a_tiles_file_arrays_stay_in_files_until_discarded(tmp_path):
    """TileOutput.files: any shape, kept in a file whose path the summary
    holds (not the array: state too big to gather in one process);
    discard_files deletes what the run's work folder holds of them."""
    from types import SimpleNamespace

    runner = TileRunner(128, stage=SimpleNamespace(name="toy", uses_opencl=False), run_key="k", seed=0,
                        project_root=tmp_path, units=None, work=tmp_path / "work")
    _, parts = runner.map(_state_of_tile, "state", (300, 200), {}, None, keep=False)
    tiles = runner.tiles((300, 200))
    assert len(parts) == len(tiles) == 6
    for t, part in zip(tiles, parts):
        assert isinstance(part["state"], str) and part["n"] == t.rows * t.cols
        assert np.array_equal(np.load(part["state"]), np.full((3, t.col0 + 1), t.row0, np.int32))
    runner.discard_files(p["state"] for p in parts)
    assert not any(Path(p["state"]).exists() for p in parts)


def _sum_of_shared(tctx, inputs, params, shared):
    values = shared["scale"](shared["values"]) if isinstance(shared, dict) else shared
    return TileOutput(summary={"sum": float(np.asarray(values).sum()), "tile": tctx.tile.name})


def _passes_on_a_worker(work: str) -> tuple[list, list, list[str], bool]:
    """Two passes of a 16-tile world run from inside a Dask task: one with a
    1 MiB value every tile reads (and a function made here, which Dask's
    cloudpickle carries and plain pickle would not), one with a 1 MiB part
    per tile; the Dask warnings they raise and whether the values' files are
    left behind."""
    import warnings
    from types import SimpleNamespace

    runner = TileRunner(256, stage=SimpleNamespace(name="toy", uses_opencl=False), run_key="k", seed=0,
                        project_root=Path(work), units=None, work=Path(work) / "work")
    shape = (1024, 1024)
    big = np.arange(1 << 18, dtype=np.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _, every = runner.map(_sum_of_shared, "every", shape, {}, None, {"values": big, "scale": lambda v: 2 * v},
                              keep=False)
        own = {t.name: big + i for i, t in enumerate(runner.tiles(shape))}
        _, parts = runner.map(_sum_of_shared, "own", shape, {}, None, per_tile=own, keep=False)
    left = any((Path(work) / "work" / name / "_shared").exists() for name in ("every", "own"))
    return every, parts, [str(w.message) for w in caught if "large graph" in str(w.message)], left


def test_tile_tasks_on_dask_get_their_shared_values_outside_the_task_graph(tmp_path):
    """A value every tile reads is sent once, and the tiles' own parts are
    not gathered in the graph: 16 tiles of 1 MiB would make a 16 MiB graph,
    which Dask warns of (its limit is 10 MB) and its scheduler would hold."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        every, parts, warned, left = client.submit(_passes_on_a_worker, str(tmp_path), pure=False).result()
    total = float(np.arange(1 << 18, dtype=np.float32).sum())
    assert [p["sum"] for p in every] == [2 * total] * 16
    assert [p["sum"] for p in parts] == [total + i * (1 << 18) for i in range(16)]
    assert warned == [] and not left


@pytest.mark.parametrize("resolution, tile_cells", [(512, 256), (640, 256)])
def test_a_tiled_heightmap_is_the_untiled_one_byte_for_byte(project, resolution, tile_cells):
    """4 tiles, and 3 x 3 tiles whose last row and column are part tiles."""
    res = f"heightmap.resolution={resolution}"
    whole = bake(project, "b_whole", res)
    tiled = bake(project, "b_tiled", res, f"tiling.tile_cells={tile_cells}")
    key = lambda p: json.loads(p.stdout)[0]["steps"][0]["key"]
    assert key(whole) == key(tiled)  # the tiling is how the work is done, not what it makes: in no key
    assert stage_files(project / "b_whole", "heightmap") == stage_files(project / "b_tiled", "heightmap")
    m = manifest(project / "b_tiled", "heightmap")
    n = (-(-resolution // tile_cells)) ** 2
    assert m["metrics"]["tiling"]["passes"][0]["tiles"] == n
    # the tile units resume a stopped run; once the run is in place they are gone (tiling.keep_tiles keeps them)
    assert m["units"] == {} and not list((project / "b_tiled" / "units").glob("heightmap/*"))
    assert "tiling" not in manifest(project / "b_whole", "heightmap")["metrics"]
    for name in ("height_min_m", "height_max_m"):
        assert m["metrics"][name] == manifest(project / "b_whole", "heightmap")["metrics"][name]
    info = exr.grid_info(next((project / "b_tiled" / "artifacts" / "heightmap").glob("*/height.exr")))
    assert info.shape == (resolution, resolution) and info.tile == exr.TILE


def test_a_tiled_bake_on_dask_is_the_local_one(project):
    local = bake(project, "b_local", "heightmap.resolution=512")
    dask = bake(project, "b_dask", "heightmap.resolution=512", "tiling.tile_cells=256", executor="dask")
    assert json.loads(local.stdout)[0]["steps"][0]["key"] == json.loads(dask.stdout)[0]["steps"][0]["key"]
    assert stage_files(project / "b_local", "heightmap") == stage_files(project / "b_dask", "heightmap")


def test_a_stopped_tiled_bake_resumes_from_its_tiles(project):
    """The run's tiles are units: with the run itself gone (a bake killed
    before its rename), the next bake reuses every tile and writes the same files."""
    # keep_tiles: the units outlive the run, so removing the run leaves what a kill before its rename leaves
    bake(project, "b", "heightmap.resolution=512", "tiling.tile_cells=256", "tiling.keep_tiles=true")
    before = stage_files(project / "b", "heightmap")
    shutil.rmtree(project / "b" / "artifacts" / "heightmap")
    bake(project, "b", "heightmap.resolution=512", "tiling.tile_cells=256", "tiling.keep_tiles=true")
    assert stage_files(project / "b", "heightmap") == before
    m = manifest(project / "b", "heightmap")
    (p,) = m["metrics"]["tiling"]["passes"]
    assert p["reused"] == p["tiles"] == len(m["units"]) == 4


# 2 m cells in 3 x 3 tiles of 256 (the last row and column part tiles): geological time and the storm on
# 8 m blocks with the microrelief below them, the talus rule's 150 iterations in rounds of 32
ERODED = ("heightmap.size_m=1280", "heightmap.resolution=640", "erosion.geological_cell_m=8", 'outputs=["erosion"]')


@pytest.mark.parametrize("executor", ["local", "dask"])
def test_a_tiled_erosion_is_the_untiled_one_byte_for_byte(project, executor):
    bake(project, "whole", *ERODED)
    bake(project, "tiled", *ERODED, "tiling.tile_cells=256", executor=executor)
    assert stage_files(project / "tiled", "erosion") == stage_files(project / "whole", "erosion")
    whole, tiled = manifest(project / "whole", "erosion")["metrics"], manifest(project / "tiled", "erosion")["metrics"]
    assert tiled["geological_cell_factor"] == tiled["storm_cell_factor"] == 4 and tiled["thermal_rounds"] == 5
    assert tiled["microrelief_classes"] == whole["microrelief_classes"] == 4  # the relief finer than the geology's 8 m
    for key in ("steps", "thermal_iterations", "wear_volume_m3", "final_fraction_above_talus", "thermal_max_excess_deg"):
        assert tiled[key] == pytest.approx(whole[key], rel=1e-12), key
    passes = tiled["tiling"]["passes"]
    assert [p["pass"] for p in passes] == ["prepare", "heights", "thermal0", "thermal32", "thermal64", "thermal96",
                                           "thermal128", "storm_input", "maps"]
    assert [p["kept"] for p in passes] == [True, True, False, False, False, False, True, False, True]
    assert all(p["tiles"] == 9 for p in passes)


def test_a_stopped_tiled_erosion_resumes_from_its_last_talus_round(project):
    """The talus rule's rounds before the last are not kept; a bake that
    finds the last round's tiles in the store starts there."""
    bake(project, "b", *ERODED, "tiling.tile_cells=256", "tiling.keep_tiles=true")
    before = stage_files(project / "b", "erosion")
    shutil.rmtree(project / "b" / "artifacts" / "erosion")
    bake(project, "b", *ERODED, "tiling.tile_cells=256", "tiling.keep_tiles=true")
    assert stage_files(project / "b", "erosion") == before
    passes = manifest(project / "b", "erosion")["metrics"]["tiling"]["passes"]
    assert [p["pass"] for p in passes] == ["prepare", "heights", "thermal128", "storm_input", "maps"]
    assert [p["reused"] for p in passes] == [9, 9, 9, 0, 9]


def test_a_world_whose_erosion_spans_its_cells_runs_whole(project):
    """16 m cells: the storm would run on the terrain's own cells."""
    sets = ("heightmap.resolution=512", 'outputs=["erosion"]', "erosion.geological_years=1e6")
    bake(project, "whole", *sets)
    bake(project, "tiled", *sets, "tiling.tile_cells=256")
    assert stage_files(project / "tiled", "erosion") == stage_files(project / "whole", "erosion")
    assert manifest(project / "tiled", "erosion")["metrics"]["tiled_steps"].startswith("none: geological time runs")


def test_tiled_inputs_are_read_by_window(tmp_path):
    grid = np.arange(700 * 300, dtype=np.float32).reshape(700, 300)
    from pipeline.grid import Grid

    exr.write_grid(tmp_path / "g.exr", Grid(grid, 2.0))
    g = GridFile(tmp_path / "g.exr")
    assert g.shape == (700, 300) and g.cell_size_m == 2.0
    tile = tiles_of(g.shape, 256)[4]  # the middle of the second row of tiles
    r0, c0, rows, cols = tile.window(2)
    assert np.array_equal(g.read_tile(tile, 2), grid[r0:r0 + rows, c0:c0 + cols])


@pytest.mark.parametrize("value, why", [("100", "multiple of 256"), ("-256", "multiple of 256"),
                                        ('"big"', "multiple of 256"), ("true", "multiple of 256")])
def test_a_bad_tiling_is_refused_before_any_stage_runs(project, value, why):
    proc = bake(project, "b", f"tiling.tile_cells={value}", check=False)
    assert proc.returncode == 2 and "tiling.tile_cells" in proc.stderr and why in proc.stderr
    assert not (project / "b" / "artifacts").exists()


def test_an_unknown_tiling_key_is_named(project):
    proc = bake(project, "b", "tiling.tile_size=256", check=False)
    assert proc.returncode == 2 and "tiling.tile_size: unknown key" in proc.stderr
    proc = bake(project, "b", "tiling.keep_tiles=1", check=False)
    assert proc.returncode == 2 and "tiling.keep_tiles: must be true or false, got 1" in proc.stderr
    assert not (project / "b").exists() or not list((project / "b").glob("artifacts/*"))


def test_a_tiled_run_is_checked_for_the_memory_of_a_tile(project):
    """A world too large to hold whole is refused untiled, and baked in tiles."""
    big = ("heightmap.resolution=2048",)
    env_limit = {"WORLDBAKE_MAX_MEMORY_GB": "0.1"}  # 2048^2 x 48 B = 0.19 GiB; a tile of 256 and its halo: 3 MiB
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", "b", "bake", "configs/default.toml",
           "--set", 'outputs=["heightmap"]', "--set", big[0]]
    env = {**os.environ, "WORLDBAKE_REPORT": "0", **env_limit}
    refused = subprocess.run(cmd, cwd=project, capture_output=True, text=True, env=env)
    assert refused.returncode == 2 and "heightmap.resolution" in refused.stderr
    tiled = subprocess.run(cmd + ["--set", "tiling.tile_cells=256"], cwd=project, capture_output=True, text=True,
                           env=env)
    assert tiled.returncode == 0, tiled.stderr[-2000:]


@pytest.mark.parametrize("args, named", [(("--workers", "0"), "--workers 0"),
                                         (("--worker-memory", "0"), "--worker-memory 0")])
def test_bad_cluster_sizes_are_refused_before_any_work(project, args, named):
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", "b", "bake", "configs/default.toml", "--executor", "dask",
           *args]
    proc = subprocess.run(cmd, cwd=project, capture_output=True, text=True)
    assert proc.returncode == 2 and named in proc.stderr and not (project / "b").exists()
