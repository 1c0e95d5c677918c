"""The ground's detail layer in world pictures: where a pixel sees the
terrain, its albedo and normal are the splat-weighted triplanar blend of the
ground types' detail textures (worldlib.ground_detail.blend), so a view from
2 m shows blades, stones and cracks instead of the 1 m bake's smear.

Read from USD as a DCC would: the ground material's detail NodeGraph (a
NodeGraph with outputs <type>_albedo, <type>_normal and <type>_weight for
every ground type; stages/world/ground_near.py authors it): each type's
albedo (its sourceColorSpace) and normal texture (its scale and bias), its
tile size (1 / the scale of the UsdTransform2d feeding it, st_detail being
metres), and the texture and channel each weight reads, through the primvar
its st names. The terrain pixels are found from the render's depth: the hit
point lies on the ground mesh (worldlib.terrain.mesh.height_on_mesh), within
the pixel's footprint.

    img = with_ground_detail(img, world_usda, camera, width, height)
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from worldlib import ground_detail
from worldlib.ground import GROUND_TYPES


@dataclass
class GroundDetailView:
    layer: ground_detail.DetailLayer
    splat: np.ndarray  # (rows, cols, types) from the weight textures, row 0 at st t = 1
    st_affine: np.ndarray  # (3, 2): [x, z, 1] @ st_affine = st of the splat textures' primvar
    lattice: object  # a TerrainMesh-like (points, normals, lattice_shape) of the ground mesh
    covered: object = None  # (top (rows, cols), x0, z0, cell_m): the highest other mesh (water) over the ground

    def weights(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        st = np.stack([x, z, np.ones_like(x)], -1) @ self.st_affine
        rows, cols = self.splat.shape[:2]
        return ground_detail.splat_bilinear(self.splat, (1.0 - st[:, 1]) * rows - 0.5, st[:, 0] * cols - 0.5)

    def ground_pixels(self, img, camera, width: int, height: int):
        """(pixel mask, hit points (m, 3), view directions (m, 3), footprint (m,) m)."""
        from worldlib.terrain.mesh import height_on_mesh

        rec = camera.frame(width, height).astype(np.float64)
        eye, fwd, right, up = rec[0:3], rec[3:6], rec[6:9], rec[9:12]
        if rec[12] > 0.5:
            return np.zeros((height, width), bool), None, None, None
        x = 2.0 * (np.arange(width) + 0.5) / width - 1.0
        y = 1.0 - 2.0 * (np.arange(height) + 0.5) / height
        depth = img.depth.astype(np.float64)
        mask = np.isfinite(depth) & (img.alpha > 0.999)
        pr, pc = np.nonzero(mask)
        d = fwd + x[pc, None] * right + y[pr, None] * up
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        p = eye + d * depth[pr, pc, None]
        pix = 2.0 * np.linalg.norm(up) / height  # radians a pixel spans (at the centre)
        P = self.lattice.points
        inside = ((p[:, 0] >= P[:, 0].min()) & (p[:, 0] <= P[:, 0].max()) & (p[:, 2] >= P[:, 2].min())
                  & (p[:, 2] <= P[:, 2].max()))
        on = np.zeros(len(p), bool)
        ground_y = np.full(len(p), np.nan)
        ground_y[inside] = height_on_mesh(self.lattice, p[inside, 0], p[inside, 2])
        on[inside] = np.abs(p[inside, 1] - ground_y[inside]) < 0.02 + 1.5 * depth[pr, pc][inside] * pix
        # and facing as the ground does there (the foot of a trunk or a wall is as low, but not as turned)
        nr, nc = self.lattice.lattice_shape
        P3 = P.reshape(nr, nc, 3)
        ci = np.interp(p[on, 0], P3[0, :, 0], np.arange(nc))
        ri = np.interp(p[on, 2], P3[:, 0, 2], np.arange(nr))
        mesh_n = ground_detail.splat_bilinear(self.lattice.normals.reshape(nr, nc, 3).astype(np.float64), ri, ci)
        pixel_n = img.normal[pr[on], pc[on]].astype(np.float64)
        cos = (mesh_n * pixel_n).sum(1) / np.maximum(
            np.linalg.norm(mesh_n, axis=1) * np.linalg.norm(pixel_n, axis=1), 1e-12)
        on[np.flatnonzero(on)[cos < 0.9]] = False
        if self.covered is not None:  # water lies on its bed, as low and as turned as the ground: by where it is
            top, x0, z0, cell = self.covered
            i = np.flatnonzero(on)
            r = np.clip(((p[i, 2] - z0) / cell).astype(np.int64), 0, top.shape[0] - 1)
            c = np.clip(((p[i, 0] - x0) / cell).astype(np.int64), 0, top.shape[1] - 1)
            with np.errstate(invalid="ignore"):  # where the other surface is above the ground, the ray meets it first
                on[i[top[r, c] >= ground_y[i] - 0.005]] = False
        mask[pr[~on], pc[~on]] = False
        footprint = depth[pr, pc][on] * pix
        return mask, p[on], d[on], footprint

    def apply(self, img, camera, width: int, height: int):
        """img (a render Image) with the detail layer's albedo and normal on its ground pixels."""
        mask, p, d, footprint = self.ground_pixels(img, camera, width, height)
        if not mask.any():
            return img
        n = img.normal[mask].astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        cos = np.maximum(np.abs((n * d).sum(1)), 0.05)
        # the pixel's footprint on the surface: stretched by the view's slant (its geometric mean: the
        # larger side blurs, the smaller aliases)
        albedo, normal = ground_detail.blend(self.layer, self.weights(p[:, 0], p[:, 2]), p, n,
                                             footprint / np.sqrt(cos))
        a = img.albedo.copy()
        nr = img.normal.copy()
        a[mask] = albedo * img.alpha[mask][:, None]
        nr[mask] = normal
        return replace(img, albedo=a, normal=nr)


