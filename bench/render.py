"""Speed of the offline renderer (pipeline/render), not part of `make test`.

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
   and rays per second.
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
    from pipeline.render import Camera, Scene, Settings, render

    rng = np.random.default_rng(5)
    c = rng.random((300, 3)) * 2 - 1
    P = (c[:, None, :] + 0.3 * (rng.random((300, 3, 3)) - 0.5)).reshape(-1, 3)
    scene = Scene(P, np.tile([0.0, 0.0, 1.0], (len(P), 1)), np.zeros((len(P), 2)), np.arange(len(P)).reshape(-1, 3),
                  rng.random((300, 3)), -1)
    s = Settings(48, 48, samples=2, ao_rays=4, ao_radius_m=0.5)
    cam = Camera((0.0, 0.0, 4.0), (0.0, 0.0, -1.0), fov_y_deg=40.0)
    render(scene, cam, s)  # build the kernel
    tk, a = best_of(lambda: render(scene, cam, s), repeat)
    tn, b = best_of(lambda: render(scene, cam, s, device=False), 1)
    rays = 48 * 48 * 4 * (1 + 4 * float(a.alpha.mean()))
    print(f"\n== 1. kernel vs numpy reference, tiny scene ({scene.n_triangles} triangles, 48x48, 2x2 samples, 4 AO rays)")
    print(f"kernel     {tk * 1e3:8.1f} ms  {rays / tk / 1e6:8.3f} Mrays/s (BVH build included)")
    print(f"reference  {tn * 1e3:8.1f} ms  {rays / tn / 1e6:8.3f} Mrays/s (brute force, float64)")
    print(f"speed-up   {tn / tk:8.1f} x   largest |albedo| difference {np.abs(a.albedo - b.albedo).max():.2e}, "
          f"coverage differs in {(np.abs(a.alpha - b.alpha) > 1e-4).mean():.2%} of pixels")


def tree_scene(quick: bool):
    from stages.plants import measure
    from stages.plants.plant import Settings, build_plant
    from stages.plants.stage import PRESETS

    spec = PRESETS["conifer"]
    res = build_plant("conifer", spec, 20261123, Settings(lod_count=1))
    rgba = np.concatenate([res.cards.albedo, res.cards.alpha[..., None]], -1)
    return measure.plant_scene(res.lods[0], spec, rgba, None), spec


def tree(quick: bool, repeat: int) -> None:
    from pipeline.render import Prepared, Scene, Settings
    from stages.plants import measure

    scene, _ = tree_scene(quick)
    n = 256 if quick else 512
    cam = measure.side_cameras(scene.positions.astype(np.float64), 8)[1]
    t0 = time.perf_counter()
    prep = Prepared(scene)
    t_bvh = time.perf_counter() - t0
    s1 = Settings(n, n, samples=1)
    prep.render(cam, s1)
    tk, img = best_of(lambda: prep.render(cam, s1), repeat)
    opaque = Scene(scene.positions, scene.normals, scene.uv, scene.triangles, scene.tint, -1, scene.textures)
    prep_o = Prepared(opaque)
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
    from pipeline.render import Prepared, Settings
    from stages.plants import measure

    scene, _ = tree_scene(quick)
    n = 192 if quick else 384
    cam = measure.side_cameras(scene.positions.astype(np.float64), 8)[1]
    prep = Prepared(scene)
    s = Settings(n, n, samples=3, ao_rays=8, ao_radius_m=0.5)
    t, img = best_of(lambda: prep.render(cam, s), max(1, repeat - 1))
    rays = n * n * 9 * (1 + 8 * float(img.alpha.mean()))
    print(f"\n== 3. bake-quality render of the conifer: {n}x{n}, 3x3 samples, 8 AO rays")
    print(f"{t:.2f} s   {n * n / t / 1e3:8.1f} kpixels/s   {rays / t / 1e6:8.2f} Mrays/s (primary + AO)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    from pipeline.opencl import get_cl

    print(f"device: {get_cl().fingerprint}")
    tiny(a.repeat)
    tree(a.quick, a.repeat)
    bake_quality(a.quick, a.repeat)


if __name__ == "__main__":
    main()
