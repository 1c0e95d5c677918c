"""The content-addressed artifact store.

    build/artifacts/<stage>/<key>/   the files and manifest.json (written last)
    build/tmp/<stage>-<key>-<pid>/   a run in progress; renamed into place when whole
    build/worlds/<world>/            world.usda and manifest.json naming every key used
    build/units/<stage>/<key>/       parts of runs a later run of the stage may reuse (pipeline.units)

A folder under artifacts/ exists only once it is complete: runs write into
build/tmp/ (same file system) and rename, so a killed run leaves nothing in
artifacts/; `worldbake` removes leftovers of dead runs from build/tmp/.

build/store.lock: a bake holds it shared from its first look at the store
to the publishing of its worlds (what it made or reuses is named by no world
until then); gc holds it exclusive, so it waits for running bakes (or, not
waiting, refuses) and no bake starts while it deletes. flock locks go with
their process: a killed bake holds nothing.
"""
from __future__ import annotations

import contextlib
import fcntl
import fnmatch
import hashlib
import json
import os
import shutil
import sys
from pathlib import Path, PurePosixPath
from typing import Any, Iterator

MANIFEST = "manifest.json"
UNIT_MANIFEST = "unit.json"  # a unit folder's manifest (pipeline.units), written last
UNIT_RUN_RECORD = "run.json"  # beside a unit's unit.json: the figures of the run that made it (pipeline.units)

# Run records: the files that say how a bake went (timings, metrics, file
# mtimes, this bake's seconds), not what it made. They alone may differ
# between two clean bakes of the same config: no key and no USD layer hashes
# them, and no other file holds what they hold. Paths relative to the build
# folder; `*` is one folder name.
RUN_RECORDS = (
    f"artifacts/*/*/{MANIFEST}",      # a stage run: key, inputs, params, files (hashes, sizes, mtimes), timings, metrics
    f"worlds/*/{MANIFEST}",           # a world: the keys it uses, and this bake's steps with their seconds
    "worlds/*/report.html",           # the report: the runs' timings and metrics among the world's figures
    "worlds/*/report_cache.json",     # the report's figures as HTML (the same timings), for a bake of the same runs
    f"units/*/*/{UNIT_RUN_RECORD}",   # a unit: the run figures (seconds) of the run that made it
)


def is_run_record(relative_path: str) -> bool:
    """Whether a file of the build folder, by its POSIX path relative to
    the folder, is a run record (RUN_RECORDS)."""
    parts = PurePosixPath(relative_path).parts
    for pattern in RUN_RECORDS:
        want = PurePosixPath(pattern).parts
        if len(parts) == len(want) and all(fnmatch.fnmatchcase(a, b) for a, b in zip(parts, want)):
            return True
    return False


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _files_under(folder: Path) -> set[str]:
    """Every file below folder, as a POSIX path relative to it."""
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir()}


class StoreBusy(Exception):
    """gc without waiting while a bake uses the store."""


