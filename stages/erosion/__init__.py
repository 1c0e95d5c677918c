"""erosion: thermal weathering and hydraulic erosion (virtual pipes, flux-form sediment) on the OpenCL device."""
from .stage import STAGE, ErosionParams

__all__ = ["STAGE", "ErosionParams"]
