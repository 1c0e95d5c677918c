"""The report's map of rivers and lakes as the composed world.usda holds
them (what a DCC tool shows, not the grids): the river and lake meshes under
the water prim (rivers at least a pixel wide), over the terrain's hillshade;
and the table of river width against drainage area. Declared in
STAGE.report (pipeline.contract.DrawnMap, ReportTable)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.contract import Drawn, MapFrame, Table

RIVER_RGB = (40, 110, 220)
LAKE_RGB = (30, 80, 190)


def draw_water(world_usda: Path, frame: MapFrame) -> Drawn:
    """Rivers and lakes of the composed world over the frame's relief."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world_usda))
    base = frame.light
    rgb = (np.stack([base] * 3, -1) * np.array([200, 200, 190]) * 0.5 + np.array([110, 110, 100])).clip(0, 255)
    lake_mask = np.zeros(base.shape, bool)
    river_mask = np.zeros(base.shape, bool)
    yy, xx = np.mgrid[0:base.shape[0], 0:base.shape[1]]
    px, (ox, oz) = frame.metres_per_px, frame.origin_m
    centres = (ox + (xx + 0.5) * px, oz + (yy + 0.5) * px)  # x, z of each pixel's centre
    n_curves = n_lakes = 0
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
        elif prim.IsA(UsdGeom.BasisCurves):
            n_curves += _draw_curves(river_mask, UsdGeom.BasisCurves(prim), frame, centres)
        elif prim.IsA(UsdGeom.Mesh) and "/rivers/" in str(prim.GetPath()).lower():
            n_curves += _draw_ribbon(river_mask, UsdGeom.Mesh(prim), frame)
        elif prim.IsA(UsdGeom.Mesh) and "water" in str(prim.GetPath()).lower():
            _draw_mesh(lake_mask, UsdGeom.Mesh(prim), frame)
            n_lakes += 1
    rgb[river_mask] = RIVER_RGB
    rgb[lake_mask] = LAKE_RGB
    return Drawn(rgb.astype(np.uint8), (
        (RIVER_RGB, f"rivers ({n_curves} river surface quads or curves, at least a pixel wide)"),
        (LAKE_RGB, f"lakes ({n_lakes} lake meshes)")))


def _draw_ribbon(mask: np.ndarray, mesh, frame: MapFrame) -> int:
    """Mark the pixels under a river mesh's quads, and the pixels along each
    quad's centreline so a river narrower than a pixel still shows; returns the quads."""
    _draw_mesh(mask, mesh, frame)
    pts = np.asarray(mesh.GetPointsAttr().Get() or [], np.float64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64).reshape(-1, 4)
    if not len(idx):
        return 0
    (ox, oz), px = frame.origin_m, frame.metres_per_px
    a = 0.5 * (pts[idx[:, 0]] + pts[idx[:, 1]])
    b = 0.5 * (pts[idx[:, 2]] + pts[idx[:, 3]])
    for f in np.linspace(0.0, 1.0, 5):
        x, z = a[:, 0] + f * (b[:, 0] - a[:, 0]), a[:, 2] + f * (b[:, 2] - a[:, 2])
        c, r = np.floor((x - ox) / px).astype(np.int64), np.floor((z - oz) / px).astype(np.int64)
        ok = (r >= 0) & (r < mask.shape[0]) & (c >= 0) & (c < mask.shape[1])
        mask[r[ok], c[ok]] = True
    return int(len(idx))


