"""The offline renderer the baking stages share (plants' foliage cards and
crown measurements, impostor atlases, volume error views, report pictures).

Ray casting through a BVH (bvh.py) in an OpenCL kernel (kernels.cl), with a
brute-force numpy reference (reference.py) for tiny scenes:

    img = render(scene, Camera(eye, forward, ortho_height_m=2.0), Settings(256, 256, samples=3, ao_rays=8))
    img.albedo, img.alpha, img.normal, img.depth, img.ao

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
from .scene import Camera, Image, Scene, Settings, linear_from_srgb, srgb8

__all__ = ["Camera", "Image", "Scene", "Settings", "render", "reference", "linear_from_srgb", "srgb8", "KERNELS"]

KERNELS = Path(__file__).with_name("kernels.cl")
LOCAL = (8, 8)
_KERNEL: dict = {}


def _kernel():
    import pyopencl as cl

    from pipeline.opencl import load_program

    prg = load_program(KERNELS)
    if id(prg) not in _KERNEL:
        _KERNEL[id(prg)] = cl.Kernel(prg, "render")
    return _KERNEL[id(prg)]


class Prepared:
    """A scene's BVH and device buffers, to render many views of one scene."""

    def __init__(self, scene: Scene, leaf_size: int = 4):
        import pyopencl as cl

        from pipeline.opencl import get_cl

        self.scene = scene
        tree = _bvh.build(scene.positions, scene.triangles, leaf_size)
        if tree.depth_bound >= 60:
            raise ValueError("the scene's BVH is deeper than the kernel's stack")
        o = tree.order
        tris = scene.triangles[o]
        env = get_cl()
        mf = cl.mem_flags

        def buf(a):
            a = np.ascontiguousarray(a)
            if a.size == 0:
                a = np.zeros(4, a.dtype)
            return cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)

        self.buffers = [buf(tree.nodes.ravel()), buf(scene.positions[tris].astype(np.float32).ravel()),
                        buf(scene.normals[tris].astype(np.float32).ravel()), buf(scene.uv[tris].astype(np.float32).ravel()),
                        buf(scene.tint[o].astype(np.float32).ravel()), buf(scene.texture[o].astype(np.int32)),
                        buf(scene.textures.ravel())]
        self.n_nodes = len(tree.nodes)

    def render(self, camera: Camera, settings: Settings, local: tuple[int, int] | None = LOCAL) -> Image:
        import pyopencl as cl

        from pipeline.opencl import get_cl, global_size

        env = get_cl()
        W, H = settings.width, settings.height
        _, th, tw, _ = self.scene.textures.shape
        mf = cl.mem_flags
        cam = cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=camera.frame(W, H))
        outs = [np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32),
                np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)]
        dev = [cl.Buffer(env.ctx, mf.WRITE_ONLY, a.nbytes) for a in outs]
        k = _kernel()
        k(env.queue, global_size((W, H), local), local, np.int32(W), np.int32(H), np.int32(settings.samples),
          np.int32(settings.ao_rays), np.float32(settings.ao_radius_m), np.float32(settings.alpha_threshold),
          np.uint32(settings.seed & 0xFFFFFFFF), np.int32(tw), np.int32(th), cam, *self.buffers, *dev)
        for a, b in zip(outs, dev):
            cl.enqueue_copy(env.queue, a, b)
        env.queue.finish()
        return Image(*outs)


def render(scene: Scene, camera: Camera, settings: Settings, device: bool = True,
           local: tuple[int, int] | None = LOCAL) -> Image:
    """Render one view: on the OpenCL device (default) or with the numpy
    reference (device=False; tiny scenes only). `local` is the work-group
    size (None lets the runtime choose); the image does not depend on it."""
    if settings.width < 1 or settings.height < 1 or settings.samples < 1:
        raise ValueError(f"render size {settings.width}x{settings.height} with {settings.samples}^2 samples")
    if not device:
        return reference.render(scene, camera, settings)
    if scene.n_triangles == 0:
        W, H = settings.width, settings.height
        return Image(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32),
                     np.full((H, W), np.inf, np.float32), np.ones((H, W), np.float32))
    return Prepared(scene).render(camera, settings, local)
