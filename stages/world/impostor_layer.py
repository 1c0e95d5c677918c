"""The impostors over the plant prototypes: in the world's root layer, each
species' prototype class prim (which references its plant asset) also
references the impostors stage's overs on that asset, more strongly, so
every instancer tile's (instanceable) prototype gains the `impostor` LOD,
the proxy-purpose Impostor prim beside the render-purpose meshes, the
cards textures and the switch distances. Neither the plants' nor the
impostors' files are changed."""
from __future__ import annotations

from pathlib import Path

from pipeline.contract import Input, RunContext
from worldlib.plant_asset import plant_asset_prim

IMPOSTOR_INPUT = Input("impostors", one_of=("impostors.layer",), optional=True,
                       description="the impostors' overs on the plant assets (impostors.usda)")


def bind_impostors(root_path: Path, bound: dict[str, str], placed: dict, impostors_layer: Path,
                   ctx: RunContext) -> list[str]:
    """For every species whose asset was bound (bound: species -> asset prim)
    and that the impostors layer holds: prepend its reference on the
    species' prototype class prim. Returns the species so bound."""
    from pxr import Sdf

    overs = Sdf.Layer.FindOrOpen(str(impostors_layer))
    layer = Sdf.Layer.FindOrOpen(str(root_path))
    done = []
    for species in sorted(bound):
        proto_path = placed.get("prototypes", {}).get(species)
        asset_prim = Sdf.Path(plant_asset_prim(species))
        if proto_path is None or not overs.GetPrimAtPath(asset_prim):
            continue
        spec = Sdf.CreatePrimInLayer(layer, Sdf.Path(proto_path))
        spec.referenceList.Prepend(Sdf.Reference(ctx.asset_path(impostors_layer), asset_prim))
        done.append(species)
    layer.Save()
    return done
