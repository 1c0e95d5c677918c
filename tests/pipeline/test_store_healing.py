"""A damaged store heals itself, a full check finds what the cheap one
cannot, and a dry-run gc waits for nobody. Each damage is done to a copy of
one baked small world's build folder; the next bake must exit 0 with a
world equal to the clean bake, and say in one line what it made again."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.store import MANIFEST, Store

from .test_cli import REPO, SMALL, _decoded, worldbake


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Path:
    """A project with one clean small world in build/."""
    project = tmp_path_factory.mktemp("heal")
    shutil.copytree(REPO / "configs", project / "configs")
    worldbake(project, "bake", "configs/default.toml", *SMALL)
    return project


def _copy(project: Path, name: str) -> Path:
    target = project / name
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(project / "build", target, symlinks=True)  # copy2: sizes and mtimes kept
    return target


def _world_content(build: Path) -> dict:
    """What the world is made of: the decoded artifacts it uses, by stage and file."""
    manifest = json.loads((build / "worlds" / "default" / MANIFEST).read_text())
    used = {f"{e['stage']}/{e['key']}" for e in manifest["uses"]}
    return {name: value for name, value in _decoded(build).items() if name.rsplit("/", 1)[0] in used} | \
        {"world.usda": (build / "worlds" / "default" / "world.usda").read_text()}


def _folder(build: Path, stage: str) -> Path:
    manifest = json.loads((build / "worlds" / "default" / MANIFEST).read_text())
    key = next(e["key"] for e in manifest["artifacts"] if e["stage"] == stage)
    return build / "artifacts" / stage / key


def _biggest_file(folder: Path) -> Path:
    return max((p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST), key=lambda p: p.stat().st_size)


def _delete_manifest(build):
    (_folder(build, "vegetation") / MANIFEST).unlink()


def _delete_file(build):
    _biggest_file(_folder(build, "vegetation")).unlink()


def _extra_file(build):
    (_folder(build, "vegetation") / "stray.txt").write_text("not the stage's\n")


def _truncate_file(build):
    path = _biggest_file(_folder(build, "vegetation"))
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size // 2)


def _empty_folder(build):
    folder = _folder(build, "vegetation")
    shutil.rmtree(folder)
    folder.mkdir()


def _unit_without_its_json(build):
    manifest = json.loads((_folder(build, "plants") / MANIFEST).read_text())
    unit = build / "units" / "plants" / next(iter(manifest["units"].values()))
    (unit / "unit.json").unlink()
    shutil.rmtree(_folder(build, "plants"))  # so the next run of plants meets the half unit


@pytest.mark.parametrize("damage", [_delete_manifest, _delete_file, _extra_file, _truncate_file, _empty_folder,
                                    _unit_without_its_json], ids=lambda f: f.__name__.strip("_"))
def test_a_damaged_store_is_made_whole_by_the_next_bake(baked, damage):
    reference = _world_content(baked / "build")
    build = _copy(baked, f"build_{damage.__name__.strip('_')}")
    damage(build)
    proc = worldbake(baked, "bake", "configs/default.toml", *SMALL, build=build.name)
    assert "Traceback" not in proc.stderr
    said = [line for line in proc.stderr.splitlines() if "again" in line]
    assert len(said) == 1 and ("vegetation" in said[0] or "unit" in said[0]), proc.stderr
    assert _world_content(build) == reference
    for folder in (build / "artifacts").glob("*/*"):
        manifest = json.loads((folder / MANIFEST).read_text())  # every folder whole
        on_disk = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
        assert on_disk == set(manifest["files"]) | {MANIFEST}, folder
    assert Store(build).verify_world("default")[0] == []
    shutil.rmtree(build)


def test_verify_finds_a_flipped_byte_that_keeps_size_and_mtime_and_bake_verify_remakes_it(baked):
    reference = _world_content(baked / "build")
    build = _copy(baked, "build_flip")
    path = next(p for p in _folder(build, "erosion").rglob("*.exr"))
    st = path.stat()
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert path.stat().st_size == st.st_size

    found = worldbake(baked, "verify", "default", build=build.name, check=False)
    assert found.returncode == 1, found.stderr
    assert path.name in found.stdout and "damaged" in found.stdout
    # the cheap check of a bake cannot see it; --verify re-hashes and makes it again
    remade = worldbake(baked, "bake", "configs/default.toml", *SMALL, "--verify", build=build.name)
    assert path.name in remade.stderr
    assert worldbake(baked, "verify", build=build.name, check=False).returncode == 0
    assert _world_content(build) == reference
    shutil.rmtree(build)


def test_gc_dry_run_does_not_wait_for_a_bake(baked):
    store = Store(baked / "build")
    with store.baking():  # a bake holds the store
        proc = subprocess.run([sys.executable, "-m", "pipeline.cli", "gc", "--dry-run"], cwd=baked,
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        assert "waits" not in proc.stderr
        busy = subprocess.run([sys.executable, "-m", "pipeline.cli", "gc", "--no-wait"], cwd=baked,
                              capture_output=True, text=True, timeout=60)
        assert busy.returncode != 0  # a real gc still refuses while the bake runs
