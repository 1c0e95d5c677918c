"""build/worlds/<name>/report.html: one page to look at a world before
opening a DCC tool, with its PNGs beside it (report_*.png).

Generic over the stages: it reads only what every run leaves in the store
(the world manifest, each run's manifest.json with its outputs, channel
names, units, timings and metrics, the json outputs, the EXR grids and the
USD layers) and imports no stage code, so a new stage shows up in the table
by itself. Maps are found by the conventions of DESIGN.md's channel names:
- height: the last artifact named `<stage>.height` in plan order (the
  terrain the world was built on);
- erosion change: an artifact `<stage>.change` (channel `change.net`);
- rivers and lakes: the BasisCurves and the water meshes of the composed
  world.usda (what a DCC tool shows, not the grids);
- moisture: the last grid with a channel `moisture`;
- ground types: the channels `splat.*` (the largest weight per cell);
- density per species: the channels `density.<species>`.
Warnings: species whose `suitability.<species>` is zero everywhere or that
no instancer places, metrics named `warnings`, `*_ok` flags that are false,
non-empty `unplaced`/`not_placed` lists, and --set overrides that had no
effect (the config already held that value, or their stage did not run).
Plots of run time against error: any list of records in a run's metrics
carrying both a time (`*seconds*`, `*_s`) and an error (`*error*`,
`hausdorff*`), e.g. the plant LOD chain.

The world picture is one function (world_picture) so that it can be
switched to another renderer call.
"""
from __future__ import annotations

import html
import json
import math
import re
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .store import MANIFEST, Store

MAP_PX = 480  # pixels on the long side of a map
VIEW_SIZE = (960, 540)

# Ground types: a colour each (sRGB), for the legend; unknown types get grey.
GROUND_COLOURS = {"rock": (120, 112, 104), "scree": (168, 160, 150), "grass": (86, 130, 52), "dry_grass": (176, 160, 92),
                  "mud": (104, 82, 60), "snow": (240, 242, 248), "sand": (220, 200, 150)}


# --------------------------------------------------------------------------- colour ramps


def _ramp(stops: list[tuple[float, tuple[int, int, int]]]) -> Callable[[np.ndarray], np.ndarray]:
    xs = np.array([s[0] for s in stops])
    cs = np.array([s[1] for s in stops], np.float64)

    def apply(t: np.ndarray) -> np.ndarray:
        t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
        return np.stack([np.interp(t, xs, cs[:, i]) for i in range(3)], axis=-1).round().astype(np.uint8)
    return apply


TERRAIN = _ramp([(0.0, (40, 90, 60)), (0.3, (120, 150, 80)), (0.55, (190, 170, 110)), (0.8, (150, 120, 100)),
                 (1.0, (250, 250, 250))])
DIVERGING = _ramp([(0.0, (40, 70, 170)), (0.5, (245, 245, 245)), (1.0, (180, 40, 30))])
WET = _ramp([(0.0, (235, 225, 200)), (0.5, (110, 180, 170)), (1.0, (20, 60, 140))])
DENSITY = _ramp([(0.0, (245, 245, 235)), (0.4, (150, 200, 110)), (1.0, (20, 80, 30))])


def _write_png(path: Path, rgb: np.ndarray) -> None:
    from .exr import write_png

    write_png(path, np.ascontiguousarray(rgb, np.uint8))


def _map_size(shape: tuple[int, int], px: int = MAP_PX) -> tuple[int, int]:
    """Map pixels (rows, cols) for a grid: the long side about px, cells square."""
    f = px / max(shape)
    return max(1, round(shape[0] * f)), max(1, round(shape[1] * f))


def _upscale(rgb: np.ndarray, px: int = MAP_PX) -> np.ndarray:
    """Nearest-neighbour resampling so that the long side is about px."""
    rows, cols = _map_size(rgb.shape[:2], px)
    r = ((np.arange(rows) + 0.5) * rgb.shape[0] / rows).astype(int)
    c = ((np.arange(cols) + 0.5) * rgb.shape[1] / cols).astype(int)
    return rgb[r][:, c]


def _hillshade(h: np.ndarray, cell: float) -> np.ndarray:
    from .grid import Grid
    from worldlib.terrain.hillshade import hillshade

    return hillshade(Grid(np.ascontiguousarray(h, np.float32), cell))[..., 0].astype(np.float64) / 255.0


def _nice(x: float) -> float:
    """A round number (1, 2, 5 x 10^n) no larger than x."""
    if x <= 0:
        return 0.0
    e = 10 ** math.floor(math.log10(x))
    return max(m * e for m in (1, 2, 5) if m * e <= x)


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        if v == 0 or not math.isfinite(v):
            return str(v)
        return f"{v:.4g}" if 1e-3 <= abs(v) < 1e6 else f"{v:.3e}"
    return html.escape(str(v))


