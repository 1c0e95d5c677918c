"""The ground types: vegetation writes their splat weights, the world's
ground material reads them. One definition of the ground for every stage."""

GROUND_TYPES = ("rock", "scree", "grass", "dry_grass", "mud", "snow")

# The splat weights' channel names, in GROUND_TYPES order.
SPLAT_CHANNELS = tuple(f"splat.{name}" for name in GROUND_TYPES)

# A colour per ground type (8-bit sRGB) for maps of the ground types (the
# report's); the ground material's albedo is stages/world/ground.py's.
GROUND_MAP_COLOURS = {"rock": (120, 112, 104), "scree": (168, 160, 150), "grass": (86, 130, 52),
                      "dry_grass": (176, 160, 92), "mud": (104, 82, 60), "snow": (240, 242, 248)}
