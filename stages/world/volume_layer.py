"""The forest sector volumes in the world: the farthest LOD of the
vegetation. The forest_volumes stage writes a layer of `over`s on the
vegetation's quadtree tiles, each adding a FarVolume (purpose proxy, a
`mip` variant set of UsdVol.Volume prims whose OpenVDBAsset fields density
and albedo name a .vdb per level, the EXR column runs beside it in
customData); the world composes that layer beside the vegetation's, so a
viewer that shows proxies sees every forest tile as one volume (Blender:
import with "proxy" purpose on)."""
from __future__ import annotations

from pipeline.contract import Input

SECTOR_VOLUMES = Input("sector_volumes", one_of=("forest_volumes.sectors",), optional=True,
                       description="one voxel volume per forest tile of the vegetation quadtree (purpose proxy): the "
                       "farthest LOD")
