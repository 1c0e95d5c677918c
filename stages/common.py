"""Names several stages agree on, held once.

Not a stage (the registry loads only packages): the artifact names and USD
prim paths by which one stage finds what another wrote. The engine
(`pipeline/`) knows none of them; a stage's key covers this file because the
stage imports it.
"""
from __future__ import annotations

# The final terrain height: from erosion when it runs, else the heightmap.
TERRAIN_SOURCES = ("erosion.height", "heightmap.height")

# The ground types' splat weights, as vegetation writes them and the world's
# ground material reads them (one definition of the ground for the world).
SPLAT_CHANNELS = ("splat.rock", "splat.scree", "splat.grass", "splat.dry_grass", "splat.mud", "splat.snow")

# The plant assets layer: one prim per species under PLANTS_ROOT.
PLANTS_ROOT = "/Plants"
# The vegetation layer's class prims, one per placed species, that every
# point instancer's prototype inherits; the world binds the assets there.
VEGETATION_PROTOTYPES = "/World/Vegetation/Prototypes"


def plant_asset_prim(species: str) -> str:
    """The prim of a species' plant asset in the plants layer."""
    return f"{PLANTS_ROOT}/{species}"


def prototype_prim(species: str) -> str:
    """The class prim of a species in the vegetation layer."""
    return f"{VEGETATION_PROTOTYPES}/{species}"