def _texture_input(shader, name: str):
    from pxr import UsdShade

    inp = shader.GetInput(name)
    if inp and inp.HasConnectedSource():
        return UsdShade.Shader(inp.GetConnectedSource()[0].GetPrim())
    return None


def _read_texture(tex) -> np.ndarray:
    from .usd_asset import read_image

    asset = tex.GetInput("file").Get()
    path = asset.resolvedPath or str(Path(tex.GetInput("file").GetAttr().GetPropertyStack()[0].layer.realPath).parent
                                     / asset.path)
    cs = tex.GetInput("sourceColorSpace")
    rgb = read_image(path, str(cs.Get()) if cs and cs.Get() else "auto")[..., :3].astype(np.float64)
    scale, bias = tex.GetInput("scale"), tex.GetInput("bias")
    if scale and scale.Get() is not None:
        rgb = rgb * np.asarray(scale.Get(), np.float64)[:3]
    if bias and bias.Get() is not None:
        rgb = rgb + np.asarray(bias.Get(), np.float64)[:3]
    return rgb


def _source(graph, output: str):
    """(shader, its output name) an output of the graph connects to."""
    from pxr import UsdShade

    out = graph.GetOutput(output)
    if not out or not out.HasConnectedSource():
        return None, None
    src, name, _ = out.GetConnectedSource()
    return UsdShade.Shader(src.GetPrim()), name


def _st_affine(mesh, primvar: str) -> np.ndarray | None:
    """Least squares [x, z, 1] -> the primvar's st over the mesh's vertices;
    None unless the primvar is an affine map of x and z (a planar terrain st)."""
    from pxr import UsdGeom

    pv = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(primvar)
    pts = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), np.float64)
    if not pv or pv.Get() is None or len(pv.Get()) != len(pts):
        return None
    st = np.asarray(pv.Get(), np.float64)
    A = np.stack([pts[:, 0], pts[:, 2], np.ones(len(pts))], -1)
    coef = np.linalg.lstsq(A, st, rcond=None)[0]
    return coef if np.abs(A @ coef - st).max() < 1e-4 else None


def _splat_from(graph, mesh) -> tuple[np.ndarray, np.ndarray] | None:
    planes, affine, cache = [], None, {}
    for t in GROUND_TYPES:
        tex, channel = _source(graph, f"{t}_weight")
        if tex is None or channel not in ("r", "g", "b"):
            return None
        key = str(tex.GetPath())
        if key not in cache:
            cache[key] = _read_texture(tex)
            reader = _texture_input(tex, "st")
            var = reader.GetInput("varname").Get() if reader and reader.GetInput("varname") else "st"
            affine = _st_affine(mesh, str(var))
            if affine is None:
                return None
        planes.append(cache[key][..., "rgb".index(channel)])
    return np.stack(planes, -1).astype(np.float32), affine


def load_detail_view(world_usda: str | Path) -> GroundDetailView | None:
    """The detail layer of the world's ground, or None where its material has none."""
    from pxr import Usd, UsdGeom, UsdShade

    from worldlib.render.usd_asset import mute_dcc_selection
    from worldlib.terrain.mesh import weld_lattice

    stage = Usd.Stage.Open(str(world_usda))
    mute_dcc_selection(stage)  # the terrain at its full LOD (dcc.usdc may choose coarser tiles)
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        if not material:
            continue
        graphs = [UsdShade.NodeGraph(c) for c in material.GetPrim().GetChildren() if c.IsA(UsdShade.NodeGraph)
                  and not c.IsA(UsdShade.Material)]
        graph = next((g for g in graphs if all(g.GetOutput(f"{t}_weight") for t in GROUND_TYPES)), None)
        if graph is None:
            continue
        splat = _splat_from(graph, prim)
        if splat is None:
            return None
        textures, tile = {}, {}
        for t in GROUND_TYPES:
            albedo, _ = _source(graph, f"{t}_albedo")
            normal, _ = _source(graph, f"{t}_normal")
            xf = _texture_input(albedo, "st")
            scale = xf.GetInput("scale").Get() if xf and xf.GetInput("scale") else None
            tile[t] = 1.0 / float(scale[0]) if scale is not None else 1.0
            textures[t] = (_read_texture(albedo), 0.5 * _read_texture(normal) + 0.5)  # from_textures takes 0..1
        # the terrain's tiles (stages/world/terrain_tiles.py): the meshes beside it bound to the same material
        tiles = [p for p in prim.GetParent().GetChildren() if p.IsA(UsdGeom.Mesh) and
                 UsdShade.MaterialBindingAPI(p).ComputeBoundMaterial()[0].GetPath() == material.GetPath()]
        pts = [np.asarray(UsdGeom.Mesh(p).GetPointsAttr().Get(), np.float32) for p in tiles]
        normals = [UsdGeom.Mesh(p).GetNormalsAttr().Get() for p in tiles]
        if any(n is None or len(n) != len(q) for n, q in zip(normals, pts)):
            return None
        lattice = weld_lattice(np.concatenate(pts), np.concatenate([np.asarray(n, np.float32) for n in normals]))
        if lattice is None:  # not every tile at its full LOD
            return None
        return GroundDetailView(ground_detail.DetailLayer.from_textures(textures, tile), splat[0], splat[1], lattice,
                                covered_by_other_meshes(stage, {p.GetPath() for p in tiles}, lattice.points))
    return None


