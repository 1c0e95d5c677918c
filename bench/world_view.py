"""A picture of a baked world from its world.usda (worldlib.render.world_view):

    python -m bench.world_view build/worlds/default/world.usda out.png [--width 1600 --height 900]
        [--azimuth 200 --elevation 32 --zoom 1 4]

Prints the triangles, the instances drawn per prototype and the seconds
spent building the scene and rendering."""
from __future__ import annotations

import argparse


def main(argv=None) -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render import world_view

    ap = argparse.ArgumentParser()
    ap.add_argument("world")
    ap.add_argument("out")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--azimuth", type=float, default=200.0)
    ap.add_argument("--elevation", type=float, default=32.0)
    ap.add_argument("--zoom", type=float, nargs="+", default=[1.0],
                    help="move the camera this many times closer to the centre; several: one picture each "
                    "(OUT with _z<zoom> before .png), the scene built once")
    a = ap.parse_args(argv)
    for zoom in a.zoom:
        stats: dict = {}
        out = a.out if len(a.zoom) == 1 else a.out.replace(".png", f"_z{zoom:g}.png")
        rgba = world_view.render_world(cl_env, a.world, a.width, a.height, azimuth_deg=a.azimuth, elevation_deg=a.elevation,
                                       zoom=zoom, stats=stats)
        world_view.save_png(out, rgba)
        print(f"{stats['triangles']:,} triangles; instances drawn {stats['instances']}; "
              f"left to the ground {stats['skipped_small']}")
        print(f"scene {stats['scene_s']} s, render {stats['render_s']} s ({a.width}x{a.height}, 2x2 samples, "
              f"2 AO rays): wrote {out}")

if __name__ == "__main__":
    main()