class Store:
    def __init__(self, build_dir: Path | str):
        self.build = Path(build_dir)
        self.artifacts = self.build / "artifacts"
        self.tmp = self.build / "tmp"
        self.worlds = self.build / "worlds"
        self.units = self.build / "units"  # pipeline.units: parts of runs that later runs reuse
        self.lock_path = self.build / "store.lock"

    @contextlib.contextmanager
    def _locked(self, mode: int, wait: bool, waiting_message: str | None = None) -> Iterator[None]:
        self.build.mkdir(parents=True, exist_ok=True)
        with open(self.lock_path, "a+") as f:
            try:
                fcntl.flock(f, mode | fcntl.LOCK_NB)
            except BlockingIOError:
                if not wait:
                    raise StoreBusy(f"{self.build}: a bake is using this build folder") from None
                if waiting_message:
                    print(waiting_message, file=sys.stderr, flush=True)
                fcntl.flock(f, mode)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def baking(self) -> contextlib.AbstractContextManager:
        """Held by a bake: many bakes at once, but no gc meanwhile."""
        return self._locked(fcntl.LOCK_SH, True, f"worldbake: waiting for gc in {self.build} to finish")

    def folder(self, stage: str, key: str) -> Path:
        return self.artifacts / stage / key

    def has(self, stage: str, key: str) -> bool:
        return (self.folder(stage, key) / MANIFEST).is_file()

    def manifest(self, stage: str, key: str) -> dict:
        return json.loads((self.folder(stage, key) / MANIFEST).read_text())

    def damaged(self, stage: str, key: str, full: bool = False) -> list[str]:
        """The files of a stored run that are no longer what it wrote:
        missing, extra (not in its manifest), another size, or another
        sha256. Without `full`, a file keeping the size and mtime it was
        written with is taken as unchanged (a bake's cheap check; an edit
        that restores both is found only by `full`, which hashes every file).
        A manifest that cannot be read makes the whole run damaged."""
        folder = self.folder(stage, key)
        try:
            manifest = self.manifest(stage, key)
            files, stats = dict(manifest["files"]), manifest.get("file_stats", {})
        except (OSError, ValueError, KeyError, TypeError):
            return [MANIFEST]
        bad = sorted(_files_under(folder) - set(files) - {MANIFEST})
        for rel, digest in files.items():
            try:
                st = (folder / rel).stat()
            except OSError:
                bad.append(rel)
                continue
            size, mtime_ns = stats.get(rel, (st.st_size, None))
            if st.st_size != size:
                bad.append(rel)
            elif (full or st.st_mtime_ns != mtime_ns) and sha256_file(folder / rel) != digest:
                bad.append(rel)
        return bad

    def verify_world(self, world: str) -> tuple[list[str], int]:
        """Re-hash every file the world uses against what its runs and units
        recorded (Store.damaged with full=True; units against their
        unit.json). Returns the problems, one line each, and the number of
        files checked."""
        manifest = json.loads((self.worlds / world / MANIFEST).read_text())
        entries = manifest.get("uses") or manifest.get("artifacts", [])
        problems, checked = [], 0
        for stage, key in sorted({(e["stage"], e["key"]) for e in entries}):
            if not self.has(stage, key):
                problems.append(f"{stage} {key}: missing from the store")
                continue
            problems += [f"{stage} {key}: {rel} is damaged" for rel in self.damaged(stage, key, full=True)]
            checked += len(self.manifest(stage, key).get("files", {}))
            for unit_key in self.manifest(stage, key).get("units", {}).values():
                folder = self.units / stage / unit_key
                try:
                    files = json.loads((folder / UNIT_MANIFEST).read_text())["files"]
                except (OSError, ValueError, KeyError, TypeError):
                    problems.append(f"{stage} unit {unit_key}: missing or without a readable {UNIT_MANIFEST}")
                    continue
                checked += len(files)
                for rel, digest in sorted(files.items()):
                    if not (folder / rel).is_file() or sha256_file(folder / rel) != digest:
                        problems.append(f"{stage} unit {unit_key}: {rel} is damaged")
        return problems, checked

    def discard(self, stage: str, key: str) -> None:
        """Take a damaged run out of the store (renamed aside first, so no
        reader ever finds it half deleted)."""
        self.tmp.mkdir(parents=True, exist_ok=True)
        aside = self.tmp / f"discarded-{stage}-{key}-{os.getpid()}"
        shutil.rmtree(aside, ignore_errors=True)
        try:
            os.rename(self.folder(stage, key), aside)
        except FileNotFoundError:  # a concurrent bake discarded it first
            return
        shutil.rmtree(aside, ignore_errors=True)

    def clean_stale(self) -> list[Path]:
        """Remove what killed runs left in build/tmp/ (their pid is gone)."""
        removed = []
        if not self.tmp.is_dir():
            return removed
        for entry in self.tmp.iterdir():
            pid = entry.name.rsplit("-", 1)[-1]
            if not pid.isdigit() or not _pid_alive(int(pid)) or int(pid) == os.getpid():
                shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() else entry.unlink(missing_ok=True)
                removed.append(entry)
        return removed

    @contextlib.contextmanager
    def writing(self, stage: str, key: str) -> Iterator[Path]:
        """A fresh temporary folder for a run; on a clean exit the caller has
        written its manifest last and the folder is renamed into place. On an
        exception it is deleted: nothing half-made is ever visible."""
        self.tmp.mkdir(parents=True, exist_ok=True)
        work = self.tmp / f"{stage}-{key}-{os.getpid()}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        try:
            yield work
            if not (work / MANIFEST).is_file():
                raise RuntimeError(f"internal: {stage} run finished without a manifest")
            final = self.folder(stage, key)
            final.parent.mkdir(parents=True, exist_ok=True)
            if final.exists() and not self.has(stage, key):
                # a folder without its manifest is not a run (deleted manifest, a copy cut short)
                print(f"worldbake: {stage} {key}: an incomplete folder (no {MANIFEST}) was in the store; "
                      f"moved aside and made again", file=sys.stderr, flush=True)
                self.discard(stage, key)
            try:
                os.rename(work, final)
            except OSError:
                if not self.has(stage, key):  # not a concurrent twin that won the race
                    raise
        finally:
            shutil.rmtree(work, ignore_errors=True)

    @contextlib.contextmanager
    def publishing(self, world: str) -> Iterator[Path]:
        """Like writing(), for build/worlds/<world>/: the old folder is
        replaced only once the new one is whole."""
        self.tmp.mkdir(parents=True, exist_ok=True)
        work = self.tmp / f"world-{world}-{os.getpid()}"
        old = self.tmp / f"oldworld-{world}-{os.getpid()}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        try:
            yield work
            final = self.worlds / world
            final.parent.mkdir(parents=True, exist_ok=True)
            if final.exists():
                os.rename(final, old)
            os.rename(work, final)
        finally:
            shutil.rmtree(work, ignore_errors=True)
            shutil.rmtree(old, ignore_errors=True)

    def closure(self, keys: set[tuple[str, str]]) -> set[tuple[str, str]]:
        """`keys` and every (stage, key) their manifests name as an input,
        transitively: a run cached by early cutoff may reference (by a USD
        asset path) the folder of an earlier run of its producer."""
        todo, seen = list(keys), set()
        while todo:
            entry = todo.pop()
            if entry in seen:
                continue
            seen.add(entry)
            if self.has(*entry):
                for inp in self.manifest(*entry).get("inputs", {}).values():
                    todo.append((inp["stage"], inp["key"]))
        return seen

    def referenced_keys(self) -> set[tuple[str, str]]:
        """(stage, key) pairs some world uses: named by its manifest, or
        reached from those through the artifacts' inputs."""
        refs = set()
        if not self.worlds.is_dir():
            return refs
        for world in self.worlds.iterdir():
            m = world / MANIFEST
            if m.is_file():
                for entry in json.loads(m.read_text()).get("artifacts", []):
                    refs.add((entry["stage"], entry["key"]))
        return self.closure(refs)

    def gc(self, wait: bool = True, dry_run: bool = False) -> list[Path]:
        """Remove every artifact folder that no world references, once no
        bake uses the store (wait: until then; else StoreBusy). dry_run:
        the folders that would go, nothing removed."""
        if not self.build.is_dir():
            return []
        if dry_run:  # removes nothing, so it waits for no bake (a running bake's new runs may show as removable)
            return self._gc(dry_run=True)
        with self._locked(fcntl.LOCK_EX, wait, f"worldbake: gc waits for the bakes using {self.build}"):
            return self._gc(dry_run)

    def _gc(self, dry_run: bool = False) -> list[Path]:
        keep = self.referenced_keys()
        # the units the kept runs used (a unit no kept run names is only a cache)
        keep_units = {(stage, key) for stage, run_key in keep if self.has(stage, run_key)
                      for key in self.manifest(stage, run_key).get("units", {}).values()}
        removed = []
        for root, kept in ((self.artifacts, keep), (self.units, keep_units)):
            if not root.is_dir():
                continue
            for stage_dir in sorted(root.iterdir()):
                for key_dir in sorted(stage_dir.iterdir()):
                    if (stage_dir.name, key_dir.name) not in kept:
                        if not dry_run:
                            shutil.rmtree(key_dir)
                        removed.append(key_dir)
                if not dry_run and not any(stage_dir.iterdir()):
                    stage_dir.rmdir()
        if not dry_run:
            self.clean_stale()
        return removed
