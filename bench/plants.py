"""Benchmark of the plants stage (not part of `make test`).

    python -m bench.plants            # full sizes
    python -m bench.plants --quick    # smaller kernel inputs, fewer sweep points

It prints, in one run on the same device:
1. per preset (one tree each, world seed --seed): bake seconds split into
   mesh (L-system, turtle, tubes, union, leaves), foliage textures (card
   cluster render, bark / card / blade textures written as EXR + PNG), LODs
   (chain and Hausdorff) and look measures (crown opacity at 8 azimuths per
   LOD); the foliage and wood areas, LAI and crown opacity per LOD; the
   triangles of every LOD with its Hausdorff error and simplification time;
2. the mesh builder: triangles per second of each vertex kernel (tube rings,
   leaf instances, grass blades) against its numpy reference, kernel-only
   (buffers resident) and end to end (with host transfers), plus the
   achieved write bandwidth against a copy kernel measured in the same run;
3. LOD error against simplification time: pymeshlab quadric edge collapse of
   the broadleaf's woody solid to falling triangle targets, each with its
   time and symmetric Hausdorff error;
4. the renderer the foliage cards and crown measures use (bench.render):
   kernel against its numpy reference, rays per second (and Embree's on the
   same rays when embreex is installed).
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np


def best_of(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def presets(seed: int) -> dict:
    from stages.plants.plant import Settings, build_plant
    from pipeline.opencl import get_cl
    from stages.plants.stage import PRESETS

    print(f"\n== 1. presets (world seed {seed}, default settings: 4 LODs, halving, 20000 Hausdorff samples)")
    out = {}
    for name, spec in sorted(PRESETS.items()):
        t0 = time.perf_counter()
        res = build_plant(name, spec, seed, Settings(cl=get_cl()))
        dt = time.perf_counter() - t0
        m = res.metrics
        out[name] = res
        parts = ", ".join(f"{k} {m[k]:.2f}" for k in ("seconds_lsystem", "seconds_turtle", "seconds_tubes", "seconds_union",
                                                    "seconds_leaves", "seconds_blades") if k in m)
        lod_s = sum(e["simplify_seconds"] for e in m["lods"])
        print(f"{name:10s} {dt:6.2f} s/tree   LOD0 {res.lod_info[0]['triangles']:7d} triangles   "
              f"diag {m['bbox_diagonal_m']:.2f} m   [{parts}, LOD chain {lod_s:.2f}]")
        _looks(name, spec, res, seed, dt)
        if "wood_check" in m:
            c = m["wood_check"]
            print(f"{'':10s} wood: {m['segments']} segments, {m['tubes']} tubes, {m['tube_triangles']} tube triangles -> "
                  f"{c['triangles']} after the union; watertight {c['watertight']}, manifold {c['manifold']}, "
                  f"degenerate {c['degenerate']}, min altitude {c['min_altitude']:.2e} m; leaves {m['leaves']}")
        for e in m["lods"]:
            print(f"{'':10s}   LOD{e['level']}: {e['triangles']:7d} triangles {str(e['parts']):40s} "
                  f"error {100 * e['hausdorff_fraction']:6.3f} % ({1000 * e['hausdorff_m']:7.2f} mm)   "
                  f"simplify {e['simplify_seconds']:.2f} s")
    return out


def _looks(name, spec, res, seed, build_seconds) -> None:
    """The stage's texture writing and look measures for one species, timed."""
    import tempfile
    from pathlib import Path

    from stages.plants import stage as plants_stage

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        plants_stage._write_textures(Path(tmp), Path(tmp) / f"{name}.usdc", name, spec, res, {}, seed)
        t_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    looks = plants_stage._measure_looks(spec, res)
    t_measure = time.perf_counter() - t0
    m = res.metrics
    tex = m.get("seconds_foliage_textures", 0.0) + t_write
    lods = m.get("seconds_measure", 0.0) + sum(e["simplify_seconds"] for e in m["lods"])
    mesh_s = build_seconds - m.get("seconds_foliage_textures", 0.0) - lods
    print(f"{'':10s} bake: mesh {mesh_s:6.2f} s   foliage textures {tex:6.2f} s   LODs {lods:6.2f} s   "
          f"look measures {t_measure:6.2f} s")
    ratio = looks["foliage_to_wood"]
    print(f"{'':10s} foliage {looks['foliage_area_m2']:7.2f} m2   wood {looks['wood_area_m2']:6.2f} m2   "
          f"ratio {ratio if ratio is None else round(ratio, 2)}   LAI {looks['leaf_area_index']:6.2f}   crown opacity "
          + " / ".join(f"LOD{e['level']} {e['crown_opacity']:.3f}" for e in looks["levels"]))


