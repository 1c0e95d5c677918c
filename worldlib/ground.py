"""The ground types: vegetation writes their splat weights, the world's
ground material reads them. One definition of the ground for every stage."""

GROUND_TYPES = ("rock", "scree", "grass", "dry_grass", "mud", "snow")

# The splat weights' channel names, in GROUND_TYPES order.
SPLAT_CHANNELS = tuple(f"splat.{name}" for name in GROUND_TYPES)
