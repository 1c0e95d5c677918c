"""Look at a terrain: an oblique perspective view by ray-marching the height
field (numpy, headless) and a hillshade, as PNG (not part of `make test`).

    python -m bench.terrain_view build/artifacts/erosion/<key>/height.exr out.png
    python -m bench.terrain_view height.exr out.png --azimuth 200 --elevation 28 --width 1280

Each pixel's ray advances by a step bounded by its height above the terrain
divided by the steepest slope, so it cannot tunnel through a ridge, then
bisects the crossing. Shading: Lambert from a low sun plus sky light, a
shadow ray toward the sun, albedo grass/rock/snow from slope and height so
that valleys and ridges read at a glance, aerial perspective toward the
horizon. The camera orbits the map centre.
"""
from __future__ import annotations

import argparse
import math

import numpy as np


def bilinear(h: np.ndarray, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    rows, cols = h.shape
    x = np.clip(x, 0, cols - 1.001)
    z = np.clip(z, 0, rows - 1.001)
    x0, z0 = np.floor(x).astype(np.int64), np.floor(z).astype(np.int64)
    fx, fz = x - x0, z - z0
    a = h[z0, x0] * (1 - fx) + h[z0, x0 + 1] * fx
    b = h[z0 + 1, x0] * (1 - fx) + h[z0 + 1, x0 + 1] * fx
    return a * (1 - fz) + b * fz


def march(h, origin, dirs, max_slope, t_max, iters=400):
    """Distance along each ray (in cells) to the terrain, inf where it misses."""
    rows, cols = h.shape
    t = np.zeros(dirs.shape[0])
    hit = np.zeros(dirs.shape[0], bool)
    live = np.ones(dirs.shape[0], bool)
    for _ in range(iters):
        idx = np.flatnonzero(live)
        if not idx.size:
            break
        p = origin[None, :] + dirs[idx] * t[idx, None]
        inside = (p[:, 0] >= 0) & (p[:, 0] <= cols - 1) & (p[:, 2] >= 0) & (p[:, 2] <= rows - 1)
        g = bilinear(h, p[:, 0], p[:, 2])
        above = p[:, 1] - g
        done = inside & (above < 0.05)
        hit[idx[done]] = True
        live[idx[done]] = False
        gone = t[idx] > t_max
        live[idx[gone & ~done]] = False
        step = np.maximum(above / (max_slope + 1.0), 0.25)
        t[idx[~done]] += step[~done]
    t[~hit] = np.inf
    return t


def render(height: np.ndarray, cell_m: float, width: int = 1024, azimuth_deg: float = 210.0,
           elevation_deg: float = 30.0, fov_deg: float = 50.0, distance: float = 1.25) -> np.ndarray:
    h = np.asarray(height, np.float64) / cell_m  # heights in cells
    rows, cols = h.shape
    gz, gx = np.gradient(h)
    max_slope = float(np.max(np.hypot(gx, gz)))
    centre = np.array([cols / 2, float(np.median(h)), rows / 2])
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    back = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    eye = centre + back * distance * max(rows, cols)
    fwd = -back
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    height_px = int(width * 9 / 16)
    tan = math.tan(math.radians(fov_deg) / 2)
    u = (np.arange(width) + 0.5) / width * 2 - 1
    v = 1 - (np.arange(height_px) + 0.5) / height_px * 2
    uu, vv = np.meshgrid(u * tan, v * tan * height_px / width)
    dirs = fwd[None, :] + uu.ravel()[:, None] * right[None, :] + vv.ravel()[:, None] * up[None, :]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = march(h, eye, dirs, max_slope, t_max=4.0 * max(rows, cols))
    hit = np.isfinite(t)
    p = eye[None, :] + dirs * np.where(hit, t, 0)[:, None]
    nx = -bilinear(gx, p[:, 0], p[:, 2])
    nz = -bilinear(gz, p[:, 0], p[:, 2])
    n = np.stack([nx, np.ones_like(nx), nz], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    sun = np.array([math.cos(math.radians(35)) * math.sin(math.radians(135)), math.sin(math.radians(35)),
                    math.cos(math.radians(35)) * math.cos(math.radians(135))])
    lam = np.clip(n @ sun, 0, 1)
    # shadow rays toward the sun from the hit points
    sh = np.ones(p.shape[0])
    idx = np.flatnonzero(hit)
    if idx.size:
        start = p[idx] + n[idx] * 0.5
        ts = _shadow(h, start, sun, max_slope)
        sh[idx] = np.where(np.isfinite(ts), 0.0, 1.0)
    slope = np.degrees(np.arccos(np.clip(n[:, 1], -1, 1)))
    rel = (p[:, 1] - h.min()) / max(np.ptp(h), 1e-9)
    grass = np.array([0.32, 0.38, 0.20])
    rock = np.array([0.45, 0.42, 0.38])
    snow = np.array([0.92, 0.93, 0.96])
    w_rock = np.clip((slope - 28) / 12, 0, 1)[:, None]
    w_snow = (np.clip((rel - 0.8) / 0.08, 0, 1) * np.clip((40 - slope) / 15, 0, 1))[:, None]
    albedo = (grass * (1 - w_rock) + rock * w_rock) * (1 - w_snow) + snow * w_snow
    sky_light = 0.35 * (0.5 + 0.5 * n[:, 1])
    colour = albedo * (1.1 * lam * sh + sky_light)[:, None]
    sky = np.array([0.62, 0.74, 0.90])
    fog = 0.6 * (1 - np.exp(-np.where(hit, t, 0) / (3.0 * max(rows, cols))))[:, None]
    colour = colour * (1 - fog) + sky * fog
    colour[~hit] = sky
    img = np.clip(colour, 0, 1) ** (1 / 2.2)
    return (img.reshape(height_px, width, 3) * 255 + 0.5).astype(np.uint8)


def _shadow(h, start, sun, max_slope, iters=160):
    """Distance to the first blocker toward the sun, inf when lit."""
    rows, cols = h.shape
    t = np.full(start.shape[0], 0.5)
    blocked = np.zeros(start.shape[0], bool)
    live = np.ones(start.shape[0], bool)
    top = h.max()
    for _ in range(iters):
        idx = np.flatnonzero(live)
        if not idx.size:
            break
        p = start[idx] + sun[None, :] * t[idx, None]
        out = (p[:, 0] < 0) | (p[:, 0] > cols - 1) | (p[:, 2] < 0) | (p[:, 2] > rows - 1) | (p[:, 1] > top)
        g = bilinear(h, p[:, 0], p[:, 2])
        above = p[:, 1] - g
        b = ~out & (above < 0)
        blocked[idx[b]] = True
        live[idx[b | out]] = False
        t[idx] += np.maximum(above / (max_slope + 1.0), 0.5)
    return np.where(blocked, 0.0, np.inf)


def main() -> None:
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    ap = argparse.ArgumentParser()
    ap.add_argument("height", help="a height EXR (first channel) or .npy")
    ap.add_argument("out", help="the PNG to write")
    ap.add_argument("--cell", type=float, default=None, help="cell size in m (default: the EXR's, 8 for .npy)")
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--azimuth", type=float, default=210.0)
    ap.add_argument("--elevation", type=float, default=30.0)
    ap.add_argument("--distance", type=float, default=1.25)
    ap.add_argument("--hillshade", default=None, help="also write the hillshade PNG here")
    args = ap.parse_args()
    from pipeline.exr import read_grid, write_png
    from pipeline.grid import Grid
    from worldlib.terrain.hillshade import hillshade

    if args.height.endswith(".npy"):
        h, cell = np.load(args.height), args.cell or 8.0
    else:
        g = read_grid(args.height)
        h, cell = g.channel(g.channels[0]), args.cell or g.cell_size_m
    write_png(args.out, render(cl_env, h, cell, args.width, args.azimuth, args.elevation, distance=args.distance))
    if args.hillshade:
        write_png(args.hillshade, hillshade(Grid(np.asarray(h, np.float32), cell)))


if __name__ == "__main__":
    main()
