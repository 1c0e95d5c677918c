"""Speed of the offline renderer (worldlib/render), not part of `make test`.

    python -m bench.render [--quick]

Prints, on one device in one run:
1. kernel against the numpy reference on the same tiny scene (a few hundred
   random triangles, 48 x 48 pixels, 2 x 2 samples, 4 AO rays): seconds and
   rays per second of each, the speed-up, and their largest difference;
2. primary rays per second on a whole tree (the conifer preset's LOD0 with its
   alpha-tested cards) for the kernel, against Embree (embreex, if installed:
   `pip install embreex`) casting the same rays at the same opaque triangles
   (Embree has no alpha test here, so the kernel also runs with the cards
   opaque for the like-for-like figure); BVH build time of each;
3. a full bake-quality render (3 x 3 samples, 8 AO rays) of the tree: pixels
   and rays per second;
4. the bake's own workloads on the plant assets of a baked plants artifact
   (`--plants build/artifacts/plants/<key>/plants.usda`; by default the newest
   one under build/artifacts/plants), conifer and broadleaf LOD0 as the
   impostors stage reads them: atlas frames (orthographic, 128 px, 2 x 2
   samples, 1 AO ray), held-out mesh views (96 px, 3 x 3 samples) and a
   perspective view (256 px, 2 x 2 samples, 4 AO rays): rays per second and
   BVH build seconds for this checkout's renderer and, with `--baseline REV`,
   for the renderer of git revision REV in the same run (same rays, same
   machine load), with the largest difference between their images; and the
   numpy reference on a 12 x 12 crop-sized view of the conifer against the
   kernel.

    python -m bench.render --section assets --baseline b22dd94
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def best_of(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def tiny(repeat: int) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render import Camera, Scene, Settings, render

    rng = np.random.default_rng(5)
    c = rng.random((300, 3)) * 2 - 1
    P = (c[:, None, :] + 0.3 * (rng.random((300, 3, 3)) - 0.5)).reshape(-1, 3)
    scene = Scene(P, np.tile([0.0, 0.0, 1.0], (len(P), 1)), np.zeros((len(P), 2)), np.arange(len(P)).reshape(-1, 3),
                  rng.random((300, 3)), -1)
    s = Settings(48, 48, samples=2, ao_rays=4, ao_radius_m=0.5)
    cam = Camera((0.0, 0.0, 4.0), (0.0, 0.0, -1.0), fov_y_deg=40.0)
    render(cl_env, scene, cam, s)  # build the kernel
    tk, a = best_of(lambda: render(cl_env, scene, cam, s), repeat)
    tn, b = best_of(lambda: render(None, scene, cam, s), 1)
    rays = 48 * 48 * 4 * (1 + 4 * float(a.alpha.mean()))
    print(f"\n== 1. kernel vs numpy reference, tiny scene ({scene.n_triangles} triangles, 48x48, 2x2 samples, 4 AO rays)")
    print(f"kernel     {tk * 1e3:8.1f} ms  {rays / tk / 1e6:8.3f} Mrays/s (BVH build included)")
    print(f"reference  {tn * 1e3:8.1f} ms  {rays / tn / 1e6:8.3f} Mrays/s (brute force, float64)")
    print(f"speed-up   {tn / tk:8.1f} x   largest |albedo| difference {np.abs(a.albedo - b.albedo).max():.2e}, "
          f"coverage differs in {(np.abs(a.alpha - b.alpha) > 1e-4).mean():.2%} of pixels")


def tree_scene(quick: bool):
    from pipeline.opencl import get_cl
    from stages.plants import measure
    from stages.plants.plant import Settings, build_plant
    from stages.plants.stage import PRESETS

    spec = PRESETS["conifer"]
    res = build_plant("conifer", spec, 20261123, Settings(lod_count=1, cl=get_cl()))
    rgba = np.concatenate([res.cards.albedo, res.cards.alpha[..., None]], -1)
    return measure.plant_scene(res.lods[0], spec, rgba, None), spec


def tree(quick: bool, repeat: int) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render import Prepared, Scene, Settings
    from stages.plants import measure

    scene, _ = tree_scene(quick)
    n = 256 if quick else 512
    cam = measure.side_cameras(scene.positions.astype(np.float64), 8)[1]
    t0 = time.perf_counter()
    prep = Prepared(cl_env, scene)
    t_bvh = time.perf_counter() - t0
    s1 = Settings(n, n, samples=1)
    prep.render(cam, s1)
    tk, img = best_of(lambda: prep.render(cam, s1), repeat)
    opaque = Scene(scene.positions, scene.normals, scene.uv, scene.triangles, scene.tint, -1, scene.textures)
    prep_o = Prepared(cl_env, opaque)
    tko, img_o = best_of(lambda: prep_o.render(cam, s1), repeat)
    print(f"\n== 2. primary rays on the conifer (LOD0, {scene.n_triangles} triangles), {n}x{n}, 1 sample")
    print(f"kernel, alpha-tested cards  {n * n / tk / 1e6:8.2f} Mrays/s   coverage {img.alpha.mean():.3f}   BVH build {t_bvh:.2f} s")
    print(f"kernel, opaque cards        {n * n / tko / 1e6:8.2f} Mrays/s   coverage {img_o.alpha.mean():.3f}")
    try:
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        print("embreex not installed (pip install embreex): no Embree figure")
        return
    t0 = time.perf_counter()
    es = rtcs.EmbreeScene()
    TriangleMesh(es, opaque.positions[opaque.triangles].astype(np.float32))
    rec = cam.frame(n, n).astype(np.float64)
    ys, xs = np.mgrid[0:n, 0:n]
    x = 2 * ((xs + 0.5) / n) - 1
    y = 1 - 2 * ((ys + 0.5) / n)
    org = (rec[0:3] + x.reshape(-1, 1) * rec[6:9] + y.reshape(-1, 1) * rec[9:12]).astype(np.float32)
    dirs = np.tile(rec[3:6], (n * n, 1)).astype(np.float32)
    es.run(org, dirs)
    t_build = time.perf_counter() - t0
    te, hit = best_of(lambda: es.run(org, dirs), repeat)
    cov = float((np.asarray(hit) >= 0).mean())
    print(f"Embree (embreex), opaque    {n * n / te / 1e6:8.2f} Mrays/s   coverage {cov:.3f}   (build + first run {t_build:.2f} s)")
    print(f"kernel / Embree (opaque)    {te / tko:8.3f}")


def bake_quality(quick: bool, repeat: int) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render import Prepared, Settings
    from stages.plants import measure

    scene, _ = tree_scene(quick)
    n = 192 if quick else 384
    cam = measure.side_cameras(scene.positions.astype(np.float64), 8)[1]
    prep = Prepared(cl_env, scene)
    s = Settings(n, n, samples=3, ao_rays=8, ao_radius_m=0.5)
    t, img = best_of(lambda: prep.render(cam, s), max(1, repeat - 1))
    rays = n * n * 9 * (1 + 8 * float(img.alpha.mean()))
    print(f"\n== 3. bake-quality render of the conifer: {n}x{n}, 3x3 samples, 8 AO rays")
    print(f"{t:.2f} s   {n * n / t / 1e3:8.1f} kpixels/s   {rays / t / 1e6:8.2f} Mrays/s (primary + AO)")


def baseline_renderer(rev: str):
    """worldlib/render as it was at git revision `rev`, imported as its own
    package from a temporary folder (its kernel file beside it)."""
    import importlib.util
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    pkg = Path(tempfile.mkdtemp(prefix="render_baseline_")) / "render_baseline"
    pkg.mkdir()
    for name in ("__init__.py", "bvh.py", "scene.py", "reference.py", "kernels.cl"):
        text = subprocess.run(["git", "show", f"{rev}:worldlib/render/{name}"], cwd=root, check=True,
                              capture_output=True, text=True).stdout
        (pkg / name).write_text(text)
    spec = importlib.util.spec_from_file_location("render_baseline", pkg / "__init__.py",
                                                  submodule_search_locations=[str(pkg)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["render_baseline"] = mod
    spec.loader.exec_module(mod)
    return mod


def newest_plants_layer():
    from pathlib import Path

    found = sorted(Path("build/artifacts/plants").glob("*/plants.usda"), key=lambda p: p.stat().st_mtime)
    if not found:
        raise SystemExit("no plants artifact under build/artifacts/plants: bake one, e.g. `worldbake bake "
                         "configs/default.toml --set heightmap.resolution=256 --set 'outputs=[\"plants\"]' --name small`")
    return found[-1]


def workloads(ps, r) -> dict:
    """name -> [(camera, settings)] of the bake's renders of one plant asset
    (`r`: the renderer module whose Camera and Settings to use)."""
    from stages.impostors import octahedral

    c, rad = np.asarray(ps.centre, np.float64), float(ps.radius)
    dirs = octahedral.frame_directions(16, "hemi")
    back = rad * 1.05 + 0.01

    def ortho(d):
        right, up = octahedral.frame_basis(d)
        return r.Camera(tuple(c + d * back), tuple(-d), tuple(up), ortho_height_m=2.0 * rad)

    atlas_dirs = [dirs[j, (3 * j + 5) % 16] for j in range(0, 16, 2)]  # 8 frames across the atlas' rows
    atlas_s = r.Settings(128, 128, samples=2, ao_rays=1, ao_radius_m=0.08 * rad, seed=12345)
    held_dirs = [octahedral.view_direction(az, el) for az, el in ((17.5, 12.0), (137.5, 32.0), (257.5, 52.0))]
    held_s = r.Settings(96, 96, samples=3)
    eye = c + rad * np.array([2.2, 0.6, 1.4])
    persp = r.Camera(tuple(eye), tuple(c - eye), fov_y_deg=45.0)
    return {"atlas frames": [(ortho(d), atlas_s) for d in atlas_dirs],
            "held-out views": [(ortho(d), held_s) for d in held_dirs],
            "perspective+AO": [(persp, r.Settings(256, 256, samples=2, ao_rays=4, ao_radius_m=0.3 * rad, seed=3))]}


def count_rays(views, images) -> float:
    n = 0.0
    for (_, s), img in zip(views, images):
        per = s.width * s.height * s.samples ** 2
        n += per * (1.0 + s.ao_rays * float(img.alpha.mean()))
    return n


def image_difference(a, b) -> str:
    cov = np.abs(a.alpha - b.alpha) > 1e-4
    ok = ~cov
    fin = ok & np.isfinite(a.depth) & np.isfinite(b.depth)
    d_alb = float(np.abs(a.albedo - b.albedo)[ok].max()) if ok.any() else 0.0
    d_dep = float(np.abs(a.depth[fin] - b.depth[fin]).max()) if fin.any() else 0.0
    d_ao = float(np.abs(a.ao - b.ao)[ok].max()) if ok.any() else 0.0
    return f"coverage differs in {cov.mean():.3%} px, elsewhere |albedo| {d_alb:.1e} |depth| {d_dep:.1e} m |ao| {d_ao:.2f}"


def assets(plants: str | None, baseline: str | None, repeat: int, species=("conifer", "broadleaf"),
           with_reference: bool = True) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    import inspect
    from pathlib import Path

    import worldlib.render as current

    from worldlib.plant_asset import plant_asset_prim
    from stages.impostors import asset_scene

    layer = Path(plants) if plants else newest_plants_layer()
    renderers = {"this checkout": current}
    if baseline:
        renderers[f"baseline {baseline}"] = baseline_renderer(baseline)
    print(f"\n== 4. the bake's renders of the plant assets in {layer}")
    for sp in species:
        ps = asset_scene.load(layer, plant_asset_prim(sp))
        sc = ps.scene
        prepared, times = {}, {}
        for name, r in renderers.items():
            scene = r.Scene(sc.positions, sc.normals, sc.uv, sc.triangles, sc.tint, sc.texture, sc.textures)
            t0 = time.perf_counter()
            # a revision from before the device was handed around chose it itself
            prepared[name] = (r.Prepared(cl_env, scene) if "env" in inspect.signature(r.Prepared).parameters
                              else r.Prepared(scene))
            times[name] = time.perf_counter() - t0
        print(f"-- {sp}: {sc.n_triangles} triangles; BVH build + upload: "
              + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()))
        for wl in workloads(ps, current):
            best, images = {}, {}
            for _ in range(repeat):  # the renderers take turns: both see the same machine load
                for name, r in renderers.items():
                    views = workloads(ps, r)[wl]
                    c0, t0 = time.process_time(), time.perf_counter()
                    imgs = [prepared[name].render(cam, s) for cam, s in views]
                    t, c = time.perf_counter() - t0, time.process_time() - c0
                    if name not in best or t < best[name][0]:
                        best[name] = (t, c)
                    images[name] = imgs
            views = workloads(ps, current)[wl]
            rays = count_rays(views, images["this checkout"])
            for name in renderers:
                t, c = best[name]
                print(f"   {wl:15s} {name:22s} {rays / t / 1e6:7.2f} Mrays/s wall {rays / c / 1e6:7.2f} Mrays/CPU-s "
                      f"({rays / 1e6:.2f} M rays in {t:.2f} s wall, {c:.2f} s CPU)")
            if baseline:
                a, b = images["this checkout"], images[f"baseline {baseline}"]
                worst = max(range(len(a)), key=lambda i: float((np.abs(a[i].alpha - b[i].alpha) > 1e-4).mean()))
                t_new, t_old = best["this checkout"][0], best[f"baseline {baseline}"][0]
                c_new, c_old = best["this checkout"][1], best[f"baseline {baseline}"][1]
                print(f"   {'':15s} speed-up {t_old / t_new:5.2f} x wall, {c_old / c_new:5.2f} x CPU; against the baseline: "
                      f"{image_difference(a[worst], b[worst])}")
    if not with_reference:
        return
    # the oracle: the numpy reference on a small view of the conifer
    ps = asset_scene.load(layer, plant_asset_prim("conifer"))
    cam = workloads(ps, current)["atlas frames"][3][0]
    s = current.Settings(12, 12, samples=2, ao_rays=1, ao_radius_m=0.08 * ps.radius, seed=5)
    tk, a = best_of(lambda: current.Prepared(cl_env, ps.scene).render(cam, s), 1)
    tn, b = best_of(lambda: current.render(None, ps.scene, cam, s), 1)
    rays = count_rays([(cam, s)], [a])
    print(f"-- numpy reference, conifer 12x12, 2x2 samples, 1 AO ray: {rays / tn:.1f} rays/s in {tn:.1f} s "
          f"(kernel, with its BVH build, {tk:.2f} s); kernel vs reference: {image_difference(a, b)}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--section", choices=("all", "tiny", "tree", "bake", "assets"), default="all")
    ap.add_argument("--plants", help="a plants artifact's plants.usda (default: the newest under build/artifacts)")
    ap.add_argument("--baseline", metavar="REV", help="also measure worldlib/render of this git revision")
    ap.add_argument("--no-reference", action="store_true", help="skip the numpy reference on the conifer (about a minute)")
    a = ap.parse_args(argv)
    from pipeline.opencl import get_cl

    print(f"device: {get_cl().fingerprint}")
    if a.section in ("all", "tiny"):
        tiny(a.repeat)
    if a.section in ("all", "tree"):
        tree(a.quick, a.repeat)
    if a.section in ("all", "bake"):
        bake_quality(a.quick, a.repeat)
    if a.section in ("all", "assets"):
        assets(a.plants, a.baseline, a.repeat, with_reference=not a.no_reference)


if __name__ == "__main__":
    main()
