"""A picture of a baked world from its world.usda (pipeline.render.world_view):

    python -m bench.world_view build/worlds/default/world.usda out.png [--width 1600 --height 900]
        [--azimuth 200 --elevation 32]

Prints the triangles, the instances drawn per prototype and the seconds
spent building the scene and rendering."""
from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> None:
    from pipeline.render import world_view

    ap = argparse.ArgumentParser()
    ap.add_argument("world")
    ap.add_argument("out")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--azimuth", type=float, default=200.0)
    ap.add_argument("--elevation", type=float, default=32.0)
    ap.add_argument("--fov", type=float, default=38.0)
    ap.add_argument("--zoom", type=float, default=1.0, help="move the camera this many times closer to the centre")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    scene, summary = world_view.build_world_scene(a.world)
    t1 = time.perf_counter()
    lo, hi = np.asarray(summary["bounds"][0]), np.asarray(summary["bounds"][1])
    cam = world_view.default_camera(lo, hi, a.azimuth, a.elevation, a.fov, a.width / a.height)
    if a.zoom != 1.0:
        c = 0.5 * (lo + hi)
        eye = c + (np.asarray(cam.eye) - c) / a.zoom
        cam = world_view.Camera(tuple(eye), cam.forward, cam.up, fov_y_deg=cam.fov_y_deg)
    from pipeline.render import Prepared, Settings, srgb8

    img = Prepared(scene).render(cam, Settings(a.width, a.height, samples=2, ao_rays=2, ao_radius_m=25.0, seed=1))
    t2 = time.perf_counter()
    rgb = srgb8(img.shaded(sun=(-0.45, 0.75, 0.5), sky=0.5, background=(0.55, 0.68, 0.85)))
    world_view.save_png(a.out, rgb, keep_alpha=True)
    print(f"{summary['triangles']:,} triangles; instances drawn {summary['instances']}; "
          f"left to the ground {summary['skipped_small']}")
    print(f"scene {t1 - t0:.1f} s, render {t2 - t1:.1f} s ({a.width}x{a.height}, 2x2 samples, 2 AO rays): wrote {a.out}")


if __name__ == "__main__":
    main()
