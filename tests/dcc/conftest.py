"""Blender (bpy 5.0, from PyPI) as a real USD client of the baked world.

bpy needs numpy<2 and this project numpy>=2, so Blender lives in its own
environment, .venv-blender (`make dcc-env`, which .ci/run calls): the tests
write their inputs here and run Blender as a subprocess
(blender_scripts/*.py), which writes JSON and images back. Without that
environment every test here skips and says why.

One small world is baked and exported (folder and .usdz) per test run: the
SMALL settings of tests/pipeline/test_cli.py with the tree species built.
The xdist workers share it (the first bakes under a file lock, the others
wait and read it), and the bake's store is the content-keyed build folder
build_dcc_tests/ (WORLDBAKE_DCC_BUILD), so a rerun bakes only the stages
whose code or inputs changed. `make test` keeps these tests on one worker
(xdist_group "dcc", --dist loadgroup): the others go on with the rest."""
from __future__ import annotations

import fcntl
import functools
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BLENDER_PY = REPO / ".venv-blender" / "bin" / "python"
SCRIPTS = Path(__file__).resolve().parent / "blender_scripts"
TREES = ("conifer", "broadleaf")
# the default samples per texel (3 x 3): the slices' alpha and colour are what a user gets; frames of 64 px
# (the default conifer's), so the Impostor prim's tiles have 128 texels, one per pixel of test_blender's views
IMPOSTORS_SMALL = [a for kv in ("frames=8", "atlas_px=512", "heldout_px=24", "heldout_samples=1",
                                "heldout_stride=108", "card_px=16") for a in ("--set", f"impostors.{kv}")]
SMALL = ["--set", "heightmap.resolution=96", "--set", "world.texture_size=64", "--set", "shared.mesh_max_vertices=49",
         *IMPOSTORS_SMALL, "--set", f"plants.build={json.dumps(list(TREES) + ['grass'])}",
         "--set", "plants.hausdorff_samples=2000", "--set", "world.ground_texel_m=16",
         "--set", "world.ground_tile_texels=256",
         "--set", "world.terrain_tile_quads=16"]  # 48 quads a side: 3 x 3 terrain tiles, each a payload


@functools.lru_cache(maxsize=1)
def blender_problem() -> str | None:
    """Why Blender cannot run here, or None."""
    if not BLENDER_PY.exists():
        return f"{BLENDER_PY.relative_to(REPO)} is missing: `make dcc-env` installs Blender (bpy 5.0.1 from PyPI)"
    proc = subprocess.run([str(BLENDER_PY), "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True,
                          text=True, timeout=120)
    if proc.returncode != 0:
        return f"bpy does not import in {BLENDER_PY.parent.parent.name}: {proc.stderr.strip()[-400:]}"
    return None


def run_blender(script: str, *args, timeout: float = 300) -> subprocess.CompletedProcess:
    """Runs blender_scripts/<script>.py with Blender's Python; fails with its output."""
    cmd = [str(BLENDER_PY), str(SCRIPTS / f"{script}.py"), *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


@pytest.fixture(scope="session")
def blender():
    problem = blender_problem()
    if problem:
        pytest.skip(f"Blender tests skipped: {problem}")
    return run_blender


def pytest_collection_modifyitems(items):
    """Every test here on one xdist worker (with --dist loadgroup): one bake, and no worker idles waiting for it."""
    here = Path(__file__).resolve().parent
    for item in items:
        if here in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.xdist_group("dcc"))


def _run_root(tmp_path_factory) -> Path:
    """A folder of this test run that every xdist worker sees."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _once(tmp_path_factory, name: str, make) -> Path:
    """run_root/name, made by make(folder) by the first process of this test run to ask (the others wait)."""
    root = _run_root(tmp_path_factory)
    folder, done = root / name, root / f"{name}.done"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.exists():
                shutil.rmtree(folder, ignore_errors=True)  # what a process that failed here left
                folder.mkdir()
                make(folder)
                done.touch()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return folder


def _bake_and_export(root: Path) -> None:
    build = Path(os.environ.get("WORLDBAKE_DCC_BUILD") or REPO / "build_dcc_tests")
    base = [sys.executable, "-m", "pipeline.cli", "--build", str(build)]
    # --replace: this folder is the tests' own cache, and a change of SMALL must not stop the bake
    for args in (["bake", "configs/default.toml", *SMALL, "--replace"], ["export", "default", str(root / "export")],
                 ["export", "default", str(root / "packed" / "world.usdz")]):
        proc = subprocess.run(base + args, capture_output=True, text=True, cwd=REPO, timeout=900)
        assert proc.returncode == 0, f"worldbake {' '.join(args)}:\n{proc.stderr[-3000:]}"
    (root / "build").symlink_to(build.resolve(), target_is_directory=True)
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    (root / "packed" / "world.usdz").rename(elsewhere / "world.usdz")
    (root / "packed").rmdir()


@pytest.fixture(scope="session")
def small_world(tmp_path_factory) -> dict:
    """The small world baked, exported as a folder and as a .usdz (moved
    to another folder): {folder, usdz, build, root}."""
    reuse = os.environ.get("WORLDBAKE_DCC_WORLD")  # a folder this fixture filled before: no bake (for work on the tests)
    root = Path(reuse) if reuse else _once(tmp_path_factory, "dcc_world", _bake_and_export)
    return {"folder": root / "export" / "world.usda", "usdz": root / "elsewhere" / "world.usdz",
            "build": root / "build", "root": root}


@pytest.fixture(scope="session")
def dcc_world(small_world, blender, tmp_path_factory) -> dict:
    """small_world and what Blender imports (import_report.py) from the
    folder and from the .usdz: {..., report, usdz_report}."""
    sources = (("report", small_world["folder"]), ("usdz_report", small_world["usdz"]))

    def imports(folder: Path) -> None:
        for name, src in sources:
            blender("import_report", src, folder / f"{name}.json")

    folder = _once(tmp_path_factory, "dcc_imports", imports)
    return {**small_world, **{name: json.loads((folder / f"{name}.json").read_text()) for name, _ in sources}}
