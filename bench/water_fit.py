"""Do the rivers and lakes of a bake sit on its terrain? (not part of `make test`)

    python -m bench.water_fit                 # the newest default bake under build/
    python -m bench.water_fit --world build/worlds/default

Reads the hydrology stage's water.usda and builds the terrain mesh the world
stage writes (worldlib/terrain/mesh.py, the same lattice) from the height
the hydrology stage read. Prints, over every river vertex: its height above
the mesh (share within 0.5 m, worst below and above); over every segment:
the highest ground between its ends (sampled every metre) above the higher
end (share over 1 m); and per lake of the map above the minimum area: whether
the USD has it and at which level against the map's spill level.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def curves(path: Path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    out, lakes = [], {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.BasisCurves):
            bc = UsdGeom.BasisCurves(prim)
            pts = np.array(bc.GetPointsAttr().Get(), np.float64)
            counts = np.array(bc.GetCurveVertexCountsAttr().Get())
            out.extend(np.split(pts, np.cumsum(counts)[:-1]))
        elif prim.IsA(UsdGeom.Mesh) and "/Lakes/" in str(prim.GetPath()):
            pts = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(), np.float64)
            lakes[prim.GetName()] = float(pts[:, 1].mean())
    return out, lakes


def fit(world: Path, max_vertices: int = 513) -> dict:
    from pipeline.exr import read_grid
    from pipeline.grid import Grid
    from worldlib.terrain.mesh import build_terrain_mesh, height_on_mesh

    manifest = json.loads((world / "manifest.json").read_text())
    build = world.parent.parent
    hyd = _artifact_dir(build, manifest, "hydrology")
    ero = _artifact_dir(build, manifest, "erosion") or _artifact_dir(build, manifest, "heightmap")
    g = read_grid(ero / "height.exr")
    h = g.channel(g.channels[0])
    mesh = build_terrain_mesh(Grid(np.asarray(h, np.float32), g.cell_size_m, ("height",), g.origin_m), max_vertices)
    rivers, lakes_usd = curves(hyd / "water.usda")
    above = []
    bumps = []
    for c in rivers:
        above.append(c[:, 1] - height_on_mesh(mesh, c[:, 0], c[:, 2]))
        a, b = c[:-1], c[1:]
        seg = np.linalg.norm(b[:, [0, 2]] - a[:, [0, 2]], axis=1)
        steps = int(np.ceil(seg.max())) + 1 if seg.size else 1
        f = np.linspace(0.0, 1.0, steps)[None, :]
        x = a[:, 0:1] + (b[:, 0:1] - a[:, 0:1]) * f
        z = a[:, 2:3] + (b[:, 2:3] - a[:, 2:3]) * f
        ground = height_on_mesh(mesh, x.ravel(), z.ravel()).reshape(x.shape).max(axis=1)
        bumps.append(ground - np.maximum(a[:, 1], b[:, 1]))
    above = np.concatenate(above) if above else np.zeros(0)
    bumps = np.concatenate(bumps) if bumps else np.zeros(0)
    lk = read_grid(hyd / "lakes.exr")
    lake_id = lk.channel("lake.id")
    level = lk.channel("lake.level")
    # vertices on a lake sit at its level (the lake's surface), not on the ground
    pts = np.concatenate(rivers) if rivers else np.zeros((0, 3))
    col = np.clip(((pts[:, 0] - g.origin_m[0]) / g.cell_size_m).astype(int), 0, h.shape[1] - 1)
    row = np.clip(((pts[:, 2] - g.origin_m[1]) / g.cell_size_m).astype(int), 0, h.shape[0] - 1)
    lvl = level[row, col]
    on_lake = np.isfinite(lvl) & (np.abs(pts[:, 1] - lvl) < 1e-3)
    params = json.loads((hyd / "manifest.json").read_text()).get("params", {})
    min_area = float(params.get("lake_min_area_m2", 20000.0))
    ids, counts = np.unique(lake_id[lake_id > 0].astype(np.int64), return_counts=True)
    big = ids[counts * g.cell_size_m ** 2 >= min_area]
    level_err = []
    missing = 0
    for lid in big:
        name = f"Lake_{lid:05d}"
        if name not in lakes_usd:
            missing += 1
            continue
        level_err.append(abs(lakes_usd[name] - float(np.nanmax(level[lake_id == lid]))))
    return {
        "river_vertices": int(above.size), "river_vertices_on_lakes": int(on_lake.sum()),
        "vertices_within_0.5m_share": float((np.abs(above) <= 0.5).mean()) if above.size else 0.0,
        "vertex_above_mesh_min_m": float(above.min()) if above.size else float("nan"),
        "vertex_above_mesh_max_m": float(above.max()) if above.size else float("nan"),
        "vertices_off_lakes_within_0.5m_share": float((np.abs(above[~on_lake]) <= 0.5).mean()) if above.size else 0.0,
        "vertex_off_lakes_above_mesh_min_m": float(above[~on_lake].min()) if (~on_lake).any() else float("nan"),
        "vertex_off_lakes_above_mesh_max_m": float(above[~on_lake].max()) if (~on_lake).any() else float("nan"),
        "segments": int(bumps.size),
        "segments_over_ground_1m_share": float((bumps > 1.0).mean()) if bumps.size else float("nan"),
        "segment_ground_above_higher_end_max_m": float(bumps.max()) if bumps.size else float("nan"),
        "lakes_in_map_above_min_area": int(big.size), "lakes_missing_in_usd": missing,
        "lake_level_error_max_m": float(max(level_err)) if level_err else 0.0,
    }


def _artifact_dir(build: Path, manifest: dict, stage: str) -> Path | None:
    for a in manifest.get("artifacts", []):
        if a.get("stage") == stage:
            return build / "artifacts" / stage / a["key"]
    return None


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--world", default="build/worlds/default")
    args = ap.parse_args()
    for k, v in fit(Path(args.world)).items():
        print(f"{k:40s} {v}")


if __name__ == "__main__":
    main()
