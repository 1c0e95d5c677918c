"""Threshold landsliding: run time against error for the cones' rounding
(erosion.landslide_round_sweeps, stages/erosion/hillslope.py; not part of
`make test`).

    python -m bench.landslide                      # 1024^2, sweeps 0 8 16 32 64 128 256
    python -m bench.landslide --size 512 --sweeps 0 32

Error: a single foot in a 401^2 plateau (1 m cells), the envelope against
the exact round cone Sc r within 180 cells of the foot: the worst height
ratio over Sc r and the worst angle between the slope and the radius (a
polygon cone's faces show as a fan of facets; 0 for a round one).
Time: on the default world's heightmap at --size^2 over 8192 m, made three
times as steep so that most of it slides (the default's geological steps
see about this much), the 32-direction envelope (numpy) and the rounding
on the OpenCL device at each sweep count, best of --repeat; the numpy
reference's time for one count, and the ratio.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

SC = math.tan(math.radians(33.0))


def cone_errors(env, sweeps: int) -> tuple[float, float]:
    from stages.erosion import hillslope

    n, reach = 401, 180
    h = np.full((n, n), 1e4)
    h[n // 2, n // 2] = 0.0
    z = hillslope.cone_envelope(h, 1.0, SC)
    z = hillslope.round_cones(env, z, np.full(z.shape, SC), sweeps)
    r, c = np.mgrid[0:n, 0:n] - n // 2
    rad = np.hypot(r, c)
    ring = (rad > 5) & (rad < reach)
    ratio = float((z[ring] / (SC * rad[ring])).max())
    gy, gx = np.gradient(z)
    err = (np.degrees(np.arctan2(gy, gx) - np.arctan2(r, c))[ring] + 180.0) % 360.0 - 180.0
    return ratio - 1.0, float(np.abs(err).max())


def main(argv=None) -> None:
    from bench.hydrology import best_of, dem
    from pipeline.opencl import get_cl
    from stages.erosion import hillslope

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--sweeps", type=int, nargs="+", default=[0, 8, 16, 32, 64, 128, 256])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--reference-sweeps", type=int, default=32, help="sweeps of the device-against-numpy comparison")
    args = ap.parse_args(argv)
    env = get_cl()
    dx = 8192.0 / args.size
    h = dem(args.size).astype(np.float64) * 3.0
    z = hillslope.cone_envelope(h, dx, SC)
    rise = np.full(z.shape, SC * dx)
    t_env = best_of(lambda: hillslope.cone_envelope(h, dx, SC), args.repeat)
    print(f"{args.size}^2 cells of {dx:g} m on {env.device.name}: the 32-direction envelope {t_env:.3f} s")
    print(f"{'sweeps':>6} {'round s':>8} {'ms/sweep':>8} {'cone height err':>15} {'slope dir err':>13}")
    for s in args.sweeps:
        t = best_of(lambda: hillslope.round_cones(env, z, rise, s), args.repeat)
        height, angle = cone_errors(env, s)
        print(f"{s:6d} {t:8.3f} {1e3 * t / max(s, 1):8.2f} {100 * height:14.2f}% {angle:12.1f} deg")
    s = args.reference_sweeps
    t_dev = best_of(lambda: hillslope.round_cones(env, z, rise, s), args.repeat)
    t_ref = best_of(lambda: hillslope.round_cones_reference(z, rise, s), 1)
    same = np.array_equal(hillslope.round_cones(env, z, rise, s), hillslope.round_cones_reference(z, rise, s))
    print(f"{s} sweeps: device {t_dev:.3f} s, numpy reference {t_ref:.3f} s ({t_ref / t_dev:.1f}x), "
          f"bitwise equal: {same}")


if __name__ == "__main__":
    main()
