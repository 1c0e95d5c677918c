"""Species tables the plants stage refuses before anything runs, naming the
species and the key."""
import math

import pydantic
import pytest

from stages.plants.stage import PlantsParams


@pytest.mark.parametrize("table, key", [
    ({"preset": "conifer", "leaf": {"length": math.nan}}, "length"),
    ({"preset": "conifer", "lsystem": {"tropism": [0.0, math.inf, 0.0]}}, "tropism"),
    ({"preset": "broadleaf", "lsystem": {"constants": {"shrink": math.nan}}}, "shrink"),
    ({"preset": "shrub", "lsystem": {"axiom": "  "}}, "axiom"),
    ({"preset": "shrub", "foliage": {"leaves_per_kard": 3}}, "leaves_per_kard"),
    ({"preset": "meadow_flower", "foliage": {"flower_color": [0.5, math.nan, 0.1]}}, "flower_color"),
])
def test_bad_species_tables_are_refused(table, key):
    with pytest.raises(pydantic.ValidationError) as e:
        PlantsParams.model_validate({"species": {"badtree": table}, "build": ["badtree"]})
    text = str(e.value)
    assert "badtree" in text and key in text
