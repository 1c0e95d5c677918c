"""Discovery of stages: every subpackage of `stages` that exports STAGE."""
from __future__ import annotations

import functools
import importlib
import pkgutil

from .contract import Stage


@functools.lru_cache(maxsize=1)
def all_stages() -> dict[str, Stage]:
    import stages

    found: dict[str, Stage] = {}
    for info in sorted(pkgutil.iter_modules(stages.__path__), key=lambda m: m.name):
        if not info.ispkg:
            continue
        module = importlib.import_module(f"stages.{info.name}")
        stage = getattr(module, "STAGE", None)
        if not isinstance(stage, Stage):
            raise TypeError(f"stages/{info.name}/__init__.py must export STAGE, a pipeline.contract.Stage")
        if stage.name != info.name:
            raise TypeError(f"stages/{info.name} declares the name {stage.name!r}; a stage's name is its folder's")
        found[stage.name] = stage
    return found
