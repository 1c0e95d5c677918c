"""Benchmark of the impostor atlases: bake time against held-out error (not
part of `make test`).

    python -m bench.impostors                      # every species of the newest plants artifact, the full sweep
    python -m bench.impostors --species conifer --azimuth-every 3 --out bench/out/impostors.png

For each species of a plants layer (the newest build/artifacts/plants run,
or --plants PATH) and every combination of frames in {8, 12, 16}, atlas
side in {1024, 2048, 4096} and layout in {octahedral, hemi}, it bakes the
view atlas (stages.impostors.atlas, the stage's samples and AO) and
measures it from the held-out views of stages.impostors.heldout: azimuth
every 5 degrees (every --azimuth-every-th of them), elevation every 10
degrees from 0 (hemi) or -80 (octahedral) to 80, the mesh rendered once
per view and species with --reference-samples^2 samples per pixel at
--view-px. It prints one table row per species and setting (bake seconds,
frame size, median and worst PSNR and IoU, median depth RMSE, worst view)
and plots bake seconds against median IoU and PSNR (PNG, --out).
"""
from __future__ import annotations

import argparse
import glob
import itertools
import time
from pathlib import Path

import numpy as np


def newest_plants_layer() -> Path:
    found = sorted(glob.glob("build/artifacts/plants/*/plants.usda"), key=lambda p: Path(p).stat().st_mtime)
    if not found:
        raise SystemExit("no plants artifact in build/: run `make bake` first or give --plants")
    return Path(found[-1])


def main() -> None:
    from pipeline.render import Prepared
    from stages.impostors import asset_scene, atlas, heldout, octahedral, sampler
    from stages.impostors.stage import ImpostorsParams

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plants", type=Path, default=None)
    ap.add_argument("--species", nargs="*", default=None)
    ap.add_argument("--frames", nargs="*", type=int, default=[8, 12, 16])
    ap.add_argument("--atlas", nargs="*", type=int, default=[1024, 2048, 4096])
    ap.add_argument("--layouts", nargs="*", default=["octahedral", "hemi"])
    ap.add_argument("--azimuth-every", type=int, default=1, help="keep every k-th 5-degree azimuth")
    ap.add_argument("--view-px", type=int, default=ImpostorsParams().heldout_px)
    ap.add_argument("--reference-samples", type=int, default=ImpostorsParams().heldout_samples)
    ap.add_argument("--out", type=Path, default=Path("bench/out/impostors.png"))
    args = ap.parse_args()
    defaults = ImpostorsParams()
    layer = args.plants or newest_plants_layer()
    from pxr import Sdf

    plants = Sdf.Layer.FindOrOpen(str(layer))
    names = [c.name for c in plants.GetPrimAtPath("/Plants").nameChildren]
    names = [n for n in names if args.species is None or n in args.species]
    print(f"plants layer {layer}; samples {defaults.samples}^2, AO rays {defaults.ao_rays}, held-out views at "
          f"{args.view_px} px, reference {args.reference_samples}^2 samples, azimuth every {5 * args.azimuth_every} deg")
    print(f"{'species':14s} {'layout':10s} {'frames':>6s} {'atlas':>5s} {'frame':>5s} {'bake s':>7s} {'views':>5s} "
          f"{'PSNR med':>8s} {'PSNR min':>8s} {'IoU med':>7s} {'IoU min':>7s} {'depth m':>7s}  worst view (az, el)")
    rows = []
    for name in names:
        ps = asset_scene.load(layer, f"/Plants/{name}")
        prepared = Prepared(ps.scene)
        references: dict = {}
        height = float(ps.hi[1] - ps.lo[1])
        for layout, frames, atlas_px in itertools.product(args.layouts, args.frames, args.atlas):
            t0 = time.perf_counter()
            at = atlas.build(prepared, ps.centre, ps.radius, frames, atlas_px, layout, defaults.samples, defaults.ao_rays,
                             defaults.padding_px, seed=1, ao_radius=defaults.ao_radius)
            bake_s = time.perf_counter() - t0
            views = heldout.held_out(heldout.directions(layout, subsample=args.azimuth_every), at.directions)
            errors = []
            for az, el in views:
                if (az, el) not in references:
                    m = heldout.mesh_view(prepared, octahedral.view_direction(az, el), ps.centre, ps.radius,
                                          args.view_px, args.reference_samples)
                    references[(az, el)] = (np.concatenate([m.albedo, m.alpha[..., None]], -1), m.depth)
                rgba, depth = references[(az, el)]
                v = sampler.render_view(at, octahedral.view_direction(az, el), args.view_px, defaults.depth_steps)
                errors.append(heldout.ViewError(az, el, *heldout.compare(rgba, depth, v.rgba, v.depth)))
            s = heldout.summarize(errors, height)
            w = s["worst_view"]
            print(f"{name:14s} {layout:10s} {frames:6d} {atlas_px:5d} {at.frame_px:5d} {bake_s:7.2f} {s['views']:5d} "
                  f"{s['psnr_db']['median']:8.2f} {s['psnr_db']['min']:8.2f} {s['alpha_iou']['median']:7.3f} "
                  f"{s['alpha_iou']['min']:7.3f} {s['depth_rmse_m']['median']:7.3f}  ({w['azimuth_deg']:.0f}, "
                  f"{w['elevation_deg']:.0f})", flush=True)
            rows.append((name, layout, frames, atlas_px, bake_s, s))
            _plot(rows, args.out)  # after every row: a long sweep stopped early still leaves its picture


