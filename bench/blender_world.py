"""A baked world rendered by Blender (Cycles, CPU) with its DCC selection
(stages/world/dcc_layer.py), beside the project's renderer from the same
cameras (not a test; needs .venv-blender, `make dcc-env`):

    python -m bench.blender_world WORLD.usda OUT_FOLDER [--views world stand60 stand2] [--width 960 --height 540]
        [--samples 16] [--ours]

Per view prints the Blender process' wall and CPU seconds and its peak RSS
(VmHWM of the whole process: import, scene sync, render), and writes
blender_<view>.png (and .exr, .json); with --ours also ours_<view>.png and
side_<view>.png (Blender left, ours right). Views: `world` the world
renderer's default camera (worldlib.render.world_view.default_camera);
`stand60` a conifer stand near the world's centre from 60 m; `stand2` the
same stand from 2 m above the ground inside it."""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BLENDER_PY = REPO / ".venv-blender" / "bin" / "python"
SCRIPT = REPO / "tests" / "dcc" / "blender_scripts" / "render_view.py"
SKY_RGB = (0.55, 0.68, 0.85)  # world_view's background
SUN = (-0.45, 0.75, 0.5)  # world_view's sun
TRANSPARENT_BOUNCES = 128  # as the README advises: Blender's default 8 ends paths inside a canopy of leaf cards


def terrain_bounds(world: Path) -> tuple[np.ndarray, np.ndarray]:
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world), Usd.Stage.LoadNone)
    r = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeWorldBound(
        stage.GetPrimAtPath("/World/Terrain")).ComputeAlignedRange()
    return np.array(r.GetMin()), np.array(r.GetMax())


def plant_positions(world: Path, centre: np.ndarray, radius_m: float, species: str | None = None) -> np.ndarray:
    """The bases of the plants (of one species, or all) within radius_m of the centre, horizontally."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world))
    pts = [np.zeros((0, 3))]
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointInstancer) and (species is None or prim.GetName() == species):
            p = np.asarray(UsdGeom.PointInstancer(prim).GetPositionsAttr().Get() or [], np.float64).reshape(-1, 3)
            m = np.asarray(UsdGeom.XformCache().GetLocalToWorldTransform(prim))
            p = p @ m[:3, :3] + m[3, :3]
            pts.append(p[np.hypot(p[:, 0] - centre[0], p[:, 2] - centre[2]) < radius_m])
    return np.concatenate(pts)


def clear_eye(world: Path, stand: np.ndarray) -> np.ndarray:
    """Where to stand 6 to 12 m from the stand's plant: of 16 directions and
    four distances, the spot farthest from every plant's trunk (not inside a crown)."""
    near = plant_positions(world, stand, 40.0)
    best, best_clear = stand, -1.0
    for dist in (8.0, 6.0, 10.0, 12.0):
        for a in np.radians(np.arange(0.0, 360.0, 22.5)):
            c = stand + dist * np.array([math.cos(a), 0.0, math.sin(a)])
            clear = float(np.hypot(near[:, 0] - c[0], near[:, 2] - c[2]).min()) if len(near) else math.inf
            if clear > best_clear + 0.25:  # a clearly better spot; ties keep the nearer distance
                best, best_clear = c, clear
    return best


def stand_point(world: Path, centre: np.ndarray, species: str = "conifer") -> np.ndarray:
    """The plant of the species near the centre with the most neighbours within 20 m (its base)."""
    from scipy.spatial import cKDTree

    p = plant_positions(world, centre, 400.0, species)
    if len(p) == 0:
        raise SystemExit(f"no {species} within 400 m of the centre")
    counts = np.array([len(n) for n in cKDTree(p[:, [0, 2]]).query_ball_point(p[:, [0, 2]], 20.0)])
    return p[int(np.argmax(counts))]