def covered_by_other_meshes(stage, terrain: set, points: np.ndarray, max_cells: int = 4096):
    """How high meshes other than the terrain's (terrain: their prim paths) (water surfaces, ...; not
    plant prototypes under a PointInstancer, not invisible) lie over the
    terrain's footprint: (top, x0, z0, cell_m), top the highest of their
    triangles at each texel centre (NaN where none; a texel at least the
    terrain's width / max_cells); None when there are none."""
    from pxr import Usd, UsdGeom

    x0, z0 = float(points[:, 0].min()), float(points[:, 2].min())
    size = max(float(np.ptp(points[:, 0])), float(np.ptp(points[:, 2])), 1e-3)
    cell = max(size / max_cells, 0.25)
    n = int(np.ceil(size / cell)) + 1
    mask = np.full((n, n), np.nan, np.float32)
    cache = UsdGeom.XformCache()
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    found = False
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer) or (prim.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(prim).ComputeVisibility()
                                                 == UsdGeom.Tokens.invisible):
            it.PruneChildren()
            continue
        if not prim.IsA(UsdGeom.Mesh) or prim.GetPath() in terrain:
            continue
        mesh = UsdGeom.Mesh(prim)
        pts, counts, idx = mesh.GetPointsAttr().Get(), mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()
        if pts is None or counts is None or idx is None or len(pts) == 0:
            continue
        m = np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)
        p = np.asarray(pts, np.float64) @ m[:3, :3] + m[3, :3]
        counts, idx = np.asarray(counts), np.asarray(idx)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tris = [np.stack([idx[starts[f]], idx[starts[f] + k], idx[starts[f] + k + 1]], -1)
                for k in range(1, int(counts.max()) - 1) for f in [np.flatnonzero(counts > k + 1)]]
        for t in np.concatenate(tris) if tris else []:
            _fill_triangle(mask, p[t], x0, z0, cell)
        found = True
    return (mask, x0, z0, cell) if found and np.isfinite(mask).any() else None


def _fill_triangle(top, tri3: np.ndarray, x0: float, z0: float, cell: float) -> None:
    """At the texels whose centres lie in the triangle (in xz), its height
    if higher than what they hold."""
    mask = top
    tri = tri3[:, [0, 2]]
    lo = np.floor((tri.min(0) - [x0, z0]) / cell).astype(int)
    hi = np.ceil((tri.max(0) - [x0, z0]) / cell).astype(int)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, [mask.shape[1] - 1, mask.shape[0] - 1])
    if (hi < lo).any():
        return
    c, r = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    q = np.stack([x0 + (c + 0.5) * cell, z0 + (r + 0.5) * cell], -1)
    a, b, d = tri
    e1, e2 = b - a, d - a
    det = e1[0] * e2[1] - e1[1] * e2[0]
    if abs(det) < 1e-12:
        return
    v = q - a
    u = (v[..., 0] * e2[1] - v[..., 1] * e2[0]) / det
    w = (e1[0] * v[..., 1] - e1[1] * v[..., 0]) / det
    inside = (u >= -1e-9) & (w >= -1e-9) & (u + w <= 1 + 1e-9)
    y = tri3[0, 1] + u * (tri3[1, 1] - tri3[0, 1]) + w * (tri3[2, 1] - tri3[0, 1])
    rr, cc = r[inside], c[inside]
    top[rr, cc] = np.fmax(top[rr, cc], y[inside])


_VIEWS: dict = {}  # (path, mtime) -> GroundDetailView or None: several views of one world read it once


def with_ground_detail(img, world_usda: str | Path, camera, width: int, height: int):
    """img with the world's ground detail layer on its terrain pixels (img itself where the world has none)."""
    key = (str(Path(world_usda).resolve()), Path(world_usda).stat().st_mtime_ns)
    if key not in _VIEWS:
        _VIEWS.clear()
        _VIEWS[key] = load_detail_view(world_usda)
    view = _VIEWS[key]
    return img if view is None else view.apply(img, camera, width, height)
