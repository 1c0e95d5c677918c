"""vegetation: where each species grows on the terrain, placed without overlap, instanced in USD."""
from .params import SpeciesEcology, VegetationParams
from .stage import STAGE

__all__ = ["STAGE", "SpeciesEcology", "VegetationParams"]
