"""landscape: the ground as Unreal landscape tiles (height EXR, 16-bit PNG with its range, weightmaps per ground type)."""
from .stage import STAGE, LandscapeParams

__all__ = ["STAGE", "LandscapeParams"]