def width_tables(world_usda: Path) -> tuple[Table, ...]:
    """Bankfull width against drainage area, as the water layer records it
    (customData worldbake:width_by_area on /World/Water/Rivers)."""
    from pxr import Usd

    from .water_usd import WIDTH_TABLE_KEY

    stage = Usd.Stage.Open(str(world_usda))  # held: a prim expires with its stage
    prim = stage.GetPrimAtPath("/World/Water/Rivers")
    data = prim.GetCustomDataByKey(WIDTH_TABLE_KEY) if prim else None
    if not data:
        return ()
    cols = {k: list(v) for k, v in data.items()}
    rows = []
    for i in range(len(cols["cells"])):
        hi = cols["area_km2_to"][i]
        rows.append((f"{cols['area_km2_from'][i]:g} - {hi:g}" if hi >= 0 else f">= {cols['area_km2_from'][i]:g}",
                     int(cols["cells"][i]), round(cols["width_min_m"][i], 2), round(cols["width_median_m"][i], 2),
                     round(cols["width_max_m"][i], 2)))
    return (Table(("drainage area (km^2)", "network cells", "least width (m)", "median width (m)",
                   "largest width (m)"), tuple(rows),
                  note="bankfull width w = a Q_bf^b over the channel network's cells (the hydrology stage's "
                  "hydraulic geometry); rivers narrower than river_mesh_min_width_m have no surface mesh"),)


def _draw_curves(mask: np.ndarray, curves, frame: MapFrame, centres: tuple[np.ndarray, np.ndarray]) -> int:
    """Mark the pixels within each curve's half width (at least a pixel
    either side, to stay visible) of its segments; returns the curves."""
    px, (ox, oz) = frame.metres_per_px, frame.origin_m
    cx, cz = centres
    pts = np.asarray(curves.GetPointsAttr().Get() or [], np.float64)
    counts = list(curves.GetCurveVertexCountsAttr().Get() or [])
    widths = np.asarray(curves.GetWidthsAttr().Get() or [], np.float64)
    start = 0
    for n in counts:
        seg = pts[start:start + n]
        wseg = widths[start:start + n] if len(widths) == len(pts) else np.full(n, widths[0] if len(widths) else px)
        for i in range(n - 1):
            a, b = seg[i], seg[i + 1]
            steps = max(2, int(np.hypot(b[0] - a[0], b[2] - a[2]) / (0.5 * px)) + 1)
            for t in np.linspace(0, 1, steps):
                x, z = a[0] + t * (b[0] - a[0]), a[2] + t * (b[2] - a[2])
                r = max(0.5 * wseg[i], 1.0 * px)
                c0, r0 = int((x - ox) / px), int((z - oz) / px)
                rr = int(r / px) + 1
                sl = (slice(max(r0 - rr, 0), r0 + rr + 1), slice(max(c0 - rr, 0), c0 + rr + 1))
                mask[sl] |= (cx[sl] - x) ** 2 + (cz[sl] - z) ** 2 <= r * r
        start += n
    return len(counts)


def _draw_mesh(mask: np.ndarray, mesh, frame: MapFrame) -> None:
    """Mark the pixels inside the mesh's faces (fan triangles)."""
    pts = np.asarray(mesh.GetPointsAttr().Get() or [], np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
    start = 0
    for n in counts:
        face = pts[idx[start:start + n]]
        for j in range(1, n - 1):
            _fill_triangle(mask, face[0], face[j], face[j + 1], *frame.origin_m, frame.metres_per_px)
        start += n


def _fill_triangle(mask: np.ndarray, a, b, c, ox: float, oz: float, px: float) -> None:
    """Mark the map pixels whose centres lie in the triangle (x, z of a, b, c)."""
    xs = np.array([a[0], b[0], c[0]])
    zs = np.array([a[2], b[2], c[2]])
    c0, c1 = max(int((xs.min() - ox) / px), 0), min(int((xs.max() - ox) / px) + 1, mask.shape[1])
    r0, r1 = max(int((zs.min() - oz) / px), 0), min(int((zs.max() - oz) / px) + 1, mask.shape[0])
    if c0 >= c1 or r0 >= r1:
        return
    yy, xx = np.mgrid[r0:r1, c0:c1]
    x, z = ox + (xx + 0.5) * px, oz + (yy + 0.5) * px

    def edge(p, q):
        return (q[0] - p[0]) * (z - p[1]) - (q[1] - p[1]) * (x - p[0])
    p0, p1, p2 = (xs[0], zs[0]), (xs[1], zs[1]), (xs[2], zs[2])
    e0, e1, e2 = edge(p0, p1), edge(p1, p2), edge(p2, p0)
    inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
    mask[r0:r1, c0:c1] |= inside
