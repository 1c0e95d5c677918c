"""Where a plant asset lives in USD, as the stages that write and read it agree.

The plants layer holds one prim per species under PLANTS_ROOT; the
vegetation layer's class prims (one per placed species, under
VEGETATION_PROTOTYPES) are what every point instancer's prototype inherits,
and the world binds the assets there.
"""

PLANTS_ROOT = "/Plants"
VEGETATION_PROTOTYPES = "/World/Vegetation/Prototypes"


def plant_asset_prim(species: str) -> str:
    """The prim of a species' plant asset in the plants layer."""
    return f"{PLANTS_ROOT}/{species}"


def prototype_prim(species: str) -> str:
    """The class prim of a species in the vegetation layer."""
    return f"{VEGETATION_PROTOTYPES}/{species}"
