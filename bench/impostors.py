"""Benchmark of the impostor atlases: bake time against held-out error (not
part of `make test`).

    python -m bench.impostors                      # every placed species of the newest plants artifact, the full sweep
    python -m bench.impostors --species conifer --frames 16 --atlas 1024 --out bench/out/impostors.png
    python -m bench.impostors --agreement          # the bake's cheap held-out measure against the whole 5-degree set
    python -m bench.impostors --pictures bench/out/impostors   # mesh, impostor, slices side by side per species
    python -m bench.impostors --popping            # how much the impostor jumps between 1-degree steps, against the mesh
    python -m bench.impostors --drawn              # the Impostor prim's sheet: bake time against IoU per tile size and slabs

Sweep: for each species of a plants layer (the newest build/artifacts/plants
run, or --plants PATH; --species to choose) and every combination of frames
in {8, 12, 16}, atlas side in {1024, 2048, 4096} and layout in {octahedral,
hemi}, it bakes the view atlas (stages.impostors.atlas: the largest frames
that fit the atlas, the stage's samples and AO) and measures it from the
held-out views of stages.impostors.heldout: the 5-degree set (azimuth every
5 degrees, elevation every 10 from 0 (hemi) or -80 (octahedral) to 80), the
lattice share 1/--stride of it (the stage's), --view-px views against the
mesh rendered once per view and species with --reference-samples^2 samples.
One size for every setting, so the rows compare. The settings run cheapest
first (atlas side, then frames, then species), so a sweep stopped early
still covers every species. It prints one row per species and setting
(bake seconds wall and CPU: the machine may be shared, frame size, median and worst PSNR and IoU, median depth
RMSE, worst view) and plots bake CPU seconds against median IoU and PSNR (PNG,
--out, redrawn after every row).

--drawn: per tree and shrub species, the sheet a DCC draws (every quad at
once, alpha-tested at 0.5) for tiles of {0.5, 1, 2} x the frame side and
{8, 16} slabs: its bake seconds (wall and CPU) and its held-out IoU (the
lattice) at 2 x the frame side, one texel per pixel of the default tiles,
against the mesh at the stage's reference samples.

--agreement: per species, the stage's default atlas (its frame size,
stages.impostors.stage.plant_frame_px) measured the way the bake does (the
lattice at the frame's size) and the expensive way (all 648 / 1224 views,
--full-px views, --full-samples^2 reference samples): medians side by side.
"""
from __future__ import annotations

import argparse
import glob
import itertools
import json
import time
from pathlib import Path

import numpy as np


def newest_plants_layer() -> Path:
    found = sorted(glob.glob("build/artifacts/plants/*/plants.usda"), key=lambda p: Path(p).stat().st_mtime)
    if not found:
        raise SystemExit("no plants artifact in build/: run `make bake` first or give --plants")
    return Path(found[-1])


def placed_species(layer: Path) -> list[str] | None:
    """The species the newest vegetation run placed (None: no vegetation artifact)."""
    found = sorted(glob.glob(str(layer.parents[2] / "vegetation" / "*" / "placed.json")),
                   key=lambda p: Path(p).stat().st_mtime)
    return json.loads(Path(found[-1]).read_text())["placed"] if found else None


