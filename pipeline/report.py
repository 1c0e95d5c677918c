"""build/worlds/<name>/report.html: one page to look at a world before
opening a DCC tool, with its PNGs beside it (report_*.png).

The engine's own parts read only what every run leaves in the store (the
world manifest, each run's manifest.json with its outputs, channel names,
units, timings and metrics, the json outputs) and hold for any stage:
- warnings: metrics named `warnings`, `*_ok` flags that are false,
  non-empty `unplaced`/`not_placed` lists, and --set overrides that had no
  effect (their stage did not run);
- a row per stage: ran or cached, seconds, key, errors and statistics;
- plots of run time against error: any list of records in a run's metrics
  carrying both a time (`*seconds*`, `*_s`) and an error (`*error*`,
  `hausdorff*`), e.g. a LOD chain.
Everything else is what the stages that ran declare in `Stage.report`
(pipeline.contract): maps of their grids (colour ramps, value ranges,
relief shading, categorical legends), pictures, maps and tables of the
composed world.usda made by callables they name, and warnings. This module
lays them out (colour bars, scale bars, legends) and names no stage output.
"""
from __future__ import annotations

import hashlib
import html
import json
import math
import re
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .contract import (DrawnMap, MapFrame, Relief, ReportMap, ReportPicture, ReportTable, ReportWarning, Stage, Table,
                       ValueRange, _pattern_regex, _placeholder)
from .grid import Grid
from .store import Store, sha256_file, write_json

MAP_PX = 480  # pixels on the long side of a map
MAP_READ_CELLS = 2048  # a grid larger than this a side is read for its maps as block means (read_for_map)


# --------------------------------------------------------------------------- colour ramps


def _ramp(stops) -> Callable[[np.ndarray], np.ndarray]:
    """A colour ramp through (t, sRGB) stops, t in [0, 1]."""
    xs = np.array([s[0] for s in stops])
    cs = np.array([s[1] for s in stops], np.float64)

    def apply(t: np.ndarray) -> np.ndarray:
        t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
        return np.stack([np.interp(t, xs, cs[:, i]) for i in range(3)], axis=-1).round().astype(np.uint8)
    return apply


# The ramps a ReportMap may name; it may give its own stops instead.
PALETTES = {
    "terrain": ((0.0, (40, 90, 60)), (0.3, (120, 150, 80)), (0.55, (190, 170, 110)), (0.8, (150, 120, 100)),
                (1.0, (250, 250, 250))),
    "diverging": ((0.0, (40, 70, 170)), (0.5, (245, 245, 245)), (1.0, (180, 40, 30))),
    "wet": ((0.0, (235, 225, 200)), (0.5, (110, 180, 170)), (1.0, (20, 60, 140))),
    "greens": ((0.0, (245, 245, 235)), (0.4, (150, 200, 110)), (1.0, (20, 80, 30))),
}
GREY = (128, 128, 128)  # a category without a declared colour


def _palette(palette) -> Callable[[np.ndarray], np.ndarray]:
    if isinstance(palette, str):
        if palette not in PALETTES:
            raise KeyError(f"no palette {palette!r}: one of {sorted(PALETTES)}, or stops")
        palette = PALETTES[palette]
    return _ramp(palette)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    from .exr import write_png

    write_png(path, np.ascontiguousarray(rgb, np.uint8))


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) of a picture a stage wrote."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read {path}: {oiio.geterror()}")
    try:
        return inp.spec().width, inp.spec().height
    finally:
        inp.close()


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


