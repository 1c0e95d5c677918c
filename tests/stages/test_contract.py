"""One contract test over every registered stage (landlab's `_info` test is the model)."""
from __future__ import annotations

import inspect
import json
from pathlib import Path

import pydantic
import pytest

from pipeline.config import canonical_params
from pipeline.contract import Params, Stage
from pipeline.graph import build_graph
from pipeline.registry import all_stages

STAGES = all_stages()
STAGES_DIR = Path(__file__).resolve().parents[2] / "stages"


def test_expected_stages_are_registered():
    assert {"heightmap", "world"} <= set(STAGES)


def test_the_graph_of_all_stages_is_valid():
    build_graph(STAGES)


@pytest.mark.parametrize("name", sorted(STAGES))
def test_stage_declaration(name):
    stage: Stage = STAGES[name]
    assert stage.version >= 1 and stage.description
    assert stage.source_dir.resolve() == (STAGES_DIR / name).resolve()
    assert (stage.source_dir / "stage.py").is_file()
    for kernels in stage.source_dir.glob("*.cl"):  # every kernel file has its numpy reference beside it
        assert kernels.with_name("reference.py").is_file(), kernels
    assert list(inspect.signature(stage.run).parameters) == ["ctx", "inputs", "params"]
    for art in stage.outputs:
        assert art.name.startswith(f"{name}.") and art.description, art.name
        if art.kind == "grid":
            assert art.channels and art.units and art.file.endswith(".exr")
        if art.kind == "usd":
            assert art.file.endswith((".usda", ".usdc"))


@pytest.mark.parametrize("name", sorted(STAGES))
def test_stage_params_are_documented_bounded_and_canonical(name):
    stage = STAGES[name]
    assert issubclass(stage.params, Params)
    defaults = stage.params()  # the defaults are valid
    for fname, field in stage.params.model_fields.items():
        assert field.description, f"{name}.{fname} has no description"
        if field.annotation in (int, float):
            bounded = [m for m in field.metadata if any(getattr(m, a, None) is not None for a in ("ge", "gt", "le", "lt"))]
            assert bounded, f"{name}.{fname} has no valid range"
    text = canonical_params(defaults)
    assert stage.params.model_validate(json.loads(text)) == defaults  # round-trips through the key's JSON
    with pytest.raises(pydantic.ValidationError):
        stage.params.model_validate({"no_such_key": 1})
