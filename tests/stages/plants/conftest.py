"""Shared, session-scoped builds for the plants tests (each preset is built
once at its default size; everything else uses small L-systems)."""
import pytest

from stages.plants.plant import Settings, build_plant
from stages.plants.stage import PRESETS

SEED = 20261123


@pytest.fixture(scope="session")
def preset_builds():
    """Every preset at full size, world seed SEED, default settings."""
    return {name: build_plant(name, spec, SEED, Settings()) for name, spec in sorted(PRESETS.items())}