COLOURS = [(0.85, 0.3, 0.2), (0.2, 0.55, 0.85), (0.25, 0.7, 0.3), (0.8, 0.6, 0.1), (0.6, 0.3, 0.75)]


def _plot(rows, out: Path) -> None:
    """Two panels drawn with numpy (no plotting library in the project):
    left median IoU (0.5 .. 1), right median PSNR (15 .. 45 dB), both against
    log10 bake seconds (the printed range); one colour per species, squares
    for octahedral, crosses for hemi, bigger marks for bigger atlases; grey
    lines at IoU 0.9 and 25 dB."""
    from pipeline import exr

    W, H, pad = 420, 320, 30
    img = np.ones((H, 2 * W, 3))
    t = np.log10([max(r[4], 1e-3) for r in rows])
    t0, t1 = float(t.min()) - 0.1, float(t.max()) + 0.1
    species = sorted({r[0] for r in rows})
    for panel, (key, lo, hi, line) in enumerate((("alpha_iou", 0.5, 1.0, 0.9), ("psnr_db", 15.0, 45.0, 25.0))):
        x0 = panel * W
        img[pad:H - pad, x0 + pad] = 0.0
        img[H - pad, x0 + pad:x0 + W - pad] = 0.0
        ly = int(H - pad - (line - lo) / (hi - lo) * (H - 2 * pad))
        img[ly, x0 + pad:x0 + W - pad] = 0.6
        for r, tr in zip(rows, t):
            x = int(x0 + pad + (tr - t0) / (t1 - t0) * (W - 2 * pad))
            y = int(H - pad - (np.clip(r[5][key]["median"], lo, hi) - lo) / (hi - lo) * (H - 2 * pad))
            c = COLOURS[species.index(r[0]) % len(COLOURS)]
            k = 1 + r[3] // 1024
            if r[1] == "octahedral":
                img[max(y - k, 0):y + k + 1, max(x - k, 0):x + k + 1] = c
            else:
                for d in range(-k - 1, k + 2):
                    img[np.clip(y + d, 0, H - 1), np.clip(x + d, 0, 2 * W - 1)] = c
                    img[np.clip(y - d, 0, H - 1), np.clip(x + d, 0, 2 * W - 1)] = c
    out.parent.mkdir(parents=True, exist_ok=True)
    exr.write_png(out, np.round(img * 255).astype(np.uint8))
    print(f"plot: {out} (x: log10 bake s from {t0:.2f} to {t1:.2f}; left median IoU 0.5..1, right median PSNR "
          f"15..45 dB; colours {', '.join(species)}; squares octahedral, crosses hemi, size ~ atlas)")


if __name__ == "__main__":
    main()