class Plant:
    """A species' scene, BVH and mesh reference views (rendered once per view set)."""

    def __init__(self, layer: Path, name: str):
        from pipeline.opencl import get_cl
        from worldlib.render import Prepared
        from worldlib.render.usd_asset import load_plant

        self.name = name
        self.ps = load_plant(layer, f"/Plants/{name}")
        self.prepared = Prepared(get_cl(), self.ps.scene)
        self.height = float(self.ps.hi[1] - self.ps.lo[1])
        self.references: dict = {}

    def reference(self, az: float, el: float, px: int, samples: int):
        from stages.impostors import heldout, octahedral

        key = (az, el, px, samples)
        if key not in self.references:
            m = heldout.mesh_view(self.prepared, octahedral.view_direction(az, el), self.ps.centre, self.ps.radius,
                                  px, samples)
            self.references[key] = (np.concatenate([m.albedo, m.alpha[..., None]], -1), m.depth)
        return self.references[key]

    def default_atlas(self, defaults):
        """The atlas the stage bakes of this plant at `defaults` (its layout, its frame size)."""
        from stages.impostors import atlas
        from stages.impostors.stage import plant_frame_px

        layout = defaults.layouts.get(self.name, defaults.layout)
        px = plant_frame_px(self.ps.radius, self.height, defaults)
        return atlas.build(self.prepared, self.ps.centre, self.ps.radius, defaults.frames, defaults.atlas_px, layout,
                           defaults.samples, defaults.ao_rays, defaults.padding_px, seed=1,
                           ao_radius=defaults.ao_radius, frame_px=px)

    def measure(self, at, views, px: int, samples: int, depth_steps: int) -> dict:
        from stages.impostors import heldout, octahedral, sampler

        errors = []
        for az, el in heldout.held_out(views, at.directions):
            rgba, depth = self.reference(az, el, px, samples)
            v = sampler.render_view(at, octahedral.view_direction(az, el), px, depth_steps)
            errors.append(heldout.ViewError(az, el, *heldout.compare(rgba, depth, v.rgba, v.depth)))
        return heldout.summarize(errors, self.height)


def _row(name, layout, frames, atlas_px, frame_px, bake_s, bake_cpu_s, s) -> str:
    w = s["worst_view"]
    return (f"{name:14s} {layout:10s} {frames:6d} {atlas_px:5d} {frame_px:5d} {bake_s:7.2f} {bake_cpu_s:7.2f} "
            f"{s['views']:5d} "
            f"{s['psnr_db']['median']:8.2f} {s['psnr_db']['min']:8.2f} {s['alpha_iou']['median']:7.3f} "
            f"{s['alpha_iou']['min']:7.3f} {s['depth_rmse_m']['median']:7.3f}  ({w['azimuth_deg']:.0f}, "
            f"{w['elevation_deg']:.0f})")


HEADER = (f"{'species':14s} {'layout':10s} {'frames':>6s} {'atlas':>5s} {'frame':>5s} {'bake s':>7s} {'CPU s':>7s} "
          f"{'views':>5s} "
          f"{'PSNR med':>8s} {'PSNR min':>8s} {'IoU med':>7s} {'IoU min':>7s} {'depth m':>7s}  worst view (az, el)")


def agreement(plants: list, args, defaults) -> None:
    """The bake's measure (lattice at the frame's size) against the whole set."""
    from stages.impostors import heldout

    full = f"{args.full_px} px" if args.full_px else "the frame's size"
    print(f"agreement: the stage's default atlas of each species; cheap = lattice 1/{defaults.heldout_stride} at the "
          f"frame's size, {defaults.heldout_samples}^2 reference samples; full = every view at {full}, "
          f"{args.full_samples}^2 samples")
    print(f"{'species':14s} {'measure':8s} {'views':>5s} {'px':>4s} {'IoU med':>7s} {'IoU min':>7s} {'PSNR med':>8s} "
          f"{'PSNR min':>8s} {'seconds':>7s}")
    for plant in plants:
        layout = defaults.layouts.get(plant.name, defaults.layout)
        at = plant.default_atlas(defaults)
        view_px = min(at.frame_px, defaults.heldout_px)
        for label, views, px, samples in (
                ("cheap", heldout.lattice(layout, defaults.heldout_stride), view_px, defaults.heldout_samples),
                ("full", heldout.lattice(layout, 1), args.full_px or view_px, args.full_samples)):
            t0 = time.perf_counter()
            s = plant.measure(at, views, px, samples, defaults.depth_steps)
            print(f"{plant.name:14s} {label:8s} {s['views']:5d} {px:4d} {s['alpha_iou']['median']:7.3f} "
                  f"{s['alpha_iou']['min']:7.3f} {s['psnr_db']['median']:8.2f} {s['psnr_db']['min']:8.2f} "
                  f"{time.perf_counter() - t0:7.1f}", flush=True)


