"""Shared, session-scoped builds for the plants tests (each preset is built
once at its default size; everything else uses small L-systems)."""
import pytest

from pipeline.opencl import get_cl

from stages.plants.plant import Settings, build_plant
from stages.plants.stage import PRESETS

SEED = 20261123


@pytest.fixture(scope="session")
def preset_builds():
    """Every preset at full size, world seed SEED, default settings."""
    return {name: build_plant(name, spec, SEED, Settings(cl=get_cl())) for name, spec in sorted(PRESETS.items())}


@pytest.fixture(scope="session")
def small_run(tmp_path_factory):
    """The stage run on helpers.SMALL, shared by the stage and the looks tests."""
    from tests.stages.plants.helpers import SMALL, run_stage

    return run_stage(tmp_path_factory.mktemp("plants"), SMALL)