def _device_time(kernel_name: str, n_items: int, scalars: list, arrays: list[np.ndarray], out_bytes: int, repeat: int) -> float:
    import pyopencl as cl

    from pipeline.opencl import get_cl, global_size
    from stages.plants import geometry

    env = get_cl()
    mf = cl.mem_flags
    bufs = [cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a)) for a in arrays]
    dst = cl.Buffer(env.ctx, mf.WRITE_ONLY, out_bytes)
    k = geometry._kernel(kernel_name)

    def go():
        k(env.queue, global_size((n_items,), (geometry.LOCAL,)), (geometry.LOCAL,), *scalars, *bufs, dst)
        env.queue.finish()

    go()
    return best_of(go, repeat)


def copy_bandwidth(n_floats: int, repeat: int) -> float:
    import pyopencl as cl

    from pipeline.opencl import get_cl, global_size
    from stages.plants import geometry

    env = get_cl()
    a = cl.Buffer(env.ctx, cl.mem_flags.READ_WRITE, n_floats * 4)
    b = cl.Buffer(env.ctx, cl.mem_flags.READ_WRITE, n_floats * 4)
    k = geometry._kernel("copy_floats")

    def go():
        k(env.queue, global_size((n_floats,), (geometry.LOCAL,)), (geometry.LOCAL,), np.int32(n_floats), a, b)
        env.queue.finish()

    go()
    return 8 * n_floats / best_of(go, repeat) / 1e9


