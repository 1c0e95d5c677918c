"""Bakes of a small world tiled and untiled, through the command line as a
user runs it, for the tests that compare their files."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path


def bake_keys(project: Path, build: str, *sets: str, executor: str = "local") -> dict:
    """Bake configs/default.toml in `project` with these --set overrides;
    the key of every stage run."""
    cmd = [sys.executable, "-m", "pipeline.cli", "--build", build, "bake", "configs/default.toml", "--json",
           "--executor", executor, *[a for s in sets for a in ("--set", s)]]
    proc = subprocess.run(cmd, cwd=project, capture_output=True, text=True, env={**os.environ, "WORLDBAKE_REPORT": "0"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {s["stage"]: s["key"] for s in json.loads(proc.stdout)[0]["steps"]}


def artifact_files(build: Path, stage: str, key: str) -> dict[str, str]:
    """Every file of an artifact (sub-folders too) but its manifest, by path, as its hash."""
    folder = build / "artifacts" / stage / key
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != "manifest.json"}
