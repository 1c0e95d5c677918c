"""The forest sector volumes in the world: the farthest LOD of the
vegetation. The forest_volumes stage writes a layer of `over`s on the
vegetation's quadtree tiles, each adding a FarVolume (purpose proxy, a
`mip` variant set of UsdVol.Volume prims over EXR Z-slice atlases); the
world composes that layer beside the vegetation's, so a viewer that shows
proxies sees every forest tile as one volume."""
from __future__ import annotations

from pipeline.contract import Input

SECTOR_VOLUMES = Input("sector_volumes", one_of=("forest_volumes.sectors",), optional=True,
                       description="one voxel volume per forest tile of the vegetation quadtree (purpose proxy): the "
                       "farthest LOD")
