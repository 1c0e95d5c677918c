"""What the USD water layer draws: river curves on the terrain mesh and lake outlines."""
from __future__ import annotations

import numpy as np

from . import rivers as rivers_mod
from .routing import Land

RIVER_MAX_RISE_M = 0.5  # a river segment may pass over ground this much above its higher end, no more


def river_curves(land: Land, riv: rivers_mod.Rivers, discharge: np.ndarray, mesh, lift_m: float):
    """Per river polyline: points (x, y, z), widths (never narrowing downstream),
    discharges and its Strahler order."""
    from worldlib.terrain.mesh import height_on_mesh

    cols, dx = land.shape[1], land.dx
    ox, oz = land.origin_m
    pts, ws, qs, orders = [], [], [], []
    surf = riv.surface.ravel()
    for seg in riv.curves:
        x = ox + (seg % cols + 0.5) * dx
        z = oz + (seg // cols + 0.5) * dx
        if mesh is not None:
            # the curve lies on the terrain mesh (lifted by river_lift_m), also where it ends on a lake's shore:
            # the coarse mesh can stand above a small lake's level, and a vertex at the level would be buried
            y = height_on_mesh(mesh, x, z) + lift_m
        else:
            y = surf[seg]
        if not np.isfinite(y).all():
            continue
        w = np.maximum.accumulate(riv.width.ravel()[seg])
        q = discharge.ravel()[seg]
        if mesh is not None:
            x, y, z, w, q = rivers_mod.follow_mesh(lambda px, pz: height_on_mesh(mesh, px, pz) + lift_m,
                                                   x, y, z, w, q, RIVER_MAX_RISE_M)
        pts.append(np.stack([x, y, z], 1))
        ws.append(w)
        qs.append(q)
        orders.append(int(riv.order.ravel()[seg[0]]))
    return pts, ws, qs, orders


def lake_outlines(land: Land, lake_id: np.ndarray, lake_level: np.ndarray, min_area_m2: float) -> list:
    """(lake id, level, mask grown by one cell onto data cells) of every lake of at least min_area_m2."""
    from scipy import ndimage

    rows, cols = land.shape
    lake_list = []
    for lid, sl in enumerate(ndimage.find_objects(lake_id), start=1):
        if sl is None:
            continue
        r0, r1 = max(sl[0].start - 1, 0), min(sl[0].stop + 1, rows)
        c0, c1 = max(sl[1].start - 1, 0), min(sl[1].stop + 1, cols)
        m = lake_id[r0:r1, c0:c1] == lid
        if m.sum() * land.cell_area < min_area_m2:
            continue
        grown = np.zeros((rows, cols), bool)
        grown[r0:r1, c0:c1] = ndimage.binary_dilation(m, structure=np.ones((3, 3), bool)) & land.data[r0:r1, c0:c1]
        lake_list.append((lid, float(np.nanmax(lake_level[r0:r1, c0:c1][m])), grown))
    return lake_list