# --------------------------------------------------------------------------- reading the world


class World:
    """A world's manifest and the runs it names, read from the store."""

    def __init__(self, store: Store, manifest: dict):
        self.store = store
        self.manifest = manifest
        self.runs = []  # (stage, key, manifest), in plan order
        for e in manifest["artifacts"]:
            if store.has(e["stage"], e["key"]):
                self.runs.append((e["stage"], e["key"], store.manifest(e["stage"], e["key"])))

    def grids(self):
        """(stage, key, artifact name, meta) of every grid output, in plan order."""
        for stage, key, m in self.runs:
            for name, meta in m.get("outputs", {}).items():
                if meta.get("kind") == "grid" and not meta.get("absent"):
                    yield stage, key, name, meta

    def read(self, stage: str, key: str, meta: dict):
        from .exr import read_grid

        return read_grid(self.store.folder(stage, key) / meta["file"])

    def find_artifact(self, suffix: str):
        found = [g for g in self.grids() if g[2].endswith(suffix)]
        return found[-1] if found else None

    def find_channel(self, test: Callable[[str], bool]):
        found = [g for g in self.grids() if any(test(c) for c in g[3].get("channels", []))]
        return found[-1] if found else None


# --------------------------------------------------------------------------- maps


class Maps:
    def __init__(self, world: World, out: Path):
        self.world, self.out = world, out
        self.items: list[dict] = []
        self.height = None  # (grid values, cell size) of the terrain

    def add(self, name: str, title: str, rgb: np.ndarray, cell_m: float, shape: tuple[int, int],
            legend: str, note: str = "") -> None:
        img = _upscale(rgb)
        file = f"report_{name}.png"
        _write_png(self.out / file, img)
        self.items.append({"file": file, "title": title, "legend": legend, "note": note,
                           "width_m": shape[1] * cell_m, "px": img.shape[1], "py": img.shape[0]})

    def colour_bar(self, name: str, ramp, lo: float, hi: float, units: str) -> str:
        t = np.linspace(0.0, 1.0, 256)[None, :].repeat(12, axis=0)
        file = f"report_bar_{name}.png"
        _write_png(self.out / file, ramp(t))
        return (f'<div class="bar"><span>{_fmt(lo)}</span><img src="{file}" alt="colour bar" width="256" height="12">'
                f'<span>{_fmt(hi)} {html.escape(units)}</span></div>')

    def shaded(self, values: np.ndarray, ramp, lo: float, hi: float) -> np.ndarray:
        t = (values - lo) / (hi - lo) if hi > lo else np.zeros_like(values)
        rgb = ramp(t).astype(np.float64)
        if self.height is not None and self.height[0].shape == values.shape:
            rgb *= (0.55 + 0.45 * _hillshade(*self.height))[..., None]
        return np.clip(rgb, 0, 255).astype(np.uint8)

    def build(self, world_usda: Path | None) -> None:
        w = self.world
        h = w.find_artifact(".height")
        if h is None:
            return
        grid = w.read(h[0], h[1], h[3])
        height = grid.channel("height").astype(np.float64)
        self.height = (height, grid.cell_size_m)
        lo, hi = float(np.nanmin(height)), float(np.nanmax(height))
        self.add("height", f"Height ({h[2]})", self.shaded(height, TERRAIN, lo, hi), grid.cell_size_m, grid.shape,
                 self.colour_bar("height", TERRAIN, lo, hi, "m"))
        ch = w.find_artifact(".change")
        if ch is not None:
            g = w.read(ch[0], ch[1], ch[3])
            name = "change.net" if "change.net" in g.channels else g.channels[0]
            v = g.channel(name).astype(np.float64)
            m = float(np.nanpercentile(np.abs(v), 99)) or 1.0
            self.add("change", f"Erosion change ({name}, deposition red, erosion blue)",
                     self.shaded(v, DIVERGING, -m, m), g.cell_size_m, g.shape,
                     self.colour_bar("change", DIVERGING, -m, m, "m") +
                     '<div class="note">clipped at the 99th percentile of |change|</div>')
        if world_usda is not None and world_usda.is_file():
            self.water(world_usda, height, grid)
        mo = w.find_channel(lambda c: c == "moisture")
        if mo is not None:
            g = w.read(mo[0], mo[1], mo[3])
            v = g.channel("moisture").astype(np.float64)
            self.add("moisture", f"Moisture ({mo[2]})", self.shaded(v, WET, 0.0, 1.0), g.cell_size_m, g.shape,
                     self.colour_bar("moisture", WET, 0.0, 1.0, mo[3].get("channel_units", {}).get("moisture", "")))
        sp = w.find_channel(lambda c: c.startswith("splat."))
        if sp is not None:
            g = w.read(sp[0], sp[1], sp[3])
            names = [c for c in g.channels if c.startswith("splat.")]
            weights = np.stack([g.channel(c) for c in names], axis=-1)
            kinds = [c.split(".", 1)[1] for c in names]
            palette = np.array([GROUND_COLOURS.get(k, (128, 128, 128)) for k in kinds], np.float64)
            rgb = palette[np.argmax(weights, axis=-1)]
            if self.height[0].shape == rgb.shape[:2]:
                rgb *= (0.6 + 0.4 * _hillshade(*self.height))[..., None]
            share = np.bincount(np.argmax(weights, axis=-1).ravel(), minlength=len(kinds)) / weights[..., 0].size
            legend = "".join(f'<span class="swatch" style="background:rgb{tuple(int(x) for x in palette[i])}"></span>'
                             f'{html.escape(k)} {100 * share[i]:.1f} % ' for i, k in enumerate(kinds))
            self.add("ground", f"Ground types ({sp[2]}, largest weight)", rgb.astype(np.uint8), g.cell_size_m, g.shape,
                     f'<div class="legend">{legend}</div>')
        de = w.find_channel(lambda c: c.startswith("density."))
        if de is not None:
            g = w.read(de[0], de[1], de[3])
            units = de[3].get("channel_units", {})
            for c in (c for c in g.channels if c.startswith("density.")):
                v = g.channel(c).astype(np.float64)
                top = float(np.nanmax(v)) if np.isfinite(v).any() else 0.0
                species = c.split(".", 1)[1]
                self.add(f"density_{species}", f"Density: {species}", self.shaded(v, DENSITY, 0.0, top or 1.0),
                         g.cell_size_m, g.shape, self.colour_bar(f"density_{species}", DENSITY, 0.0, top or 1.0,
                                                                 units.get(c, "")))

    def water(self, world_usda: Path, height: np.ndarray, grid) -> None:
        """Rivers (BasisCurves, drawn at their widths) and lakes (meshes
        under a water prim) of the composed world, over the hillshade."""
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(world_usda))
        rows, cols = height.shape
        base = _upscale(_hillshade(height, grid.cell_size_m))
        px = cols * grid.cell_size_m / base.shape[1]  # metres per map pixel
        ox, oz = grid.origin_m
        rgb = (np.stack([base] * 3, -1) * np.array([200, 200, 190]) * 0.5 + np.array([110, 110, 100])).clip(0, 255)
        lake_mask = np.zeros(base.shape, bool)
        river_mask = np.zeros(base.shape, bool)
        yy, xx = np.mgrid[0:base.shape[0], 0:base.shape[1]]
        cx, cz = ox + (xx + 0.5) * px, oz + (yy + 0.5) * px
        n_curves = n_lakes = 0
        it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
        for prim in it:
            if prim.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                continue
            if prim.IsA(UsdGeom.BasisCurves):
                curves = UsdGeom.BasisCurves(prim)
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
                            r = max(0.5 * wseg[i], 1.0 * px)  # at least a pixel either side: visible
                            c0, r0 = int((x - ox) / px), int((z - oz) / px)
                            rr = int(r / px) + 1
                            sl = (slice(max(r0 - rr, 0), r0 + rr + 1), slice(max(c0 - rr, 0), c0 + rr + 1))
                            river_mask[sl] |= (cx[sl] - x) ** 2 + (cz[sl] - z) ** 2 <= r * r
                    start += n
                    n_curves += 1
            elif prim.IsA(UsdGeom.Mesh) and "water" in str(prim.GetPath()).lower():
                mesh = UsdGeom.Mesh(prim)
                pts = np.asarray(mesh.GetPointsAttr().Get() or [], np.float64)
                counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
                idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
                start = 0
                for n in counts:
                    face = pts[idx[start:start + n]]
                    for j in range(1, n - 1):  # fan triangles
                        _fill_triangle(lake_mask, face[0], face[j], face[j + 1], ox, oz, px)
                    start += n
                n_lakes += 1
        rgb[river_mask] = (40, 110, 220)
        rgb[lake_mask] = (30, 80, 190)
        legend = (f'<div class="legend"><span class="swatch" style="background:rgb(40,110,220)"></span>rivers '
                  f'({n_curves} curves, drawn at their USD widths, at least 3 pixels wide) '
                  f'<span class="swatch" style="background:rgb(30,80,190)"></span>lakes ({n_lakes} lake meshes)</div>')
        file = "report_water.png"
        _write_png(self.out / file, rgb.astype(np.uint8))
        self.items.append({"file": file, "title": "Rivers and lakes (as in the USD)", "legend": legend, "note": "",
                           "width_m": cols * grid.cell_size_m, "px": rgb.shape[1], "py": rgb.shape[0]})


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