def read_for_map(path: Path, cells: int = MAP_READ_CELLS) -> Grid:
    """The grid file at `path` with at most about `cells` cells a side: the
    grid itself when it is that small, else the means of s x s blocks (a map
    of MAP_PX pixels needs no more), read in bands of file tiles."""
    from . import exr

    info = exr.grid_info(path)
    s = -(-max(info.shape) // cells)
    if s <= 1:
        return exr.read_grid(path)
    rows, cols, n = info.shape[0] // s, info.shape[1] // s, len(info.channels)
    out = np.empty((rows, cols, n), np.float32)
    band = max(1, exr.TILE // s) * s  # rows of cells per read: whole blocks, about a row of file tiles
    for r0 in range(0, rows * s, band):
        part = exr.read_window(path, r0, 0, min(band, rows * s - r0), cols * s).data.reshape(-1, cols * s, n)
        out[r0 // s:r0 // s + part.shape[0] // s] = part.reshape(-1, s, cols, s, n).mean(axis=(1, 3))
    return Grid(out[..., 0] if n == 1 else out, info.cell_size_m * s, info.channels, info.origin_m)


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


def _matches(pattern: str, channels) -> list[tuple[str, dict[str, str]]]:
    """The channels a name or a pattern ("density.{species}") matches, in
    their order, each with the name the placeholder binds."""
    rx = _pattern_regex(pattern)
    var = _placeholder(pattern) if "{" in pattern else None
    return [(c, {var: m.group(1)} if var else {}) for c in channels if (m := rx.fullmatch(c))]


# --------------------------------------------------------------------------- reading the world


class World:
    """A world's manifest, the runs it names (read from the store) and the
    declarations of their stages (the registry's unless given)."""

    def __init__(self, store: Store, manifest: dict, stages: dict[str, Stage] | None = None):
        if stages is None:
            from .registry import all_stages

            stages = all_stages()
        self.store = store
        self.manifest = manifest
        self.stages = stages
        self.runs = []  # (stage, key, manifest), in plan order
        for e in manifest["artifacts"]:
            if store.has(e["stage"], e["key"]):
                self.runs.append((e["stage"], e["key"], store.manifest(e["stage"], e["key"])))

    def declared(self, kind: type) -> list[tuple[str, str, dict, Any]]:
        """(stage, key, manifest, item) of every report item of that kind
        the stages that ran declare, in plan order."""
        return [(stage, key, m, item) for stage, key, m in self.runs
                for item in getattr(self.stages.get(stage), "report", ()) if isinstance(item, kind)]

    def grids(self):
        """(stage, key, artifact name, meta) of every grid output, in plan order."""
        for stage, key, m in self.runs:
            for name, meta in m.get("outputs", {}).items():
                if meta.get("kind") == "grid" and not meta.get("absent"):
                    yield stage, key, name, meta

    def read(self, stage: str, key: str, meta: dict):
        """A grid for the maps: whole, or on a big world block means of
        s x s cells read a band at a time, so no whole map is ever held."""
        return read_for_map(self.store.folder(stage, key) / meta["file"])

    def output(self, stage: str, key: str, m: dict, artifact: str):
        """A run's grid output (meta), None when it wrote none."""
        meta = m.get("outputs", {}).get(artifact)
        return meta if meta and meta.get("kind") == "grid" and not meta.get("absent") else None

    def first_of(self, one_of: tuple[str, ...]):
        """(stage, key, name, meta) of the first of these grids the world holds."""
        for name in one_of:
            found = [g for g in self.grids() if g[2] == name]
            if found:
                return found[-1]
        return None


# --------------------------------------------------------------------------- maps


def _value_range(v: np.ndarray, r: ValueRange) -> tuple[float, float]:
    """The ends of a map's colour ramp (hi > lo) for values v."""
    finite = v[np.isfinite(v)]
    if r.symmetric_percentile is not None:
        m = float(np.percentile(np.abs(finite), r.symmetric_percentile)) if finite.size else 0.0
        return -(m or 1.0), m or 1.0
    lo = float(r.lo) if r.lo is not None else (float(finite.min()) if finite.size else 0.0)
    hi = float(r.hi) if r.hi is not None else (float(finite.max()) if finite.size else lo)
    return lo, hi if hi > lo else lo + 1.0


def _legend(entries) -> str:
    """Swatches with their labels: entries of (sRGB, label)."""
    return '<div class="legend">' + "".join(
        f'<span class="swatch" style="background:rgb{tuple(int(x) for x in rgb)}"></span>{html.escape(label)} '
        for rgb, label in entries) + "</div>"


class Maps:
    """The maps the stages that ran declare, in plan order, written as
    report_<name>.png beside the page."""

    def __init__(self, world: World, out: Path):
        self.world, self.out = world, out
        self.items: dict[str, dict] = {}  # map name -> what the page shows of it
        self.problems: list[str] = []
        self._lights: dict = {}

    def build(self, world_usda: Path | None) -> None:
        """Every declared map; a map a later stage declares under the same
        name is left to that stage."""
        decls = self.world.declared((ReportMap, DrawnMap))
        for i, (stage, key, m, d) in enumerate(decls):
            if "{" not in d.name and any(later[3].name == d.name and later[0] != stage for later in decls[i + 1:]):
                continue
            try:
                if isinstance(d, DrawnMap):
                    self.drawn(d, world_usda)
                elif d.categories:
                    self.categorical(stage, key, m, d)
                else:
                    self.channels(stage, key, m, d)
            except Exception as e:  # the page still shows everything else
                self.problems.append(f"report: {stage}: the map {d.name} failed: {type(e).__name__}: {e}")

    def add(self, name: str, title: str, rgb: np.ndarray, cell_m: float, shape: tuple[int, int], legend: str) -> None:
        img = _upscale(rgb)
        file = f"report_{name}.png"
        _write_png(self.out / file, img)
        self.items[name] = {"file": file, "title": title, "legend": legend, "width_m": shape[1] * cell_m,
                            "px": img.shape[1], "py": img.shape[0]}

    def colour_bar(self, name: str, ramp, lo: float, hi: float, units: str) -> str:
        t = np.linspace(0.0, 1.0, 256)[None, :].repeat(12, axis=0)
        file = f"report_bar_{name}.png"
        _write_png(self.out / file, ramp(t))
        return (f'<div class="bar"><span>{_fmt(lo)}</span><img src="{file}" alt="colour bar" width="256" height="12">'
                f'<span>{_fmt(hi)} {html.escape(units)}</span></div>')

    def light(self, relief: Relief) -> tuple[np.ndarray, Grid] | None:
        """The relief's light per cell in [0, 1] and its grid of heights;
        None when the world holds none of its grids."""
        g = self.world.first_of(relief.one_of)
        if g is None:
            return None
        key = (g[0], g[1], g[2], relief.channel, relief.shade)
        if key not in self._lights:
            grid = self.world.read(g[0], g[1], g[3])
            height = Grid(np.ascontiguousarray(grid.channel(relief.channel), np.float32), grid.cell_size_m,
                          (relief.channel,), grid.origin_m)
            light = np.asarray(relief.shade(height))
            light = light[..., 0] if light.ndim == 3 else light
            light = light.astype(np.float64) / 255.0 if light.dtype.kind in "ui" else light.astype(np.float64)
            self._lights[key] = (light, height)
        return self._lights[key]

    def shaded(self, rgb: np.ndarray, relief: Relief | None) -> np.ndarray:
        """rgb (float) darkened by the relief where the grids agree in shape."""
        rgb = rgb.astype(np.float64)
        lit = self.light(relief) if relief is not None else None
        if lit is not None and lit[0].shape == rgb.shape[:2]:
            rgb *= ((1.0 - relief.strength) + relief.strength * lit[0])[..., None]
        return np.clip(rgb, 0, 255).astype(np.uint8)

    def channels(self, stage: str, key: str, m: dict, d: ReportMap) -> None:
        """A map per channel the declaration matches, on a colour ramp."""
        meta = self.world.output(stage, key, m, d.artifact)
        if meta is None:
            return
        grid = self.world.read(stage, key, meta)
        ramp = _palette(d.palette)
        units = meta.get("channel_units", {})
        for channel, bound in _matches(d.channel, grid.channels):
            fields = {"artifact": d.artifact, "channel": channel, **bound}
            name = d.name.format(**fields)
            v = grid.channel(channel).astype(np.float64)
            lo, hi = _value_range(v, d.values)
            legend = self.colour_bar(name, ramp, lo, hi, d.units if d.units is not None else units.get(channel, ""))
            if d.note:
                legend += f'<div class="note">{html.escape(d.note.format(**fields))}</div>'
            self.add(name, d.title.format(**fields), self.shaded(ramp((v - lo) / (hi - lo)), d.relief),
                     grid.cell_size_m, grid.shape, legend)

    def categorical(self, stage: str, key: str, m: dict, d: ReportMap) -> None:
        """One map of the category of the largest weight per cell, with
        each category's share of the cells."""
        meta = self.world.output(stage, key, m, d.artifact)
        if meta is None:
            return
        grid = self.world.read(stage, key, meta)
        found = _matches(d.channel, grid.channels)
        if not found:
            return
        kinds = [next(iter(bound.values()), channel) for channel, bound in found]
        top = np.argmax(np.stack([grid.channel(c) for c, _ in found], axis=-1), axis=-1)
        colours = dict(d.categories)
        palette = np.array([colours.get(k, GREY) for k in kinds], np.float64)
        share = np.bincount(top.ravel(), minlength=len(kinds)) / top.size
        legend = _legend((palette[i], f"{k} {100 * share[i]:.1f} %") for i, k in enumerate(kinds))
        fields = {"artifact": d.artifact, "channel": d.channel}
        self.add(d.name.format(**fields), d.title.format(**fields), self.shaded(palette[top], d.relief),
                 grid.cell_size_m, grid.shape, legend)

    def drawn(self, d: DrawnMap, world_usda: Path | None) -> None:
        """A map the stage draws from the composed world over the relief."""
        lit = self.light(d.relief) if world_usda is not None else None
        if lit is None:
            return
        light, height = lit
        base = _upscale(light)
        frame = MapFrame(base, height.origin_m, height.shape[1] * height.cell_size_m / base.shape[1])
        drawn = d.draw(world_usda, frame)
        self.add(d.name, d.title, np.asarray(drawn.rgb, np.uint8), height.cell_size_m, height.shape,
                 _legend(drawn.legend))


# --------------------------------------------------------------------------- pictures and tables of the world


def pictures(world: World, out: Path, world_usda: Path | None, problems: list[str]) -> str:
    """The declared pictures of the composed world, as figures."""
    parts, cl = [], None
    for stage, _, _, p in world.declared(ReportPicture) if world_usda is not None else ():
        file = f"report_{p.name}.png"
        try:
            if cl is None:
                from .opencl import get_cl  # the engine's device: the pictures render on it

                cl = get_cl()
            caption = p.make(world_usda, out / file, cl)
            width, height = _png_size(out / file)
        except Exception as e:  # the page still shows everything else
            problems.append(f"report: {stage}: the picture {p.name} failed: {type(e).__name__}: {e}")
            continue
        parts.append(f'<figure><img src="{file}" alt="the world" width="{width}" height="{height}">'
                     f'<figcaption class="note">{html.escape(caption)}</figcaption></figure>')
    return "".join(parts)


def _cell(v: Any, tag: str = "td") -> str:
    if v is None:
        return f"<{tag}>-</{tag}>"
    if isinstance(v, tuple):
        value, note = v
        return f"<{tag} class=num>{_fmt(value)} <span class=note>{html.escape(note)}</span></{tag}>"
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return f"<{tag} class=num>{_fmt(v)}</{tag}>"
    return f"<{tag}>{html.escape(str(v))}</{tag}>"


def table_html(t: Table) -> str:
    rows = "".join("<tr>" + "".join(_cell(v) for v in r) + "</tr>" for r in t.rows)
    footer = "<tr>" + "".join(_cell(v, "th") for v in t.footer) + "</tr>" if t.footer else ""
    note = f"<p class='note'>{html.escape(t.note)}</p>" if t.note else ""
    return ("<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in t.columns) + "</tr>"
            + rows + footer + "</table>" + note)


def tables(world: World, world_usda: Path | None, problems: list[str]) -> str:
    """The declared sections of tables about the composed world."""
    parts = []
    for stage, _, _, t in world.declared(ReportTable) if world_usda is not None else ():
        try:
            made = t.make(world_usda)
        except Exception as e:  # the page still shows everything else
            problems.append(f"report: {stage}: the tables {t.title!r} failed: {type(e).__name__}: {e}")
            continue
        if made:
            parts.append(f"<h2>{html.escape(t.title)}</h2>" + "".join(table_html(x) for x in made))
    return "".join(parts)


# --------------------------------------------------------------------------- stage table, series, warnings


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


def warnings(world: World) -> list[str]:
    """The runs' failed checks and warnings, the declared warnings of the
    stages that ran, and --set overrides whose stage did not run."""
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
    for stage, key, m, w in world.declared(ReportWarning):
        meta = world.output(stage, key, m, w.artifact)
        if meta is None:
            continue
        grid = world.read(stage, key, meta)
        for channel, bound in _matches(w.channel, grid.channels):
            if not (grid.channel(channel) > 0).any():
                out.append(f"{stage}: " + w.message.format(channel=channel, **bound))
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


def _head(manifest: dict) -> str:
    e = html.escape
    overrides = manifest.get("overrides", {})
    return (f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>worldbake: {e(manifest['world'])}</title>"
            f"<style>{CSS}</style></head><body>"
            f"<h1>World {e(manifest['world'])}</h1>"
            f"<p>Config <code>{e(str(manifest.get('config')))}</code>"
            + (f" variant <code>{e(manifest['variant'])}</code>" if manifest.get("variant") else "")
            + f", seed {manifest.get('seed')}, outputs {e(', '.join(manifest.get('outputs', [])))}. Overrides: "
            + (", ".join(f"<code>{e(k)}={e(json.dumps(v))}</code>" for k, v in overrides.items()) or "none") + ".</p>")


def _maps_html(items: list[dict]) -> str:
    if not items:
        return ""
    e = html.escape
    figures = "".join(f'<figure><figcaption>{e(m["title"])}</figcaption><img src="{m["file"]}" alt="{e(m["title"])}" '
                      f'width="{m["px"]}" height="{m["py"]}">{m["legend"]}{_scale_bar(m["width_m"], m["px"])}</figure>'
                      for m in items)
    return (f'<h2>Maps</h2><div class="maps">{figures}</div>'
            "<p class='note'>North is up; x grows east. Shaded by the terrain's hillshade.</p>")


def _stages_html(rows: list[dict]) -> str:
    e = html.escape
    parts = ["<h2>Stages</h2><table><tr><th>stage</th><th>this bake</th><th>seconds</th><th>run s</th><th>key</th>"
             "<th>errors</th><th>statistics</th></tr>"]
    for r in rows:
        errs = "<br>".join(f"{e(k)} = {_fmt(v)}" for k, v in r["errors"].items()) or "-"
        stats = "".join(f"<tr><td>{e(k)}</td><td class=num>{_fmt(v)}</td></tr>" for k, v in r["stats"].items())
        parts.append(f"<tr><td>{e(r['stage'])}</td><td>{e(r['status'])}</td><td class=num>{_fmt(r['seconds'])}</td>"
                     f"<td class=num>{_fmt(r['run_s'])}</td><td><code>{e(r['key'])}</code></td>"
                     f"<td><details><summary>{len(r['errors'])}</summary>{errs}</details></td>"
                     f"<td><details><summary>{len(r['stats'])} values</summary><table>{stats}</table></details></td></tr>")
    parts.append("</table><p class='note'>seconds: this bake's time for the step (0 when cached); run s: the time "
                 "of the run that made the artifacts.</p>")
    return "".join(parts)


IMAGE_SRC = re.compile(r'<img src="([^"]+)"')  # the images a page names
REPORT_CACHE = "report_cache.json"  # beside report.html: what a bake of the same runs and world layer reuses


def report_key(world: World, world_usda: Path | None) -> str:
    """What the report's figures depend on: the runs (their keys, which
    follow their stages' code, report callables included), the overrides
    (warned of when they had no effect), the composed layer's bytes and the
    engine's code (this module and what it reads grids with). This bake's
    steps (ran or cached, seconds) are not in it: their table is remade."""
    from .sources import normalized

    h = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        h.update(path.name.encode() + b"\0" + normalized(path) + b"\0")
    material = {"runs": [[stage, key] for stage, key, _ in world.runs], "uses": world.manifest.get("uses"),
                "overrides": world.manifest.get("overrides"), "engine": h.hexdigest(),
                "layer": sha256_file(world_usda) if world_usda is not None else None,
                "stages": {name: len(getattr(st, "report", ())) for name, st in sorted(world.stages.items())}}
    return hashlib.sha256(json.dumps(material, sort_keys=True).encode()).hexdigest()


def _figures(world: World, out: Path, world_usda: Path | None) -> dict:
    """The report's parts that read the runs' files and the layer: pictures,
    maps, tables, warnings and the time-error plots, as HTML."""
    problems: list[str] = []
    view = pictures(world, out, world_usda, problems)
    maps = Maps(world, out)
    maps.build(world_usda)
    problems += maps.problems
    sections = tables(world, world_usda, problems)
    return {"view": view, "maps": _maps_html(list(maps.items.values())), "sections": sections,
            "warnings": problems + warnings(world), "plots": [svg_plot(s) for s in time_error_series(world)]}


def _cached_figures(out: Path, key: str) -> dict | None:
    """The figures of out's last report when it was made of the same runs
    and layer and every picture it names is still there."""
    try:
        cached = json.loads((out / REPORT_CACHE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(cached, dict) or cached.get("key") != key or not isinstance(cached.get("figures"), dict):
        return None
    figures = cached["figures"]
    html_parts = str(figures.get("view", "")) + str(figures.get("maps", ""))
    if not all((out / name).is_file() for name in IMAGE_SRC.findall(html_parts)):
        return None
    return figures


def carry_figures(old: Path, new: Path) -> None:
    """Copy the last report's figures (REPORT_CACHE and report_*.png) from a
    world's folder into the one replacing it, for write_report to reuse."""
    import shutil

    if (old / REPORT_CACHE).is_file():
        for path in [old / REPORT_CACHE, *old.glob("report_*.png")]:
            shutil.copy2(path, new / path.name)


def write_report(store: Store, out: Path, manifest: dict, world_usda: Path | None,
                 stages: dict[str, Stage] | None = None) -> Path:
    """Write report.html and its report_*.png into `out` (the world folder
    being published: `world_usda` is the layer as it will be found). The
    stages' declarations are the registry's unless given. The figures of
    the last report in `out` are reused when its runs and layer are the same
    (report_key; publish_world carries them over): a bake with every stage
    cached remakes only the page and its table of steps."""
    world = World(store, manifest, stages)
    if world_usda is not None and not world_usda.is_file():
        world_usda = None
    key = report_key(world, world_usda)
    figures = _cached_figures(out, key)
    if figures is None:
        for old in out.glob("report_*.png"):
            old.unlink()
        figures = _figures(world, out, world_usda)
        write_json(out / REPORT_CACHE, {"key": key, "figures": figures})
    view, warns = figures["view"], figures["warnings"]
    parts = [_head(manifest), "<h2>Warnings</h2>" + (
        '<div class="warn"><ul>' + "".join(f"<li>{html.escape(w)}</li>" for w in warns) + "</ul></div>"
        if warns else '<p class="ok">none</p>')]
    if view:
        parts.append("<h2>The world</h2>" + view)
    parts += [figures["maps"], _stages_html(stage_rows(world)), figures["sections"]]
    if figures["plots"]:
        parts.append('<h2>Run time against error</h2><div class="maps">' + "".join(figures["plots"]) + "</div>")
    parts.append("</body></html>\n")
    path = out / "report.html"
    path.write_text("".join(parts))
    return path


def referenced_images(report_html: Path) -> list[str]:
    """Every image file the page names (for tests and exports)."""
    return IMAGE_SRC.findall(report_html.read_text())
