"""hydrology: depressions, flow, rivers, lakes, wetness and moisture, and the USD water layer."""
from .stage import STAGE, HydrologyParams

__all__ = ["STAGE", "HydrologyParams"]