# --------------------------------------------------------------------------- the world picture


def world_picture(world_usda: Path, out_png: Path, size: tuple[int, int] = VIEW_SIZE) -> str:
    """A perspective view of the world's ground meshes (terrain and water,
    not the plants) in their ground colours, rendered with worldlib.render;
    returns a caption. The one call to switch for a view with plants."""
    from pxr import Usd, UsdGeom

    from worldlib.render import Camera, Scene, Settings, render, srgb8

    stage = Usd.Stage.Open(str(world_usda))
    scenes = []
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            continue
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get() or [], np.float64)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
        idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
        if not len(pts) or not len(counts):
            continue
        xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()), np.float64)
        pts = pts @ xf[:3, :3] + xf[3, :3]  # USD matrices act on row vectors
        tris = _triangulate(counts, idx)
        water = "water" in str(prim.GetPath()).lower()
        tint = np.tile([0.05, 0.12, 0.25] if water else [0.3, 0.3, 0.28], (len(tris), 1))
        if not water:
            colours = _ground_colours(prim, pts, tris)
            if colours is not None:
                tint = colours
        e1, e2 = pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]]
        fn = np.cross(e1, e2)
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
        fn[fn[:, 1] < 0] *= -1.0
        corners = tris.ravel()  # each face's normal summed at its three corners
        vn = np.stack([np.bincount(corners, np.repeat(fn[:, k], 3), len(pts)) for k in range(3)], axis=1)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
        scenes.append(Scene(pts, vn, np.zeros((len(pts), 2)), tris, tint, -1))
    if not scenes:
        raise ValueError("the world has no meshes to show")
    scene = Scene.concat(scenes)
    lo, hi = scene.positions.min(0).astype(np.float64), scene.positions.max(0).astype(np.float64)
    centre = 0.5 * (lo + hi)
    span = float(max(hi[0] - lo[0], hi[2] - lo[2]))
    direction = np.array([0.55, -0.5, -0.67])  # from the south-west, looking north-east and down
    direction /= np.linalg.norm(direction)
    eye = centre - direction * 1.6 * span
    eye[1] = max(eye[1], hi[1] + 0.3 * span)
    forward = centre - eye
    camera = Camera(tuple(eye), tuple(forward / np.linalg.norm(forward)), fov_y_deg=40.0)
    img = render(scene, camera, Settings(size[0], size[1], samples=2, ao_rays=0))
    _write_png(out_png, srgb8(img.shaded(sun=(0.5, 0.7, 0.3))))
    return (f"{scene.n_triangles:,} triangles of the ground and water meshes, worldlib.render "
            f"(perspective, 2x2 samples); plants not drawn")


