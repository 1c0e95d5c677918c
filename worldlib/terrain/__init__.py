"""Terrain: the mesh lattice stages share, DEM files, hillshade, statistics."""

# The final terrain height: from erosion when it runs, else the heightmap.
TERRAIN_SOURCES = ("erosion.height", "heightmap.height")
# The ground things stand on: the terrain with the river beds carved (hydrology), else the terrain.
GROUND_SOURCES = ("hydrology.ground",) + TERRAIN_SOURCES
