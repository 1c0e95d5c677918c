"""Parts of a stage run that a later run of the same stage may reuse
(trimesh-style content-hash caching, one level below the stage's key).

A stage's key changes when any of its inputs does: a plants layer with one
species changed gives the impostors stage a new key, yet the other species'
impostors depend only on their own plant. A stage names such a part a unit
and describes what it depends on (`material`: the content digest of what
it reads, the params it uses); the engine keys it with the stage's code
(name, version, source digest, libraries, seed) and keeps its files in

    build/units/<stage>/<unit key>/   the files and unit.json (written last), and
                                      run.json: the seconds of the run that made it

so a run whose unit key exists links the files instead of making them.
unit.json is content, the same every bake; run times go to run.json, a
run record (pipeline.store.RUN_RECORDS).

Trust: unit.json lists every file's sha256 and is checked on restore; a
unit with a missing or altered file is made again, never used. Files made
in a unit must carry only `Unit.provenance` (the unit's key, not the run's),
so a run that reuses a unit writes the same bytes as a clean run. The run's
manifest names the units it used; gc keeps those and removes the rest.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any

from .store import UNIT_MANIFEST, UNIT_RUN_RECORD, sha256_file

UNIT_KEY_LENGTH = 20


def _link_or_copy(src: Path, dst: Path) -> None:
    """A hard link (artifacts are never modified in place), a copy across
    file systems."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


class Unit:
    """One reusable part of a run. Without a store (a stage run outside a
    bake, as in the stage tests) it is never cached and save() keeps nothing."""

    def __init__(self, name: str, key: str, provenance: dict[str, Any], folder: Path | None, tmp: Path | None):
        self.name, self.key, self.provenance = name, key, provenance
        self.folder, self._tmp = folder, tmp
        self.reused = False
        self.record: dict[str, Any] = {}  # restored: the run figures of the run that made it (run.json)

    def restore(self, dest: Path) -> Any | None:
        """Link the unit's files into dest and return the result it saved;
        None when there is no whole, unaltered unit of this key."""
        if self.folder is None or not self.folder.exists():
            return None
        if not (self.folder / UNIT_MANIFEST).is_file():  # a folder without it is no unit: made again, then saved
            print(f"worldbake: unit {self.folder} is incomplete (no {UNIT_MANIFEST}); making it again",
                  file=sys.stderr, flush=True)
            return None
        try:
            saved = json.loads((self.folder / UNIT_MANIFEST).read_text())
            files = saved["files"]
            for rel, digest in files.items():
                if sha256_file(self.folder / rel) != digest:
                    raise ValueError(f"{rel} does not match its digest")
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"worldbake: unit {self.folder} is damaged ({e}); making it again", file=sys.stderr, flush=True)
            shutil.rmtree(self.folder, ignore_errors=True)
            return None
        try:
            for rel in files:
                _link_or_copy(self.folder / rel, dest / rel)
        except OSError:  # gone meanwhile (gc, or a concurrent bake replacing a damaged unit): make it
            for rel in files:  # links to the unit's files must not be written through
                (dest / rel).unlink(missing_ok=True)
            return None
        self.reused = True
        try:  # a run record: missing or unreadable, the unit is still whole
            self.record = json.loads((self.folder / UNIT_RUN_RECORD).read_text())
        except (OSError, ValueError):
            self.record = {}
        return saved["result"]

    def save(self, src: Path, files: list[str], result: Any, record: dict[str, Any] | None = None) -> None:
        """Keep `files` (paths relative to src) and the JSON-able result
        under the unit's key: written to a temporary folder, renamed when whole.
        `result` is content (the same every run: no run times); `record`,
        the run's figures (seconds), goes to run.json, a run record
        (pipeline.store.RUN_RECORDS), and comes back as `Unit.record`."""
        if self.folder is None or (self.folder / UNIT_MANIFEST).is_file():
            return
        work = self._tmp / f"unit-{self.folder.parent.name}-{self.key}-{os.getpid()}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        try:
            digests = {}
            for rel in sorted(files):
                _link_or_copy(src / rel, work / rel)
                digests[rel] = sha256_file(work / rel)
            if record is not None:
                (work / UNIT_RUN_RECORD).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
            (work / UNIT_MANIFEST).write_text(json.dumps(
                {"unit": self.name, "key": self.key, "provenance": self.provenance, "files": digests,
                 "result": result}, indent=1, sort_keys=True) + "\n")
            self.folder.parent.mkdir(parents=True, exist_ok=True)
            if (self.folder / UNIT_MANIFEST).is_file():  # a concurrent bake made it meanwhile: keep theirs
                return
            shutil.rmtree(self.folder, ignore_errors=True)  # a half folder no one completes
            try:
                os.rename(work, self.folder)
            except OSError:
                if not (self.folder / UNIT_MANIFEST).is_file():  # not a concurrent twin that won the race
                    raise
        finally:
            shutil.rmtree(work, ignore_errors=True)


class Units:
    """The units of one stage run: keys from the stage's code material and
    each unit's own; `used` names every unit the run asked for (its manifest
    keeps them from gc)."""

    def __init__(self, root: Path | None, tmp: Path | None, stage: str, code_material: dict[str, Any]):
        self.root, self.tmp, self.stage = root, tmp, stage
        self.code_material = code_material
        self.used: dict[str, str] = {}

    def _key(self, name: str, material: Any) -> str:
        text = json.dumps({"code": self.code_material, "unit": name, "material": material}, sort_keys=True,
                          separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:UNIT_KEY_LENGTH]

    def saved(self, name: str, material: Any) -> bool:
        """Whether that unit is in the store, complete (without asking for it: the run may still not use it)."""
        return self.root is not None and (self.root / self.stage / self._key(name, material) / UNIT_MANIFEST).is_file()

    def unit(self, name: str, material: Any) -> Unit:
        if name in self.used:
            raise ValueError(f"stage {self.stage}: unit {name!r} asked for twice in one run")
        key = self._key(name, material)
        self.used[name] = key
        provenance = {"stage": self.stage, "version": self.code_material.get("version"), "unit": name, "unit_key": key,
                      "seed": self.code_material.get("seed")}
        folder = self.root / self.stage / key if self.root is not None else None
        return Unit(name, key, provenance, folder, self.tmp)