def _triangulate(counts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    if (counts == 3).all():
        return idx.reshape(-1, 3)
    tris, start = [], 0
    for n in counts:
        f = idx[start:start + n]
        tris.extend((f[0], f[j], f[j + 1]) for j in range(1, n - 1))
        start += n
    return np.asarray(tris, np.int64).reshape(-1, 3)


def _ground_colours(prim, pts: np.ndarray, tris: np.ndarray) -> np.ndarray | None:
    """Linear albedo per triangle from the bound material's diffuse texture
    at the triangle's centre st (UDIM tiles resolved per tile)."""
    from pxr import UsdGeom, UsdShade

    material = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if not material or not st:
        return None
    file_attr = None
    for shader_prim in _descendants(material.GetPrim()):
        shader = UsdShade.Shader(shader_prim)
        surface_in = shader.GetInput("diffuseColor")
        if surface_in and surface_in.HasConnectedSource():
            source = surface_in.GetConnectedSource()[0]
            file_attr = source.GetPrim().GetAttribute("inputs:file")
            break
    if file_attr is None or file_attr.Get() is None:
        return None
    st_values = np.asarray(st.ComputeFlattened(), np.float64)
    if len(st_values) != len(pts):
        return None
    asset = file_attr.Get()
    layer_dir = Path(file_attr.GetPropertyStack()[0].layer.realPath).parent
    path = (layer_dir / asset.path).resolve() if "<UDIM>" in asset.path else Path(asset.resolvedPath or "")
    uv = st_values[tris].mean(axis=1)
    out = np.zeros((len(tris), 3))
    if "<UDIM>" in asset.path:
        pattern = re.escape(path.name).replace(re.escape("<UDIM>"), r"(\d{4})")
        tiles = {int(m.group(1)): f for f in path.parent.iterdir() if (m := re.fullmatch(pattern, f.name))}
        if not tiles:
            return None
        n = int(round(math.sqrt(len(tiles))))
        tu = np.clip(np.floor(uv[:, 0] * n), 0, n - 1).astype(int)
        tv = np.clip(np.floor(uv[:, 1] * n), 0, n - 1).astype(int)
        texels = math.sqrt(len(tris) / 2.0) / n  # about one texel per mesh cell of the tile
        for tile, f in tiles.items():
            u0, v0 = (tile - 1001) % 10, (tile - 1001) // 10
            sel = (tu == u0) & (tv == v0)
            if sel.any():
                out[sel] = _sample(_read_level(f, texels), uv[sel] * n - [u0, v0])
        return out
    if not path.is_file():
        return None
    return _sample(_read_level(path, math.sqrt(len(tris) / 2.0)), uv)


def _read_level(path: Path, texels: float) -> np.ndarray:
    """The texture's pixels at its smallest MIP level still `texels` wide
    (a picture of the whole world needs one texel per mesh cell, not the 1 m
    tiles' full resolution)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    try:
        level = 0
        while inp.seek_subimage(0, level + 1) and inp.spec().width >= texels:
            level += 1
        inp.seek_subimage(0, level)
        return np.asarray(inp.read_image(oiio.FLOAT))
    finally:
        inp.close()


def _descendants(prim):
    from pxr import Usd

    return list(Usd.PrimRange(prim))


def _sample(pixels: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = pixels.shape[:2]
    c = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    r = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)  # t = 1 is the image's top row
    return pixels[r, c, :3].astype(np.float64)


# --------------------------------------------------------------------------- tables, counts, warnings


ERROR_WORDS = re.compile(r"error|residual|hausdorff|budget", re.I)
TIME_KEY = re.compile(r"seconds|_s$", re.I)


def _scalars(metrics: dict, prefix: str = "", depth: int = 0) -> dict[str, Any]:
    """Scalar metrics, nested tables flattened (a.b), lists left out."""
    out = {}
    for k, v in metrics.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and depth < 2:
            out.update(_scalars(v, key + ".", depth + 1))
        elif isinstance(v, (int, float, str, bool)) or v is None:
            out[key] = v
    return out


def stage_rows(world: World) -> list[dict]:
    steps = {s["stage"]: s for s in world.manifest.get("steps", [])}
    rows = []
    for stage, key, m in world.runs:
        metrics = dict(m.get("metrics", {}))
        for name, meta in m.get("outputs", {}).items():  # a stage's json statistics
            if meta.get("kind") == "json" and name.endswith(".stats") and not meta.get("absent"):
                try:
                    metrics.update(json.loads((world.store.folder(stage, key) / meta["file"]).read_text()))
                except (OSError, ValueError):
                    pass
        flat = _scalars(metrics)
        errors = {k: v for k, v in flat.items() if ERROR_WORDS.search(k) and isinstance(v, (int, float))
                  and not isinstance(v, bool)}
        step = steps.get(stage, {})
        rows.append({"stage": stage, "key": key, "status": step.get("status", "?"),
                     "seconds": step.get("seconds"), "run_s": m.get("timings", {}).get("run_s"),
                     "errors": errors, "stats": {k: v for k, v in flat.items() if k not in errors},
                     "outputs": sorted(m.get("outputs", {}))})
    return rows


def time_error_series(world: World) -> list[dict]:
    """Lists of records in a run's metrics that hold a time and an error."""
    series = []

    def walk(stage: str, path: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(stage, f"{path}.{k}" if path else k, x)
        elif isinstance(v, list) and len(v) >= 2 and all(isinstance(r, dict) for r in v):
            tkey = next((k for k in v[0] if TIME_KEY.search(k) and isinstance(v[0][k], (int, float))), None)
            ekey = next((k for k in v[0] if ERROR_WORDS.search(k) and isinstance(v[0][k], (int, float))
                         and not isinstance(v[0][k], bool)), None)
            if tkey and ekey:
                pts = [(float(r[tkey]), float(r[ekey])) for r in v
                       if isinstance(r.get(tkey), (int, float)) and isinstance(r.get(ekey), (int, float))]
                if pts:
                    series.append({"stage": stage, "what": path, "x": tkey, "y": ekey, "points": pts})
    for stage, _, m in world.runs:
        walk(stage, "", m.get("metrics", {}))
    return series


def svg_plot(s: dict, width: int = 320, height: int = 200) -> str:
    xs = [p[0] for p in s["points"]]
    ys = [p[1] for p in s["points"]]
    x0, x1 = 0.0, max(xs) * 1.1 or 1.0
    y0, y1 = 0.0, max(ys) * 1.1 or 1.0
    m = 40

    def X(x):
        return m + (x - x0) / (x1 - x0) * (width - m - 10)

    def Y(y):
        return height - m + -(y - y0) / (y1 - y0) * (height - m - 10)
    dots = "".join(f'<circle cx="{X(x):.1f}" cy="{Y(y):.1f}" r="3.5" fill="#2a6"><title>{_fmt(x)} s, {_fmt(y)}</title></circle>'
                   for x, y in s["points"])
    line = " ".join(f"{X(x):.1f},{Y(y):.1f}" for x, y in s["points"])
    return (f'<figure class="plot"><svg width="{width}" height="{height}" role="img">'
            f'<polyline points="{line}" fill="none" stroke="#8bc" stroke-width="1"/>{dots}'
            f'<line x1="{m}" y1="{height - m}" x2="{width - 10}" y2="{height - m}" stroke="#333"/>'
            f'<line x1="{m}" y1="{height - m}" x2="{m}" y2="10" stroke="#333"/>'
            f'<text x="{width - 10}" y="{height - m + 16}" text-anchor="end">{html.escape(s["x"])} (0 .. {_fmt(x1)})</text>'
            f'<text x="{m - 4}" y="10" text-anchor="end" transform="rotate(-90 {m - 28} 10)">{html.escape(s["y"])}</text>'
            f'<text x="{m - 4}" y="22" text-anchor="end">{_fmt(y1)}</text>'
            f'</svg><figcaption>{html.escape(s["stage"])}: {html.escape(s["what"])}</figcaption></figure>')


def lod_counts(world_usda: Path) -> tuple[list[dict], list[dict]]:
    """Instances per prototype (over every PointInstancer) and, for every
    prim of the composed world with a `lod` variant set (abstract prototype
    classes included), the triangles a renderer draws in each variant:
    active, visible meshes of purpose default or render."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world_usda))
    per_proto: dict[str, int] = {}
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            inst = UsdGeom.PointInstancer(prim)
            protos = inst.GetPrototypesRel().GetTargets()
            idx = np.asarray(inst.GetProtoIndicesAttr().Get() or [], np.int64)
            counts = np.bincount(idx, minlength=len(protos)) if len(idx) else np.zeros(len(protos), int)
            for p, n in zip(protos, counts):
                per_proto[p.name] = per_proto.get(p.name, 0) + int(n)
            it.PruneChildren()
    # payloads unloaded (tiles hold only instances of the prototypes); an instance shares its prototype's rows
    unloaded = Usd.Stage.Open(str(world_usda), Usd.Stage.LoadNone)
    with_lods = [p.GetPath() for p in Usd.PrimRange.AllPrims(unloaded.GetPseudoRoot())
                 if not p.IsInstance() and "lod" in p.GetVariantSets().GetNames()]
    lods = []
    if with_lods:
        # masked to those prims, the variant switches (in the session layer) recompose only them
        masked = Usd.Stage.OpenMasked(str(world_usda), Usd.StagePopulationMask(with_lods), Usd.Stage.LoadNone)
        masked.SetEditTarget(masked.GetSessionLayer())
        for path in with_lods:
            prim = masked.GetPrimAtPath(path)
            vset = prim.GetVariantSets().GetVariantSet("lod")
            row = {"asset": path.name, "lods": {}, "from_m": _switch_distances(prim)}
            for name in vset.GetVariantNames():
                vset.SetVariantSelection(name)
                row["lods"][name] = _drawn_triangles(masked.GetPrimAtPath(path))
            lods.append(row)
    instances = [{"prototype": k, "instances": v} for k, v in sorted(per_proto.items())]
    return instances, lods


def _switch_distances(prim) -> dict[str, float]:
    """The distance from which each `lod` variant is drawn, as the asset
    publishes it (customData worldbake:lod_switch_m: variant_m, else
    ladder_m); {} when it does not."""
    text = prim.GetCustomDataByKey("worldbake:lod_switch_m")
    try:
        data = json.loads(text) if isinstance(text, str) else {}
        ladder = data["variant_m"] if "variant_m" in data else data["ladder_m"]
        return {str(k): float(v) for k, v in ladder.items() if isinstance(v, (int, float))}
    except (ValueError, KeyError, TypeError, AttributeError):
        return {}


def _drawn_triangles(prim) -> int:
    from pxr import Usd, UsdGeom

    tris = 0
    for p in Usd.PrimRange(prim, Usd.PrimIsActive & Usd.PrimIsDefined):  # prototypes are abstract classes
        if not p.IsA(UsdGeom.Mesh):
            continue
        imageable = UsdGeom.Imageable(p)
        if imageable.ComputeVisibility() == UsdGeom.Tokens.invisible or \
                imageable.ComputePurpose() not in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render):
            continue
        c = np.asarray(UsdGeom.Mesh(p).GetFaceVertexCountsAttr().Get() or [], np.int64)
        tris += int((c - 2).clip(0).sum())
    return tris


def warnings(world: World) -> list[str]:
    out = []
    for stage, _, m in world.runs:
        flat = _scalars(m.get("metrics", {}))
        for k, v in flat.items():
            if k.endswith("_ok") and v is False:
                out.append(f"{stage}: {k} is false")
        for k, v in m.get("metrics", {}).items():
            if k == "warnings" and isinstance(v, list):
                out += [f"{stage}: {w}" for w in v]
            elif re.search(r"unplaced|not_placed", k) and isinstance(v, list) and v:
                out.append(f"{stage}: {k}: {', '.join(map(str, v))}")
    suit = world.find_channel(lambda c: c.startswith("suitability."))
    if suit is not None:
        g = world.read(suit[0], suit[1], suit[3])
        for c in g.channels:
            if c.startswith("suitability.") and not np.nanmax(g.channel(c)) > 0:
                out.append(f"{suit[0]}: species {c.split('.', 1)[1]} found no suitable land (suitability is 0 everywhere)")
    for key, value in world.manifest.get("overrides", {}).items():
        stage = key.split(".")[0]
        params = world.manifest.get("params", {})
        if stage not in params and stage not in ("seed", "name", "outputs", "shared"):
            out.append(f"--set {key}={json.dumps(value)}: stage {stage} did not run in this bake; the override had no effect")
    return out


# --------------------------------------------------------------------------- the page


CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px} h2{font-size:18px;margin-top:28px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:8px 0} td,th{border:1px solid #ccc;padding:3px 8px;vertical-align:top;text-align:left}
th{background:#f2f2f2} td.num{text-align:right;font-variant-numeric:tabular-nums}
.maps{display:flex;flex-wrap:wrap;gap:18px} figure{margin:0} figcaption{font-weight:600;margin:4px 0}
.bar{display:flex;align-items:center;gap:6px;font-size:12px} .bar img{border:1px solid #999}
.legend{font-size:12px} .swatch{display:inline-block;width:12px;height:12px;border:1px solid #777;margin:0 4px -2px 8px}
.scale{font-size:12px} .scale div{height:6px;border:1px solid #000;border-top:none;background:#fff}
.warn{background:#fff3cd;border:1px solid #e0c060;padding:8px 12px} .ok{color:#270}
.note{font-size:12px;color:#555} details{font-size:12px} code{font-size:12px}
.plot text{font-size:11px}
"""


def _scale_bar(width_m: float, px: int) -> str:
    length = _nice(width_m / 4)
    w = length / width_m * px
    label = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    return f'<div class="scale" style="width:{w:.0f}px"><div></div>{label}</div>'


def write_report(store: Store, out: Path, manifest: dict, world_usda: Path | None) -> Path:
    """Write report.html and its report_*.png into `out` (the world folder
    being published: `world_usda` is the layer as it will be found)."""
    world = World(store, manifest)
    problems: list[str] = []
    view = ""
    if world_usda is not None and world_usda.is_file():
        try:
            caption = world_picture(world_usda, out / "report_view.png")
            view = (f'<figure><img src="report_view.png" alt="the world" width="{VIEW_SIZE[0]}" '
                    f'height="{VIEW_SIZE[1]}"><figcaption class="note">{html.escape(caption)}</figcaption></figure>')
        except Exception as e:  # the page still shows everything else
            problems.append(f"report: the world picture failed: {type(e).__name__}: {e}")
    maps = Maps(world, out)
    try:
        maps.build(world_usda)
    except Exception as e:
        problems.append(f"report: maps stopped: {type(e).__name__}: {e}")
    instances, lods = [], []
    if world_usda is not None and world_usda.is_file():
        try:
            instances, lods = lod_counts(world_usda)
        except Exception as e:
            problems.append(f"report: instance and LOD counts failed: {type(e).__name__}: {e}")
    warns = problems + warnings(world)
    rows = stage_rows(world)
    series = time_error_series(world)

    e = html.escape
    overrides = manifest.get("overrides", {})
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>worldbake: {e(manifest['world'])}</title>"
             f"<style>{CSS}</style></head><body>",
             f"<h1>World {e(manifest['world'])}</h1>",
             f"<p>Config <code>{e(str(manifest.get('config')))}</code>"
             + (f" variant <code>{e(manifest['variant'])}</code>" if manifest.get("variant") else "")
             + f", seed {manifest.get('seed')}, outputs {e(', '.join(manifest.get('outputs', [])))}. Overrides: "
             + (", ".join(f"<code>{e(k)}={e(json.dumps(v))}</code>" for k, v in overrides.items()) or "none") + ".</p>"]
    parts.append("<h2>Warnings</h2>" + ('<div class="warn"><ul>' + "".join(f"<li>{e(w)}</li>" for w in warns)
                                       + "</ul></div>" if warns else '<p class="ok">none</p>'))
    if view:
        parts.append("<h2>The world</h2>" + view)
    if maps.items:
        parts.append('<h2>Maps</h2><div class="maps">')
        for m in maps.items:
            parts.append(f'<figure><figcaption>{e(m["title"])}</figcaption><img src="{m["file"]}" alt="{e(m["title"])}" '
                         f'width="{m["px"]}" height="{m["py"]}">{m["legend"]}{_scale_bar(m["width_m"], m["px"])}</figure>')
        parts.append("</div><p class='note'>North is up; x grows east. Shaded by the terrain's hillshade.</p>")
    parts.append("<h2>Stages</h2><table><tr><th>stage</th><th>this bake</th><th>seconds</th><th>run s</th><th>key</th>"
                 "<th>errors</th><th>statistics</th></tr>")
    for r in rows:
        errs = "<br>".join(f"{e(k)} = {_fmt(v)}" for k, v in r["errors"].items()) or "-"
        stats = "".join(f"<tr><td>{e(k)}</td><td class=num>{_fmt(v)}</td></tr>" for k, v in r["stats"].items())
        parts.append(f"<tr><td>{e(r['stage'])}</td><td>{e(r['status'])}</td><td class=num>{_fmt(r['seconds'])}</td>"
                     f"<td class=num>{_fmt(r['run_s'])}</td><td><code>{e(r['key'])}</code></td>"
                     f"<td><details><summary>{len(r['errors'])}</summary>{errs}</details></td>"
                     f"<td><details><summary>{len(r['stats'])} values</summary><table>{stats}</table></details></td></tr>")
    parts.append("</table><p class='note'>seconds: this bake's time for the step (0 when cached); run s: the time "
                 "of the run that made the artifacts.</p>")
    if instances or lods:
        parts.append("<h2>Instances and triangles</h2>")
        if instances:
            tri_per = {r["asset"]: r["lods"] for r in lods}
            parts.append("<table><tr><th>prototype</th><th>instances</th><th>triangles at LOD0 (all instances)</th></tr>")
            for r in instances:
                lod0 = next(iter(tri_per.get(r["prototype"], {}).values()), None)
                parts.append(f"<tr><td>{e(r['prototype'])}</td><td class=num>{r['instances']:,}</td><td class=num>"
                             + (f"{lod0 * r['instances']:,}" if lod0 is not None else "-") + "</td></tr>")
            parts.append(f"<tr><th>total</th><th class=num>{sum(r['instances'] for r in instances):,}</th><th></th></tr></table>")
        if lods:
            names = sorted({n for r in lods for n in r["lods"]})
            parts.append("<table><tr><th>asset</th>" + "".join(f"<th>{e(n)} triangles</th>" for n in names) + "</tr>")
            for r in lods:
                dist = r.get("from_m", {})
                parts.append(f"<tr><td>{e(r['asset'])}</td>" + "".join(
                    (f"<td class=num>{r['lods'][n]:,}" + (f" <span class=note>from {dist[n]:,.0f} m</span>"
                                                          if n in dist else "") + "</td>")
                    if n in r["lods"] else "<td>-</td>" for n in names) + "</tr>")
            parts.append("</table><p class='note'>from: the distance from which the asset's LOD ladder draws that "
                         "LOD (customData worldbake:lod_switch_m, from each LOD's measured error at one pixel on "
                         "the reference screen); a LOD without a distance is not on the ladder.</p>")
    if series:
        parts.append('<h2>Run time against error</h2><div class="maps">' + "".join(svg_plot(s) for s in series) + "</div>")
    parts.append("</body></html>\n")
    path = out / "report.html"
    path.write_text("".join(parts))
    return path


def referenced_images(report_html: Path) -> list[str]:
    """Every image file the page names (for tests and exports)."""
    return re.findall(r'<img src="([^"]+)"', report_html.read_text())
