"""Volume textures: run time against error (not part of `make test`).

    python -m bench.volumes PLANTS_FOLDER [--voxels 32 64 128] [--species conifer ...]
                            [--sectors FOREST_VOLUMES_STATS_JSON] [--pictures OUT_FOLDER]

For each species asset in PLANTS_FOLDER (the plants stage's artifact
folder) and each resolution: the voxelization time, the alpha IoU and PSNR
of every mip level against the mesh from all four held-out views (2 x 2
samples a pixel; the bake measures two at 96 px), memory per
level (float32 as stored, and as an RGBA8 engine texture), and the woody
solid's volume against manifold3d's. --sectors prints the time per sector
from a forest_volumes stats.json (grid, occupied voxels, file size,
phases), the sectors' errors against their instances (column_errors, on
the sectors the stage measured) and the stored mips' mean coverage drift.
--pictures writes, per species, the mesh render beside the composite of
each level (first held-out view), and the largest sector at every level.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _picture(path: Path, images: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Premultiplied albedo + alpha over a grey background, side by side."""
    import OpenImageIO as oiio

    from worldlib.render import srgb8

    tiles = [rgb + (1 - a[..., None]) * 0.5 for a, rgb in images]
    oiio.ImageBuf(np.ascontiguousarray(srgb8(np.concatenate(tiles, axis=1)))).write(str(path))