def drawn_sweep(plants: list, args, defaults) -> None:
    """Bake time against held-out IoU of the drawn sheet per tile size and slab count."""
    from pipeline.opencl import get_cl
    from stages.impostors import heldout, measure, slices
    from stages.impostors.stage import plant_frame_px
    from worldlib.render import Prepared, Settings

    cl_env = get_cl()
    print(f"drawn sheet: held-out lattice 1/{args.stride}, views of 2 x the frame side, reference "
          f"{defaults.heldout_samples}^2 samples, {defaults.samples}^2 samples per texel")
    print(f"{'species':14s} {'tile':>5s} {'slabs':>5s} {'view':>5s} {'bake s':>7s} {'CPU s':>7s} {'IoU med':>7s} "
          f"{'IoU min':>7s} {'PSNR med':>8s}")
    for plant in plants:
        if "Blades" in plant.ps.parts:
            continue  # grass: seed 001's tuft, no slabs
        frame_px = plant_frame_px(plant.ps.radius, plant.height, defaults)
        view_px = 2 * frame_px
        layout = defaults.layouts.get(plant.name, defaults.layout)
        views = heldout.lattice(layout, args.stride)
        refs = measure.References(plant.prepared, plant.ps, views, view_px, defaults.heldout_samples)
        for tile, slabs in itertools.product((frame_px // 2, frame_px, 2 * frame_px), (8, 16)):
            t0, c0 = time.perf_counter(), time.process_time()
            sheet = slices.tree_slices(plant.prepared, slabs, tile, defaults.samples)
            bake_s, bake_cpu_s = time.perf_counter() - t0, time.process_time() - c0
            drawn = Prepared(cl_env, slices.sheet_scene([sheet]))
            view = measure.drawn_view(drawn, plant.ps, Settings(view_px, view_px, samples=defaults.heldout_samples))
            s = heldout.summarize(refs.measure(view), plant.height)
            print(f"{plant.name:14s} {tile:5d} {slabs:5d} {view_px:5d} {bake_s:7.2f} {bake_cpu_s:7.2f} "
                  f"{s['alpha_iou']['median']:7.3f} {s['alpha_iou']['min']:7.3f} {s['psnr_db']['median']:8.2f}",
                  flush=True)


PICTURE_VIEWS = ((35.0, 0.0), (35.0, 30.0), (215.0, 55.0), (125.0, 80.0))  # held-out (azimuth, elevation)
BACKGROUND = np.array([0.78, 0.83, 0.9])


def pictures(plants: list, out_dir: Path, defaults, scale: int) -> None:
    """Per species a PNG: one row per view of PICTURE_VIEWS, columns the mesh
    (6x6 samples), the impostor (the stage's default atlas, 3-frame blend),
    the slices blended as seed 002's shader does, the slices as a USD viewer
    draws them (every quad, alpha-tested), and the alpha masks at 0.5 of
    mesh and impostor (white both, red the mesh only, blue the impostor
    only); every view at the frame's size, enlarged `scale` times."""
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from pipeline import exr
    from worldlib.render import Prepared, Settings
    from stages.impostors import heldout, octahedral, sampler, slices

    out_dir.mkdir(parents=True, exist_ok=True)
    for plant in plants:
        layout = defaults.layouts.get(plant.name, defaults.layout)
        at = plant.default_atlas(defaults)
        px = at.frame_px
        grass = "Blades" in plant.ps.parts
        slice_px = min(defaults.slice_px, max(px // 2, 8))
        sheets = ([*slices.grass_slices(plant.prepared, defaults.grass_slice_px, defaults.samples)] if grass
                  else [slices.tree_slices(plant.prepared, defaults.slice_slabs, slice_px, defaults.samples)])
        drawn = Prepared(cl_env, slices.sheet_scene(sheets))
        rows_of = {} if grass else {r: Prepared(cl_env, slices.sheet_scene(sheets, rows=(r,))) for r in range(sheets[0].rows)}
        settings = Settings(px, px, samples=defaults.heldout_samples)

        def over(rgba):
            return rgba[..., :3] + (1.0 - rgba[..., 3:4]) * BACKGROUND

        def rgba_of(img):
            return np.concatenate([img.albedo, img.alpha[..., None]], -1)

        grid = []
        for az, el in PICTURE_VIEWS:
            d = octahedral.view_direction(az, el)
            mesh, _ = plant.reference(az, el, px, defaults.heldout_samples)
            imp = sampler.render_view(at, d, px, defaults.depth_steps).rgba
            cam, _ = heldout.view_camera(d, plant.ps.centre, plant.ps.radius)
            drawn_rgba = rgba_of(drawn.render(cam, settings))
            blend = drawn_rgba if grass else sum(w * rgba_of(rows_of[r].render(cam, settings))
                                                 for r, w in slices.slicing_weights(d))
            ma, ia = mesh[..., 3] >= 0.5, imp[..., 3] >= 0.5
            mask = np.zeros((px, px, 3))
            mask[ma & ia] = 1.0
            mask[ma & ~ia] = (1.0, 0.15, 0.1)
            mask[~ma & ia] = (0.1, 0.3, 1.0)
            grid.append(np.concatenate([over(mesh), over(imp), over(blend), over(drawn_rgba), mask], 1))
        img = np.concatenate(grid, 0)
        img = np.repeat(np.repeat(img, scale, 0), scale, 1)
        srgb = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.clip(img, 0, 1) ** (1 / 2.4) - 0.055)
        path = out_dir / f"{plant.name}_mesh_impostor_slices.png"
        exr.write_png(path, np.round(np.clip(srgb, 0, 1) * 255).astype(np.uint8))
        print(f"{path}: rows (azimuth, elevation) {', '.join(f'({a:.0f}, {e:.0f})' for a, e in PICTURE_VIEWS)}; "
              f"columns mesh, impostor ({defaults.frames}x{defaults.frames} {layout}, {px} px frames), slices "
              f"blended, slices as drawn, masks (white both, red mesh only, blue impostor only)", flush=True)


def popping(plants: list, defaults, elevations=(10.0, 40.0, 70.0), span_deg: int = 60) -> None:
    """Seams and popping between blended frames (seed 002's temporal measure):
    the stage's default atlas seen along a sweep of 1-degree azimuth steps at
    a few elevations, each step's mean absolute change of premultiplied RGBA
    per pixel, for the impostor and for the mesh (6x6 samples), at the
    frame's size. mean ratio: impostor / mesh over the sweep (1: the
    impostor changes as smoothly as the mesh); worst jump: the largest
    single step of the impostor over the mesh's mean step (a frame switch
    that pops shows here)."""
    from stages.impostors import octahedral, sampler

    print(f"popping: 1-degree azimuth steps over {span_deg} deg at elevations {', '.join(f'{e:.0f}' for e in elevations)}; "
          f"views at the frame's size, the mesh with {defaults.heldout_samples}^2 samples")
    print(f"{'species':14s} {'el':>4s} {'mesh step':>9s} {'imp step':>9s} {'mean ratio':>10s} {'worst jump':>10s}")
    for plant in plants:
        at = plant.default_atlas(defaults)
        px = at.frame_px
        for el in elevations:
            mesh, imp = [], []
            for az in range(span_deg + 1):
                rgba, _ = plant.reference(float(az), el, px, defaults.heldout_samples)
                mesh.append(rgba.astype(np.float64))
                imp.append(sampler.render_view(at, octahedral.view_direction(float(az), el), px,
                                               defaults.depth_steps).rgba.astype(np.float64))
            dm = np.array([np.abs(b - a).mean() for a, b in zip(mesh, mesh[1:])])
            di = np.array([np.abs(b - a).mean() for a, b in zip(imp, imp[1:])])
            print(f"{plant.name:14s} {el:4.0f} {dm.mean():9.5f} {di.mean():9.5f} {di.mean() / dm.mean():10.3f} "
                  f"{di.max() / dm.mean():10.3f}", flush=True)


def main() -> None:
    from stages.impostors import atlas, heldout
    from stages.impostors.stage import ImpostorsParams

    defaults = ImpostorsParams()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plants", type=Path, default=None)
    ap.add_argument("--species", nargs="*", default=None, help="default: the species the vegetation map placed")
    ap.add_argument("--frames", nargs="*", type=int, default=[8, 12, 16])
    ap.add_argument("--atlas", nargs="*", type=int, default=[1024, 2048, 4096])
    ap.add_argument("--layouts", nargs="*", default=["octahedral", "hemi"])
    ap.add_argument("--stride", type=int, default=defaults.heldout_stride, help="the lattice share of the 5-degree set")
    ap.add_argument("--view-px", type=int, default=64)
    ap.add_argument("--reference-samples", type=int, default=defaults.heldout_samples)
    ap.add_argument("--agreement", action="store_true")
    ap.add_argument("--full-px", type=int, default=0, help="--agreement: size of the full set's views (0: the frame's)")
    ap.add_argument("--full-samples", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path("bench/out/impostors.png"))
    ap.add_argument("--pictures", type=Path, default=None, help="write mesh / impostor / slices pictures here instead")
    ap.add_argument("--scale", type=int, default=3, help="--pictures: enlargement of the frame-sized views")
    ap.add_argument("--popping", action="store_true", help="measure seams and popping between frames instead")
    ap.add_argument("--drawn", action="store_true", help="the drawn sheet's bake time against IoU instead")
    args = ap.parse_args()
    layer = args.plants or newest_plants_layer()
    from pxr import Sdf

    plants_layer = Sdf.Layer.FindOrOpen(str(layer))
    names = [c.name for c in plants_layer.GetPrimAtPath("/Plants").nameChildren]
    chosen = args.species if args.species is not None else placed_species(layer)
    names = [n for n in names if chosen is None or n in chosen]
    plants = {n: Plant(layer, n) for n in names}
    if args.agreement:
        agreement(list(plants.values()), args, defaults)
        return
    if args.popping:
        popping(list(plants.values()), defaults)
        return
    if args.drawn:
        drawn_sweep(list(plants.values()), args, defaults)
        return
    if args.pictures:
        pictures(list(plants.values()), args.pictures, defaults, args.scale)
        return
    print(f"plants layer {layer}; species {', '.join(names)}; samples {defaults.samples}^2, "
          f"AO rays {defaults.ao_rays}; "
          f"held-out: 1/{args.stride} of the 5-degree set at {args.view_px} px, reference {args.reference_samples}^2 "
          "samples")
    print(HEADER)
    rows = []
    settings = itertools.product(sorted(args.atlas), sorted(args.frames), names, args.layouts)
    for atlas_px, frames, name, layout in settings:
        plant = plants[name]
        t0, c0 = time.perf_counter(), time.process_time()
        at = atlas.build(plant.prepared, plant.ps.centre, plant.ps.radius, frames, atlas_px, layout, defaults.samples,
                         defaults.ao_rays, defaults.padding_px, seed=1, ao_radius=defaults.ao_radius)
        # CPU seconds of every thread (the OpenCL runtime's too): wall time on a shared machine is noise
        bake_s, bake_cpu_s = time.perf_counter() - t0, time.process_time() - c0
        s = plant.measure(at, heldout.lattice(layout, args.stride), args.view_px, args.reference_samples,
                          defaults.depth_steps)
        print(_row(name, layout, frames, atlas_px, at.frame_px, bake_s, bake_cpu_s, s), flush=True)
        rows.append((name, layout, frames, atlas_px, bake_cpu_s, s))
        caption = _plot(rows, args.out)  # after every row: a long sweep stopped early still leaves its picture
    if rows:
        print(caption)


COLOURS = [(0.85, 0.3, 0.2), (0.2, 0.55, 0.85), (0.25, 0.7, 0.3), (0.8, 0.6, 0.1), (0.6, 0.3, 0.75)]


def _plot(rows, out: Path) -> str:
    """Two panels drawn with numpy and OpenImageIO's text (no plotting
    library in the project): left median IoU (0.5 .. 1), right median PSNR
    (15 .. 45 dB), both against bake CPU seconds on a log axis; one colour
    per species, squares for octahedral, crosses for hemi, bigger marks for
    bigger atlases; grey lines at IoU 0.9 and 25 dB; labelled axes and a
    legend."""
    import OpenImageIO as oiio

    W, H, left, right, top, bottom = 460, 360, 52, 12, 28, 44
    img = np.ones((H + 40, 2 * W, 3))
    t = np.log10([max(r[4], 1e-3) for r in rows])
    t0, t1 = float(t.min()) - 0.1, float(t.max()) + 0.1
    species = sorted({r[0] for r in rows})
    texts = []  # (x, y, text, size, colour)

    def xpix(x0, tr):
        return int(x0 + left + (tr - t0) / (t1 - t0) * (W - left - right))

    for panel, (key, lo, hi, line, label, ticks) in enumerate((
            ("alpha_iou", 0.5, 1.0, 0.9, "median held-out IoU", (0.5, 0.6, 0.7, 0.8, 0.9, 1.0)),
            ("psnr_db", 15.0, 45.0, 25.0, "median held-out PSNR, dB", (15, 20, 25, 30, 35, 40, 45)))):
        x0 = panel * W

        def ypix(v):
            return int(H - bottom - (np.clip(v, lo, hi) - lo) / (hi - lo) * (H - top - bottom))

        img[top:H - bottom + 1, x0 + left] = 0.0
        img[H - bottom, x0 + left:x0 + W - right] = 0.0
        img[ypix(line), x0 + left + 1:x0 + W - right] = 0.6
        for v in ticks:
            img[ypix(v), x0 + left - 4:x0 + left] = 0.0
            texts.append((x0 + 4, ypix(v) + 5, f"{v:g}", 13, (0, 0, 0)))
        for dec in range(int(np.floor(t0)), int(np.ceil(t1)) + 1):
            for m in (1, 2, 5):
                tr = dec + np.log10(m)
                if t0 <= tr <= t1:
                    img[H - bottom:H - bottom + (5 if m == 1 else 3), xpix(x0, tr)] = 0.0
                    if m in (1, 2, 5):
                        texts.append((xpix(x0, tr) - 6, H - bottom + 18, f"{10 ** tr:g}", 13, (0, 0, 0)))
        texts.append((x0 + left + 4, top - 10, label, 15, (0, 0, 0)))
        texts.append((x0 + left + 90, H - 8, "bake CPU seconds (log)", 14, (0, 0, 0)))
        for r, tr in zip(rows, t):
            x, y = xpix(x0, tr), ypix(r[5][key]["median"])
            c = COLOURS[species.index(r[0]) % len(COLOURS)]
            k = 1 + r[3] // 1024
            if r[1] == "octahedral":
                img[max(y - k, 0):y + k + 1, max(x - k, 0):x + k + 1] = c
            else:
                for d in range(-k - 1, k + 2):
                    img[np.clip(y + d, 0, H - 1), np.clip(x + d, 0, 2 * W - 1)] = c
                    img[np.clip(y - d, 0, H - 1), np.clip(x + d, 0, 2 * W - 1)] = c
    lx = left
    for i, name in enumerate(species):
        c = COLOURS[i % len(COLOURS)]
        img[H + 14:H + 24, lx:lx + 10] = c
        texts.append((lx + 14, H + 24, name, 14, c))
        lx += 30 + 8 * len(name)
    texts.append((lx + 10, H + 24, "square: octahedral, cross: hemi; mark size: atlas 1024 / 2048 / 4096", 13,
                  (0, 0, 0)))
    buf = oiio.ImageBuf(np.ascontiguousarray(img, np.float32))
    for x, y, text, size, colour in texts:
        oiio.ImageBufAlgo.render_text(buf, int(x), int(y), text, int(size), "", tuple(float(v) for v in colour))
    out.parent.mkdir(parents=True, exist_ok=True)
    pixels = np.round(np.clip(np.asarray(buf.get_pixels(oiio.FLOAT)), 0, 1) * 255).astype(np.uint8)
    from pipeline import exr

    exr.write_png(out, pixels)
    return (f"plot: {out} (x: bake CPU s, log, {10 ** t0:.3g} to {10 ** t1:.3g}; left median IoU 0.5..1, right "
            f"median PSNR 15..45 dB; colours {', '.join(species)}; squares octahedral, crosses hemi, size ~ atlas)")


if __name__ == "__main__":
    main()
