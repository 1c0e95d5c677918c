"""Import a USD file into Blender and write what came in as JSON:

    .venv-blender/bin/python tests/dcc/blender_scripts/import_report.py WORLD.usd(a|z) OUT.json

Imports proxy-purpose prims too. Writes objects per type, meshes, every image (file, found, pixels), every volume
(file, grids, error), each mesh object's materials and image nodes, the
point instancers, and the import's captured log (Blender's reports, CLOG,
USD diagnostics)."""
from __future__ import annotations

import os
import re
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bpy  # noqa: E402

import bl_common  # noqa: E402


def image_entry(img) -> dict:
    path = bpy.path.abspath(img.filepath, library=img.library) if img.filepath else ""
    entry = {"name": img.name, "file": path, "source": img.source, "packed": img.packed_file is not None}
    if img.source == "TILED":
        entry["packed"] = len(img.packed_files) > 0
        tiles = []
        for tile in img.tiles:
            f = path.replace("<UDIM>", str(tile.number))
            tiles.append({"number": tile.number, "file": f, "exists": os.path.isfile(f), "size": list(tile.size)})
        entry["tiles"] = tiles
        entry["found"] = bool(tiles) and all((t["exists"] or entry["packed"]) and t["size"][0] > 0 for t in tiles)
    else:
        try:
            img.reload()
            entry["size"] = list(img.size)
        except RuntimeError as e:
            entry["size"] = [0, 0]
            entry["error"] = str(e)
        entry["found"] = (entry["packed"] or os.path.isfile(path)) and entry["size"][0] > 0
    return entry


def volume_entry(obj) -> dict:
    vol = obj.data
    path = bpy.path.abspath(vol.filepath) if vol.filepath else ""
    loaded = vol.grids.load()
    return {"object": obj.name, "file": path, "exists": os.path.isfile(path), "loaded": bool(loaded),
            "error": vol.grids.error_message, "grids": sorted(g.name for g in vol.grids),
            "materials": [m.name for m in vol.materials if m]}


def material_entry(mat) -> dict:
    images, kinds = [], set()
    if mat is not None and mat.node_tree is not None:
        for node in mat.node_tree.nodes:
            kinds.add(node.bl_idname)
            if node.bl_idname == "ShaderNodeTexImage" and node.image is not None:
                images.append(node.image.name)
    return {"name": mat.name if mat else None, "images": sorted(images), "nodes": sorted(kinds)}


def instancer_entry(obj) -> dict:
    mods = [m for m in obj.modifiers if m.type == "NODES"]
    return {"object": obj.name, "type": obj.type, "points": len(obj.data.points) if obj.type == "POINTCLOUD" else None,
            "modifiers": [m.name for m in mods]}


def main() -> None:
    src, out = bl_common.args()[:2]
    bl_common.reset()
    # proxies too (the impostors beside LOD meshes, far volumes): everything the file holds that a user can show
    # Blender's default texture mode (packing): the only one that reads the textures inside a .usdz
    report = bl_common.import_usd(os.path.abspath(src), import_proxy=True, textures="IMPORT_PACK")
    objects = list(bpy.data.objects)
    types: dict[str, int] = {}
    for o in objects:
        types[o.type] = types.get(o.type, 0) + 1
    meshes = {}
    for o in objects:
        if o.type == "MESH":
            meshes[o.name] = {"materials": [material_entry(s.material) for s in o.material_slots],
                              "vertices": len(o.data.vertices), "faces": len(o.data.polygons),
                              "usd_path": o.get("usd_prim_path", "")}
    report.update({
        "object_types": types, "objects": len(objects), "meshes": meshes,
        "mesh_datablocks": len(bpy.data.meshes), "materials": len(bpy.data.materials),
        "images": [image_entry(i) for i in bpy.data.images if i.source in ("FILE", "TILED")],
        "volumes": [volume_entry(o) for o in objects if o.type == "VOLUME"],
        "instancers": [instancer_entry(o) for o in objects if o.type == "POINTCLOUD"
                       or any(m.type == "NODES" for m in o.modifiers)],
        "collections": len(bpy.data.collections),
    })
    problems = [line for line in report["log"] if re.search(r"\b(error|warning|missing|not found|cannot|failed)\b",
                                                             line, re.IGNORECASE)]
    report["problems"] = problems
    bl_common.write_json(out, report)


if __name__ == "__main__":
    main()
