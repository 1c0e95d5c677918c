"""Shared by the scripts Blender runs for tests/dcc and bench/blender_*.py
(run with .venv-blender/bin/python: bpy, numpy<2, no project imports).

The scene set-up matches the project's renderer (worldlib.render.Image.shaded):
a sun from SUN (y up) lighting 1.1 x Lambert and a uniform sky of 0.45 that
stands for its ambient-occlusion term, direct light only (no diffuse
bounces: ours has none), on a transparent film so alpha is coverage."""
from __future__ import annotations

import json
import math
import os
import resource
import sys
import tempfile
import time
from contextlib import contextmanager

import bpy
from mathutils import Matrix, Vector

SUN = (0.4, 0.8, 0.45)  # worldlib.render.scene.Image.shaded's default sun, y up
SUN_GAIN = 1.1
SKY = 0.45


def to_blender(v) -> Vector:
    """A y-up USD direction or point in Blender's z-up frame (the importer
    turns a y-up stage by +90 degrees about x)."""
    x, y, z = (float(c) for c in v)
    return Vector((x, -z, y))


def args() -> list[str]:
    argv = sys.argv
    return argv[argv.index("--") + 1:] if "--" in argv else argv[1:]


def reset() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


@contextmanager
def captured(log: list):
    """The process' stdout and stderr (C level: Blender's reports, CLOG and
    USD's diagnostics) while the block runs, appended to log as lines."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            f.seek(0)
            log.extend(f.read().decode("utf-8", "replace").splitlines())


def import_usd(path: str, **options) -> dict:
    """Imports as a user would (the operator's defaults but packing, which
    only copies the textures into the .blend); returns seconds, the
    operator's result and the captured log."""
    log: list[str] = []
    t = time.perf_counter()
    with captured(log):
        result = bpy.ops.wm.usd_import(filepath=path, import_textures_mode=options.pop("textures", "IMPORT_NONE"),
                                       **options)
    return {"seconds": round(time.perf_counter() - t, 3), "result": sorted(result), "log": log}


def look_at(obj, eye, forward, up) -> None:
    f = to_blender(forward).normalized()
    u = to_blender(up)
    r = f.cross(u).normalized()
    u = r.cross(f)
    m = Matrix((r, u, -f)).transposed().to_4x4()
    m.translation = to_blender(eye)
    obj.matrix_world = m


def camera(cam: dict, width: int, height: int):
    """cam: eye, forward, up (y up, m) and ortho_height_m or fov_y_deg, as
    worldlib.render.Camera."""
    scene = bpy.context.scene
    data = bpy.data.cameras.new("TestCamera")
    obj = bpy.data.objects.new("TestCamera", data)
    scene.collection.objects.link(obj)
    data.sensor_fit = "VERTICAL"
    if cam.get("ortho_height_m", 0.0) > 0.0:
        data.type = "ORTHO"
        # the ortho scale spans the larger side
        data.ortho_scale = cam["ortho_height_m"] * max(width, height) / height
        data.sensor_fit = "AUTO"
    else:
        data.angle_y = math.radians(cam.get("fov_y_deg", 40.0))
    data.clip_start = cam.get("clip_start", 0.01)
    data.clip_end = cam.get("clip_end", 1.0e5)
    look_at(obj, cam["eye"], cam["forward"], cam.get("up", (0.0, 1.0, 0.0)))
    scene.camera = obj
    return obj


def lights(sun=SUN, gain=SUN_GAIN, sky=SKY, sun_shadows: bool = True) -> None:
    """Sun and sky as worldlib.render's shaded(): Cycles' sun strength is
    irradiance (W/m^2), a white Lambert surface facing it shows strength/pi.
    sun_shadows False: the sun casts none, as in shaded() (its sky term is
    occluded, its sun Lambert only)."""
    scene = bpy.context.scene
    data = bpy.data.lights.new("TestSun", "SUN")
    data.use_shadow = sun_shadows
    data.energy = gain * math.pi
    data.angle = math.radians(0.5)
    obj = bpy.data.objects.new("TestSun", data)
    scene.collection.objects.link(obj)
    z = to_blender(sun).normalized()  # the lamp shines along its -z
    x = z.orthogonal().normalized()
    obj.matrix_world = Matrix((x, z.cross(x), z)).transposed().to_4x4()
    world = bpy.data.worlds.new("TestSky")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = sky
    scene.world = world


def cycles(width: int, height: int, samples: int, threads: int = 0, transparent_bounces: int = 0) -> None:
    """transparent_bounces: 0 keeps Blender's default."""
    scene = bpy.context.scene
    if transparent_bounces:
        scene.cycles.transparent_max_bounces = transparent_bounces
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.seed = 1
    # direct light only, as our renderer (its sky term is ambient occlusion); transparency as Blender's default
    scene.cycles.max_bounces = max(scene.cycles.transparent_max_bounces, 1)
    scene.cycles.diffuse_bounces = 0
    scene.cycles.glossy_bounces = 0
    scene.cycles.transmission_bounces = 0
    scene.cycles.volume_bounces = 0
    scene.cycles.caustics_reflective = False
    scene.cycles.caustics_refractive = False
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    if threads:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = threads


def render(out_prefix: str) -> dict:
    """Renders; writes OUT.exr (linear premultiplied RGBA, 32-bit) and
    OUT.png (sRGB, for eyes); returns seconds and the log."""
    scene = bpy.context.scene
    log: list[str] = []
    t = time.perf_counter()
    with captured(log):
        bpy.ops.render.render(write_still=False)
    seconds = time.perf_counter() - t
    img = bpy.data.images["Render Result"]
    s = scene.render.image_settings
    s.file_format, s.color_depth, s.color_mode = "OPEN_EXR", "32", "RGBA"
    img.save_render(out_prefix + ".exr", scene=scene)
    s.file_format, s.color_depth = "PNG", "8"
    img.save_render(out_prefix + ".png", scene=scene)
    return {"render_seconds": round(seconds, 3), "render_log": log[-40:]}


def peak_rss_mb() -> float:
    """This process' peak resident set (VmHWM: of its own memory since exec;
    getrusage's ru_maxrss also counts the parent's resident set at fork)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


def write_json(path: str, data: dict) -> None:
    data["peak_rss_mb"] = peak_rss_mb()
    with open(path, "w") as f:
        json.dump(data, f, indent=1, sort_keys=True)
