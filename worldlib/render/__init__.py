"""The offline renderer the baking stages share (plants' foliage cards and
crown measurements, impostor atlases, volume error views, report pictures).

Ray casting through a BVH (bvh.py) in an OpenCL kernel (kernels.cl), with a
brute-force numpy reference (reference.py) for tiny scenes. `env` is the
OpenCL device (pipeline.opencl.CL; a stage's ctx.cl), None for the reference:

    img = render(env, scene, Camera(eye, forward, ortho_height_m=2.0), Settings(256, 256, samples=3, ao_rays=8))
    img.albedo, img.alpha, img.normal, img.depth, img.ao

Many views of one scene (atlas frames, held-out views, measures): prepare
it once, so its BVH is built and its buffers uploaded once, then render:

    prepared = Prepared(env, scene)
    images = [prepared.render(camera, settings) for camera in cameras]

`render(env, scene, ...)` prepares the scene for that one view. The kernel
traverses a four-wide BVH (bvh.widen), so the images do not depend on the
tree: of hits at equal distance the lowest scene triangle id wins, as in
the reference.

Why ray casting and not rasterization: ambient occlusion needs rays against
the whole scene anyway, the alpha test of cards is the same code for primary
and AO rays, and one work-item per pixel that owns its samples makes the
image independent of the work-group size with no atomics or depth-buffer
races (a rasterizer's z-test over triangles in parallel needs ordered
writes). bench/render.py measures rays per second against Embree.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import bvh as _bvh
from . import reference
from pipeline.exr import linear_from_srgb, srgb8

from .scene import Camera, Image, Scene, Settings

__all__ = ["Camera", "Image", "Prepared", "Scene", "Settings", "render", "reference", "linear_from_srgb", "srgb8",
           "KERNELS"]

KERNELS = Path(__file__).with_name("kernels.cl")
LOCAL = (8, 8)
LEAF_SIZE = 4  # most triangles in a BVH leaf
STACK = 80  # the kernel's traversal stack (kernels.cl)
_KERNEL: dict = {}


def _kernel(env):
    import pyopencl as cl

    from pipeline.opencl import load_program

    prg = load_program(env, KERNELS)
    if id(prg) not in _KERNEL:
        _KERNEL[id(prg)] = cl.Kernel(prg, "render")
    return _KERNEL[id(prg)]


def slot_corners(scene: Scene, slots: np.ndarray) -> np.ndarray:
    """(slots, 3) vertex rows of each slot's triangle (an empty slot is never
    hit: it takes any triangle's, or row 0 of an empty scene's)."""
    if scene.n_triangles == 0:
        return np.zeros((len(slots), 3), np.int64)
    return scene.triangles[np.maximum(slots, 0)]


def triangle_blocks(scene: Scene, slots: np.ndarray) -> np.ndarray:
    """(b, 48) float32, the kernel's triangles four to a block (a leaf), one
    lane each: rows p0.x, p0.y, p0.z, e1.x .. e1.z, e2.x .. e2.z (e1 = p1 - p0,
    e2 = p2 - p0, float32 differences as the kernel would compute them), the
    scene triangle id and the texture index (int bits), then a pad row. An
    empty slot is a degenerate triangle (zero edges: no ray hits it)."""
    used = slots >= 0
    p = np.zeros((len(slots), 3, 3), np.float32)
    p[used] = scene.positions[scene.triangles[slots[used]]]
    texture = np.full(len(slots), -1, np.int32)
    texture[used] = scene.texture[slots[used]]
    lanes = np.zeros((len(slots), 12), np.float32)
    lanes[:, 0:3], lanes[:, 3:6], lanes[:, 6:9] = p[:, 0], p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    ints = lanes.view(np.int32)
    ints[:, 9] = np.where(used, slots, -1)
    ints[:, 10] = texture
    return np.ascontiguousarray(lanes.reshape(-1, 4, 12).transpose(0, 2, 1)).reshape(-1, 48)


class Prepared:
    """A scene's BVH and buffers on the OpenCL device `env`
    (pipeline.opencl.CL), to render many views of one scene: build one per
    scene and call render() per view (the BVH build costs more than a small
    view's rays)."""

    def __init__(self, env, scene: Scene, leaf_size: int = LEAF_SIZE):
        import pyopencl as cl

        self.env, self.scene = env, scene
        _kernel(env)  # built now: a missing device is named before the BVH is built
        if not 1 <= leaf_size <= 4:
            raise ValueError(f"leaf_size {leaf_size}: the kernel's leaves hold 1 to 4 triangles")
        tree = _bvh.widen(_bvh.build(scene.positions, scene.triangles, leaf_size))
        if 3 * tree.depth + 4 > STACK:  # a node pops one entry and pushes at most four
            raise ValueError(f"the scene's BVH ({tree.depth} levels) is deeper than the kernel's stack")
        mf = cl.mem_flags

        def buf(a):
            a = np.ascontiguousarray(a)
            if a.size == 0:
                a = np.zeros(4, a.dtype)
            return cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)

        corners = slot_corners(scene, tree.slots)
        self.buffers = [buf(tree.nodes.ravel()), buf(triangle_blocks(scene, tree.slots).ravel()),
                        buf(scene.normals[corners].ravel()), buf(scene.uv[corners].ravel()),
                        buf(scene.tint[np.maximum(tree.slots, 0)].ravel() if scene.n_triangles else np.zeros(4, np.float32)),
                        buf(np.array([t[..., 3].min() for t in scene.textures] or [1.0], np.float32)),
                        buf(scene.textures.ravel())]
        self.n_nodes = len(tree.nodes)

    def render(self, camera: Camera, settings: Settings, local: tuple[int, int] | None = LOCAL) -> Image:
        import pyopencl as cl

        from pipeline.opencl import global_size

        env = self.env
        W, H = settings.width, settings.height
        _, th, tw, _ = self.scene.textures.shape
        mf = cl.mem_flags
        cam = cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=camera.frame(W, H))
        outs = [np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32),
                np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)]
        dev = [cl.Buffer(env.ctx, mf.WRITE_ONLY, a.nbytes) for a in outs]
        k = _kernel(env)
        k(env.queue, global_size((W, H), local), local, np.int32(W), np.int32(H), np.int32(settings.samples),
          np.int32(settings.ao_rays), np.float32(settings.ao_radius_m), np.float32(settings.alpha_threshold),
          np.uint32(settings.seed & 0xFFFFFFFF), np.float32(settings.max_depth_m), np.int32(tw), np.int32(th), cam,
          *self.buffers, *dev)
        for a, b in zip(outs, dev):
            cl.enqueue_copy(env.queue, a, b)
        env.queue.finish()
        return Image(*outs)


def render(env, scene: Scene, camera: Camera, settings: Settings,
           local: tuple[int, int] | None = LOCAL) -> Image:
    """Render one view: on the OpenCL device `env` (pipeline.opencl.CL) or,
    with env None, with the numpy reference (tiny scenes only). `local` is
    the work-group size (None lets the runtime choose); the image does not
    depend on it."""
    if settings.width < 1 or settings.height < 1 or settings.samples < 1:
        raise ValueError(f"render size {settings.width}x{settings.height} with {settings.samples}^2 samples")
    if env is None:
        return reference.render(scene, camera, settings)
    if scene.n_triangles == 0:
        W, H = settings.width, settings.height
        return Image(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32),
                     np.full((H, W), np.inf, np.float32), np.ones((H, W), np.float32))
    return Prepared(env, scene).render(camera, settings, local)