def ground_y(world: Path, x: float, z: float) -> float:
    """The terrain mesh's height at its vertex nearest (x, z)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(world), Usd.Stage.LoadNone)
    stage.Load("/World/Terrain/Ground")  # its tiles' payloads (stages/world/terrain_tiles.py), not the plants'
    parts = []
    for prim in Usd.PrimRange(stage.GetPrimAtPath("/World/Terrain/Ground")):
        if prim.IsA(UsdGeom.Mesh):
            m = np.asarray(UsdGeom.XformCache().GetLocalToWorldTransform(prim))
            parts.append(np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), np.float64) @ m[:3, :3] + m[3, :3])
    p = np.concatenate(parts)
    return float(p[np.argmin((p[:, 0] - x) ** 2 + (p[:, 2] - z) ** 2), 1])


def cameras(world: Path, width: int, height: int, views: list[str]) -> dict:
    from worldlib.render import Camera
    from worldlib.render.world_view import default_camera

    lo, hi = terrain_bounds(world)
    out = {}
    if "world" in views:
        out["world"] = default_camera(lo, hi, aspect=width / height)
    if {"stand60", "stand2"} & set(views):
        s = stand_point(world, 0.5 * (lo + hi))
        look = s + np.array([0.0, 6.0, 0.0])
        d = np.array([math.cos(math.radians(30)), 0.0, math.sin(math.radians(30))])
        eye60 = look - d * 60.0 * math.cos(math.radians(20)) + np.array([0.0, 60.0 * math.sin(math.radians(20)), 0.0])
        out["stand60"] = Camera(tuple(eye60), tuple(look - eye60), (0.0, 1.0, 0.0), fov_y_deg=40.0)
        eye2 = clear_eye(world, s)  # not inside another tree's crown
        eye2[1] = max(ground_y(world, eye2[0], eye2[2]), s[1]) + 2.0  # 2 m above the ground there
        d2 = (s - eye2) * np.array([1.0, 0.0, 1.0])
        d2 /= np.linalg.norm(d2)
        out["stand2"] = Camera(tuple(eye2), tuple(d2 + np.array([0.0, 0.15, 0.0])), (0.0, 1.0, 0.0), fov_y_deg=60.0)
    return out


def blender_render(world: Path, prefix: Path, cam, width: int, height: int, samples: int) -> dict:
    spec = {"camera": {"eye": list(map(float, cam.eye)), "forward": list(map(float, cam.forward)),
                       "up": list(map(float, cam.up)), "fov_y_deg": cam.fov_y_deg, "clip_start": 0.1},
            "width": width, "height": height, "samples": samples, "sun": list(SUN), "sky": 0.5,
            "transparent_bounces": TRANSPARENT_BOUNCES}
    spec_path = prefix.with_suffix(".spec.json")
    spec_path.write_text(json.dumps(spec))
    t = time.perf_counter()
    proc = subprocess.Popen([str(BLENDER_PY), str(SCRIPT), str(world), str(prefix), str(spec_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    if status != 0:
        raise SystemExit(f"Blender failed ({status}):\n{out.decode(errors='replace')[-3000:]}")
    info = json.loads(prefix.with_suffix(".json").read_text())
    return {"wall_s": round(wall, 1), "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
            "peak_rss_mb": info["peak_rss_mb"], "import_s": info["import"]["seconds"],
            "render_s": info["render_seconds"]}


def over_sky(rgba: np.ndarray) -> np.ndarray:
    """Premultiplied linear RGBA over world_view's background, sRGB 8 bit."""
    from worldlib.render import srgb8

    return srgb8(rgba[..., :3] + (1.0 - rgba[..., 3:4]) * np.asarray(SKY_RGB, np.float32))


def main(argv=None) -> None:
    import OpenImageIO as oiio

    ap = argparse.ArgumentParser()
    ap.add_argument("world")
    ap.add_argument("out")
    ap.add_argument("--views", nargs="+", default=["world", "stand60", "stand2"])
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=540)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--ours", action="store_true", help="also the project's renderer, and side-by-side pictures")
    a = ap.parse_args(argv)
    if not BLENDER_PY.exists():
        raise SystemExit(f"{BLENDER_PY} is missing: `make dcc-env` installs Blender (bpy)")
    world, out = Path(a.world).resolve(), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cams = cameras(world, a.width, a.height, a.views)
    for view, cam in cams.items():
        prefix = out / f"blender_{view}"
        m = blender_render(world, prefix, cam, a.width, a.height, a.samples)
        print(f"{view}: Blender {a.width}x{a.height}, {a.samples} samples: wall {m['wall_s']} s, CPU {m['cpu_s']} s, "
              f"peak RSS {m['peak_rss_mb']} MB (import {m['import_s']} s, render {m['render_s']} s)", flush=True)
        mine = np.asarray(oiio.ImageBuf(str(prefix) + ".exr").get_pixels(oiio.FLOAT), np.float32)
        left = over_sky(mine)
        oiio.ImageBuf(np.ascontiguousarray(left)).write(str(out / f"blender_{view}_sky.png"))
        if a.ours:
            from pipeline.opencl import get_cl
            from worldlib.render import world_view

            full = out / "ours_world_lod0.usda"  # our renderer picks LODs itself: every asset at its own LOD0
            if not full.exists():
                from stages.world.dcc_layer import write_shot_layer

                write_shot_layer(world, full, lod="LOD0")
            rgba = world_view.render_world(get_cl(), full, a.width, a.height, camera=cam, sun=SUN)
            world_view.save_png(out / f"ours_{view}.png", rgba)
            side = np.concatenate([left, np.full((a.height, 8, 3), 255, np.uint8), rgba[..., :3]], 1)
            oiio.ImageBuf(np.ascontiguousarray(side)).write(str(out / f"side_{view}.png"))
    print("wrote", out)


if __name__ == "__main__":
    main()
