"""The stage on a tiled world (tiled.py): steps 1 to 3 per tile give the
untiled bake's files byte for byte, in this process and on Dask."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
FILL = ("outputs=[\"hydrology\"]", "hydrology.depression=fill", "erosion.enabled=false")


def bake(project: Path, build: str, *sets: str, executor: str = "local") -> dict:
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", build, "bake", "configs/default.toml", "--json",
           "--executor", executor, *[a for s in sets for a in ("--set", s)]]
    proc = subprocess.run(cmd, cwd=project, capture_output=True, text=True, env={**os.environ, "WORLDBAKE_REPORT": "0"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {s["stage"]: s["key"] for s in json.loads(proc.stdout)[0]["steps"]}


def files(build: Path, stage: str, key: str) -> dict[str, str]:
    folder = build / "artifacts" / stage / key
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())
            if p.name != "manifest.json"}


@pytest.fixture
def project(tmp_path):
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    return tmp_path


@pytest.mark.parametrize("resolution, executor", [(512, "local"), (640, "dask")])
def test_tiled_hydrology_writes_the_untiled_files(project, resolution, executor):
    """2 x 2 tiles, and 3 x 3 with part tiles on Dask: filled, routing,
    directions, accumulation and everything made from them."""
    sets = (*FILL, f"heightmap.resolution={resolution}")
    whole = bake(project, "b_whole", *sets)
    tiled = bake(project, "b_tiled", *sets, "tiling.tile_cells=256", executor=executor)
    assert whole == tiled, (whole, tiled)
    assert files(project / "b_whole", "hydrology", whole["hydrology"]) == \
        files(project / "b_tiled", "hydrology", tiled["hydrology"])
    manifest = json.loads((project / "b_tiled" / "artifacts" / "hydrology" / tiled["hydrology"] /
                           "manifest.json").read_text())
    assert manifest["metrics"]["tiled_steps"].startswith("fill, routing surface")
    assert {p["pass"] for p in manifest["metrics"]["tiling"]["passes"]} >= {"fill", "filled", "directions",
                                                                            "accumulation", "counts"}
