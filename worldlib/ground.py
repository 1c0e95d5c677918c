"""The ground types: vegetation writes their splat weights, the world's
ground material reads them. One definition of the ground for every stage."""
import numpy as np

GROUND_TYPES = ("rock", "scree", "grass", "dry_grass", "mud", "snow")

# The splat weights' channel names, in GROUND_TYPES order.
SPLAT_CHANNELS = tuple(f"splat.{name}" for name in GROUND_TYPES)

# A colour per ground type (8-bit sRGB) for maps of the ground types (the
# report's); the ground material's albedo is stages/world/ground.py's.
GROUND_MAP_COLOURS = {"rock": (120, 112, 104), "scree": (168, 160, 150), "grass": (86, 130, 52),
                      "dry_grass": (176, 160, 92), "mud": (104, 82, 60), "snow": (240, 242, 248)}

# linear albedo per ground type (GROUND_TYPES order): typical measured albedos; the ground
# material's colours and the mean colour of each type's detail texture (worldlib.ground_detail)
GROUND_COLOURS = np.array([
    [0.20, 0.19, 0.18],  # rock
    [0.30, 0.28, 0.25],  # scree
    [0.07, 0.13, 0.04],  # grass
    [0.24, 0.21, 0.11],  # dry grass
    [0.12, 0.09, 0.06],  # mud
    [0.80, 0.82, 0.86],  # snow
], np.float32)
