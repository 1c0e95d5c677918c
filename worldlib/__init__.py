"""worldbake's domain libraries: what several stages share, by topic.

Stages import these like a library (scikit-image's topic modules are the
model); the engine (`pipeline/`) imports none of them.

- `flow`: D8 / multiple flow routing, Priority-Flood, drainage area (OpenCL, numpy reference)
- `render`: the offline OpenCL ray caster the baking stages share, its USD scene loader
- `volumes`: voxel volumes (dense EXR atlases, sparse column runs, OpenVDB)
- `terrain`: the terrain mesh lattice, DEM reading, hillshade, terrain statistics
- `images`: mip-mapped texture files; `materials`: UsdPreviewSurface materials
- `ground`, `plant_asset`: names several stages agree on (ground types, plant asset prims)
- `hashing`: counter-based random numbers (numpy twin of `cl/worldbake_hash.h`)
- `cl/`: OpenCL headers that kernels include (every key that uses one hashes it)
"""
