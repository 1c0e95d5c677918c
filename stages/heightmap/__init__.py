"""heightmap: procedural terrain (fBm, ridged, domain warp, fault formation) or an imported DEM."""
from .stage import STAGE, HeightmapParams

__all__ = ["STAGE", "HeightmapParams"]
