"""The baked worlds and their history: what `worldbake worlds` lists and
the rule that keeps a bake from silently replacing another world's result.

A world is build/worlds/<name>/; its manifest records the config, the
variant and the --set overrides it was baked with. A bake publishes over
the world of the same name only when it was baked from the same config and
variant with the same overrides (a re-bake after editing the config file is
the same world, changed); otherwise it is refused before any stage runs,
unless the bake is given a world name of its own (`--name`) or told to
replace it (`--replace`).
"""
from __future__ import annotations

import json
import os

from .config import WorldConfig
from .errors import InputError
from .store import MANIFEST, Store


def world_manifest(store: Store, name: str) -> dict | None:
    path = store.worlds / name / MANIFEST
    return json.loads(path.read_text()) if path.is_file() else None


def list_worlds(store: Store) -> list[dict]:
    """Every baked world: name, config, variant, overrides, whether it has a
    world.usda, the stages it ran and when it was published."""
    rows = []
    if not store.worlds.is_dir():
        return rows
    for folder in sorted(store.worlds.iterdir()):
        manifest = world_manifest(store, folder.name)
        if manifest is None:
            continue
        rows.append({"world": folder.name, "config": manifest.get("config"), "variant": manifest.get("variant"),
                     "overrides": manifest.get("overrides", {}),
                     "world_usda": (folder / "world.usda").is_file(),
                     "report": (folder / "report.html").is_file(),
                     "stages": [a["stage"] for a in manifest.get("artifacts", [])],
                     "published": (folder / MANIFEST).stat().st_mtime})
    return rows


def _same_world(manifest: dict, config: WorldConfig) -> bool:
    return (manifest.get("overrides", {}) == json.loads(json.dumps(config.overrides))
            and os.path.normpath(manifest.get("config", "")) == os.path.normpath(config.path)
            and manifest.get("variant") == config.variant)


def check_replace(store: Store, configs: list[WorldConfig], replace: bool) -> None:
    """Refuse (InputError, exit 2, nothing written) a bake that would replace
    a world baked from another config, variant or other overrides."""
    if replace:
        return
    for config in configs:
        manifest = world_manifest(store, config.name)
        if manifest is None or _same_world(manifest, config):
            continue
        def shown(overrides: dict) -> str:
            return ", ".join(f"{k}={json.dumps(v)}" for k, v in overrides.items()) or "no overrides"
        raise InputError(
            f"world {config.name!r} in {store.worlds} was baked from {manifest.get('config')}"
            + (f" [variant {manifest['variant']}]" if manifest.get("variant") else "")
            + f" with {shown(manifest.get('overrides', {}))}; this bake ({config.path}"
            + (f" [variant {config.variant}]" if config.variant else "")
            + f" with {shown(config.overrides)}) would replace it: give this world a name of its own with "
            f"--name NAME (the earlier world is kept), or pass --replace")