def main(argv=None) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render.usd_asset import load_asset
    from stages.volumes import error
    from stages.volumes.stage import VolumesParams, load_species, volume_species
    from stages.volumes.voxelize import backend

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("plants", type=Path)
    ap.add_argument("--voxels", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--species", nargs="*")
    ap.add_argument("--sectors", type=Path)
    ap.add_argument("--pictures", type=Path)
    ap.add_argument("--pixels", type=int, default=160)
    ap.add_argument("--samples-per-voxel", type=float, default=VolumesParams().samples_per_voxel)
    a = ap.parse_args(argv)
    folder = a.plants if a.plants.is_dir() else a.plants.parent
    names = a.species or sorted(p.stem for p in folder.glob("*.usdc"))
    rows = []
    print(f"{'species':<14} {'N':>4} {'grid':>13} {'vox s':>6} {'mip':>3} {'voxel m':>8} {'MiB f32':>8} {'MiB rgba8':>9} "
          f"{'IoU min':>7} {'PSNR min':>8} {'wood err':>8}")
    for name in names:
        for n in a.voxels:
            params = VolumesParams(voxels=n, mip_levels=min(5, n.bit_length() - 3), error_view_pixels=a.pixels,
                                   error_views=4, samples_per_voxel=a.samples_per_voxel)
            with tempfile.TemporaryDirectory() as tmp:
                t = time.perf_counter()
                rep, chain = volume_species(cl_env, name, load_species(name, folder / f"{name}.usdc", params), params, Path(tmp),
                                            {"stage": "bench"})
                wall = time.perf_counter() - t
            w = rep["wood"]["relative_error"]
            for e in rep["levels"]:
                print(f"{name:<14} {n:>4} {'x'.join(map(str, e['grid'])):>13} {rep['seconds_voxelize']:>6.2f} {e['mip']:>3} "
                      f"{e['voxel_m']:>8.4f} {e['bytes'] / 2**20:>8.3f} {e['bytes_rgba8'] / 2**20:>9.3f} "
                      f"{e['alpha_iou_min']:>7.3f} {e['psnr_db_min']:>8.2f} {'-' if w is None else f'{w:+.3%}':>8}")
            rows.append({"species": name, "voxels": n, "seconds_voxelize": rep["seconds_voxelize"], "seconds": wall,
                         "levels": [{k: v for k, v in e.items() if k != "views"} for e in rep["levels"]]})
            if a.pictures and n == max(a.voxels):
                a.pictures.mkdir(parents=True, exist_ok=True)
                scene = load_asset(folder / f"{name}.usdc", levels=[0])[0].scene
                lo, hi = scene.positions.min(0), scene.positions.max(0)
                for v, cam in enumerate(error.view_cameras(lo, hi)[:2]):
                    mesh = error.mesh_views(cl_env, scene, [cam], a.pixels * 2)[0]
                    comps = [error.level_views(lv, [cam], a.pixels * 2, backend(cl_env))[0] for lv in chain[:4]]
                    _picture(a.pictures / f"{name}_view{v}.png", [(mesh.alpha, mesh.albedo)] + comps)
    if a.sectors:
        stats = json.loads(a.sectors.read_text())
        print(f"\n{'sector':<40} {'instances':>9} {'grid':>13} {'voxel m':>7} {'MiB f32':>8} {'occupied':>8} "
              f"{'KiB file':>8} {'s':>6}")
        for path, s in stats["sectors"].items():
            lv0 = s["levels"][0]
            print(f"{path:<40} {sum(s['instances'].values()):>9} {'x'.join(map(str, s['grid'])):>13} {s['voxel_m']:>7.2f} "
                  f"{lv0['bytes'] / 2**20:>8.2f} {lv0.get('occupied_voxels', 0):>8} "
                  f"{sum(e.get('bytes_file', 0) for e in s['levels']) / 1024:>8.0f} {s['seconds']:>6.2f}")
        files = sorted(a.sectors.parent.glob("*.mip*.exr"))
        print(f"sector files: {len(files)}, {sum(f.stat().st_size for f in files) / 1e6:.1f} MB; phases (s): "
              + ", ".join(f"{k} {v:.2f}" for k, v in stats.get("phases_seconds", {}).items()))
        # the sectors against their instances (forest_volumes column_errors), where the stage measured them
        measured = {p: s["error"] for p, s in stats["sectors"].items() if "error" in s}
        if measured:
            keys = ("extinction_relative", "column_relative_l1", "column_relative_l1_32m", "cover_mae", "cover_bias",
                    "side_column_relative_l1", "side_column_relative_l1_32m", "side_cover_mae", "side_cover_bias")
            short = ("extinct", "L1", "L1 32m", "cover", "bias", "side L1", "s L1 32m", "s cover", "s bias")
            print(f"\n{'sector error vs instances':<40} " + " ".join(f"{k:>8}" for k in short))
            for path, e in measured.items():
                print(f"{path:<40} " + " ".join(f"{e[k]:>8.3f}" if k != "extinction_relative" else f"{e[k]:>8.1e}"
                                                for k in keys))
            print(f"{'max |.|':<40} " + " ".join(f"{max(abs(e[k]) for e in measured.values()):>8.3g}" for k in keys))
        # the stored levels' mean coverage against the finest stored level's (read back)
        from worldlib.volumes import sparse as _volume

        drift = 0.0
        for path, s in list(stats["sectors"].items())[:: max(1, len(stats["sectors"]) // 16)]:
            stem = path.rsplit("/", 1)[-1]
            means = [_volume.read_level(a.sectors.parent / f"{stem}.mip{k}.exr").mean_density()
                     for k in range(len(s["levels"]))]
            drift = max(drift, max(abs(m / means[0] - 1) for m in means))
        print(f"stored mean coverage drift over the mips (every {max(1, len(stats['sectors']) // 16)}th sector): "
              f"{drift:.2e}")
        if a.pictures and stats["sectors"]:
            # the sector with the most instances, from above at 35 degrees, every level
            from worldlib.volumes import sparse as volume
            from worldlib.render import Camera

            path = max(stats["sectors"], key=lambda p: sum(stats["sectors"][p]["instances"].values()))
            stem = path.rsplit("/", 1)[-1]
            levels = [volume.read_level(a.sectors.parent / f"{stem}.mip{k}.exr")
                      for k in range(len(stats["sectors"][path]["levels"]))]
            lo, hi = levels[0].origin, levels[0].bbox_max
            c, r = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
            d = np.array([0.6, -0.57, 0.56])
            d /= np.linalg.norm(d)
            cam = Camera(tuple(c - d * 2 * r), tuple(d), ortho_height_m=1.2 * r)
            _picture(a.pictures / f"sector_{stem}.png",
                     [error.level_views(lv, [cam], 400, backend(cl_env))[0] for lv in levels])
    kernel_speedups(folder / f"{names[0]}.usdc")
    print(json.dumps(rows))


def kernel_speedups(usdc: Path) -> None:
    """Both kernels against their numpy references on the same small work:
    the samples of 300 triangles of the asset, a 48 x 48 composite of its
    32-voxel volume."""
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render.usd_asset import load_asset
    from stages.volumes import device, error, reference
    from stages.volumes.samples import sample_table
    from stages.volumes.voxelize import plant_grid, voxelize

    level = load_asset(usdc, levels=[0])[0]
    grid = plant_grid(level.scene, 32, 1)
    table = sample_table(level.scene, np.arange(min(300, level.scene.n_triangles)), grid.voxel / 2)
    timings = {}
    device.surface_samples(cl_env, table.take(0, 1), grid, level.scene.textures, 0.5)  # builds the program
    for name, be in (("kernel", device), ("numpy", reference)):
        t = time.perf_counter()
        be.surface_samples(table, grid, level.scene.textures, 0.5)
        timings[("samples", name)] = time.perf_counter() - t
    lv = voxelize(cl_env, level.scene, level.parts, 32, 1).level
    cam = error.view_cameras(lv.origin, lv.bbox_max)[0]
    g = error.composite_grid(lv)
    for name, be in (("kernel", device), ("numpy", reference)):
        t = time.perf_counter()
        be.composite(cam.frame(48, 48), 48, 48, g, lv.origin, lv.voxel_m, 0.5 * lv.voxel_m)
        timings[("composite", name)] = time.perf_counter() - t
    n = int(table.offset[-1])
    print(f"\nkernel vs numpy reference ({usdc.stem}): surface samples {n:,} in {timings['samples', 'kernel']:.3f} s vs "
          f"{timings['samples', 'numpy']:.2f} s ({timings['samples', 'numpy'] / timings['samples', 'kernel']:.0f}x); "
          f"composite 48^2 of 32 voxels {timings['composite', 'kernel']:.3f} s vs {timings['composite', 'numpy']:.2f} s "
          f"({timings['composite', 'numpy'] / timings['composite', 'kernel']:.0f}x)")


if __name__ == "__main__":
    main()
