"""Blender (bpy 5.0, from PyPI) as a real USD client of the baked world.

bpy needs numpy<2 and this project numpy>=2, so Blender lives in its own
environment, .venv-blender (`make dcc-env`, which .ci/run calls): the tests
write their inputs here and run Blender as a subprocess
(blender_scripts/*.py), which writes JSON and images back. Without that
environment every test here skips and says why.

One small world is baked and exported (folder and .usdz) per session: the
SMALL settings of tests/pipeline/test_cli.py with the tree species built."""
from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BLENDER_PY = REPO / ".venv-blender" / "bin" / "python"
SCRIPTS = Path(__file__).resolve().parent / "blender_scripts"
TREES = ("conifer", "broadleaf")
IMPOSTORS_SMALL = [a for kv in ("frames=8", "atlas_px=256", "samples=1", "heldout_px=24", "heldout_samples=1",
                                "heldout_stride=108", "card_px=16") for a in ("--set", f"impostors.{kv}")]
SMALL = ["--set", "heightmap.resolution=96", "--set", "world.texture_size=64", "--set", "shared.mesh_max_vertices=49",
         *IMPOSTORS_SMALL, "--set", f"plants.build={json.dumps(list(TREES) + ['grass'])}",
         "--set", "plants.hausdorff_samples=2000", "--set", "world.ground_texel_m=16",
         "--set", "world.ground_tile_texels=256"]


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


@pytest.fixture(scope="session")
def small_world(tmp_path_factory) -> dict:
    """The small world baked, exported as a folder and as a .usdz (moved
    to another folder): {folder, usdz, build, root}."""
    reuse = os.environ.get("WORLDBAKE_DCC_WORLD")  # a folder this fixture filled before: no bake (for work on the tests)
    if reuse:
        root = Path(reuse)
        return {"folder": root / "export" / "world.usda", "usdz": root / "elsewhere" / "world.usdz",
                "build": root / "build", "root": root}
    root = tmp_path_factory.mktemp("dcc_world")
    build = root / "build"
    base = [sys.executable, "-m", "pipeline.cli", "--build", str(build)]
    for args in (["bake", "configs/default.toml", *SMALL], ["export", "default", str(root / "export")],
                 ["export", "default", str(root / "packed" / "world.usdz")]):
        proc = subprocess.run(base + args, capture_output=True, text=True, cwd=REPO, timeout=900)
        assert proc.returncode == 0, f"worldbake {' '.join(args)}:\n{proc.stderr[-3000:]}"
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    usdz = elsewhere / "world.usdz"
    (root / "packed" / "world.usdz").rename(usdz)
    (root / "packed").rmdir()
    return {"folder": root / "export" / "world.usda", "usdz": usdz, "build": build, "root": root}


@pytest.fixture(scope="session")
def dcc_world(small_world, blender) -> dict:
    """small_world and what Blender imports (import_report.py) from the
    folder and from the .usdz: {..., report, usdz_report}."""
    reports = {}
    for name, src in (("report", small_world["folder"]), ("usdz_report", small_world["usdz"])):
        out = small_world["root"] / f"{name}.json"
        blender("import_report", src, out)
        reports[name] = json.loads(out.read_text())
    return {**small_world, **reports}