def builder(quick: bool, repeat: int) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from stages.plants import geometry, grass, leaves, mesh
    from stages.plants import reference as ref
    from stages.plants.species import GrassSpec, LeafSpec

    scale = 1 if quick else 4
    rng = np.random.default_rng(0)
    print(f"\n== 2. mesh builder: triangles per second, kernel vs numpy reference (best of {repeat})")
    print(f"{'kernel':14s} {'input':>22s} {'triangles':>10s} {'kernel only':>14s} {'end to end':>14s} {'numpy':>14s} "
          f"{'speed-up':>9s} {'write GB/s':>11s}")
    gbs_copy = copy_bandwidth(4_000_000 * scale, repeat)

    # tube rings: 12-sided rings, as on a trunk
    n_rings, sides = 50_000 * scale, 12
    t = rng.normal(size=(n_rings, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    nvec = np.cross(t, [0.0, 0.0, 1.0])
    nvec /= np.maximum(np.linalg.norm(nvec, axis=1, keepdims=True), 1e-9)
    ring = np.zeros((n_rings, ref.RING), np.float32)
    ring[:, 0:3], ring[:, 3:6], ring[:, 6:9], ring[:, 9:12] = rng.normal(size=(n_rings, 3)), nvec, np.cross(t, nvec), t
    ring[:, 12] = 0.05
    sides_a = np.full(n_rings, sides, np.int32)
    offset = np.arange(n_rings, dtype=np.int32) * (sides + 1)
    tris = (n_rings - 1) * sides * 2  # as if one long tube
    nv = n_rings * (sides + 1)
    tk = _device_time("tube_rings", n_rings, [np.int32(n_rings)], [ring.reshape(-1), sides_a, offset], nv * ref.VERT * 4, repeat)
    te = best_of(lambda: geometry.tube_rings(cl_env, ring, sides_a), repeat)
    tn = best_of(lambda: ref.tube_rings(ring, sides_a, offset), max(1, repeat // 2))
    _row("tube_rings", f"{n_rings} rings x {sides}", tris, tk, te, tn, nv * ref.VERT * 4)

    # leaf instances: the broadleaf's 8-triangle ovate leaf
    tmpl = leaves.make_template(LeafSpec(shape="ellipse", segments=3, length=0.12, width=0.06, petiole=0.02))
    n_leaves = 100_000 * scale
    rec = np.zeros((n_leaves, ref.LEAF), np.float32)
    rec[:, 0:3] = rng.normal(size=(n_leaves, 3))
    rec[:, 3:6], rec[:, 6:9], rec[:, 9:12] = [0, 1, 0], [-1, 0, 0], [0, 0, 1]
    rec[:, 12] = 1.0
    nt = len(tmpl.rows)
    tk = _device_time("leaf_instances", n_leaves * nt, [np.int32(n_leaves), np.int32(nt)],
                      [rec.reshape(-1), tmpl.rows.reshape(-1)], n_leaves * nt * ref.VERT * 4, repeat)
    te = best_of(lambda: geometry.leaf_instances(cl_env, rec, tmpl.rows), repeat)
    tn = best_of(lambda: ref.leaf_instances(rec, tmpl.rows), max(1, repeat // 2))
    _row("leaf_instances", f"{n_leaves} leaves x {nt} verts", n_leaves * tmpl.n_tris, tk, te, tn, n_leaves * nt * ref.VERT * 4)

    # grass blades: 8 segments
    g = GrassSpec(blades=10_000)
    brec = np.concatenate([grass.blade_records(g, rng) for _ in range(5 * scale)])
    rows = grass.row_parameters(brec, 8)
    nb, n = len(brec), 8
    tk = _device_time("grass_blades", nb * (n + 1), [np.int32(nb), np.int32(n), np.float32(g.taper)],
                      [brec.reshape(-1), rows.reshape(-1)], nb * (2 * n + 1) * ref.VERT * 4, repeat)
    te = best_of(lambda: geometry.grass_blades(cl_env, brec, rows, g.taper), repeat)
    tn = best_of(lambda: ref.grass_blades(brec, rows, g.taper), max(1, repeat // 2))
    _row("grass_blades", f"{nb} blades x {n} segs", nb * (2 * n - 1), tk, te, tn, nb * (2 * n + 1) * ref.VERT * 4)
    print(f"{'copy_floats':14s} roofline: {gbs_copy:.2f} GB/s (4 B read + 4 B written per float)")
    t0 = time.perf_counter()
    idx = mesh.tube_triangles(n_rings, sides)
    print(f"index generation (numpy, shared by both paths): {len(idx) / (time.perf_counter() - t0) / 1e6:.1f} M triangles/s")


def _row(name, what, tris, tk, te, tn, out_bytes):
    print(f"{name:14s} {what:>22s} {tris:10d} {tris / tk / 1e6:9.1f} Mt/s {tris / te / 1e6:9.1f} Mt/s "
          f"{tris / tn / 1e6:9.1f} Mt/s {tn / te:8.1f}x {out_bytes / tk / 1e9:10.2f}")


def lod_sweep(res, quick: bool) -> None:
    from stages.plants import lod

    wood = res.lods[0]["Wood"]
    ref = wood.welded()
    diag = lod.bbox_diagonal(ref[0])
    print(f"\n== 3. LOD error vs simplification time: quadric edge collapse of the broadleaf wood ({wood.n_tris} triangles, "
          f"diag {diag:.2f} m)")
    print(f"{'target':>8s} {'triangles':>10s} {'decimate s':>11s} {'Hausdorff %':>12s} {'mm':>8s} {'measure s':>10s}")
    ratios = [0.5, 0.25, 0.1] if quick else [0.5, 0.35, 0.25, 0.15, 0.1, 0.06, 0.03]
    for r in ratios:
        target = int(r * wood.n_tris)
        t0 = time.perf_counter()
        w = lod.decimate(wood, target)
        td = time.perf_counter() - t0
        t0 = time.perf_counter()
        h = lod.hausdorff(ref, w.welded(), 20000)
        tm = time.perf_counter() - t0
        print(f"{r:8.2f} {w.n_tris:10d} {td:11.3f} {100 * h['max'] / diag:12.3f} {1000 * h['max']:8.2f} {tm:10.3f}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=20261123)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    from pipeline.opencl import get_cl

    print(f"plants bench on {get_cl().fingerprint}; {platform.processor() or platform.machine()}, python {platform.python_version()}")
    res = presets(args.seed)
    builder(args.quick, args.repeat)
    lod_sweep(res["broadleaf"], args.quick)
    from bench import render as render_bench

    print("\n== 4. the renderer (bench.render)")
    render_bench.tiny(args.repeat)
    render_bench.tree(args.quick, args.repeat)


if __name__ == "__main__":
    main()
