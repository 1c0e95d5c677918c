"""Scenes and cameras of the offline renderer.

A Scene is a triangle soup with per-corner attributes: positions, shading
normals and uv per vertex row, and per triangle a linear albedo tint and a
texture index into one stack of equally sized RGBA textures (linear albedo,
alpha). Cards are triangles whose texture alpha is tested: a hit where the
texture's alpha is below `alpha_threshold` is no hit (the ray goes on).

Texture lookup is nearest-texel with wrapping uv (u - floor(u)): bark
repeats along branches and atlas cells sit inside [0, 1]. Nearest keeps
the kernel and the numpy reference bit-comparable; supersampling does the
filtering.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole (perspective) or orthographic camera.

    eye: position (m); forward, up: directions (up is made orthogonal);
    ortho_height_m: height of the view for an orthographic camera (its width
    follows the image's aspect); fov_y_deg: vertical field of view for a
    perspective one (used when ortho_height_m is 0)."""

    eye: tuple[float, float, float]
    forward: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    ortho_height_m: float = 0.0
    fov_y_deg: float = 40.0
    ortho_width_m: float = 0.0  # 0: the image's aspect; else texels are stretched (a card's texture)

    @property
    def orthographic(self) -> bool:
        return self.ortho_height_m > 0.0

    def frame(self, width: int, height: int) -> np.ndarray:
        """float32[16]: eye, forward, right * half width, up * half height
        (of the image plane at distance 1 for perspective, of the view for
        orthographic), orthographic flag; the kernel's camera record."""
        f = np.asarray(self.forward, np.float64)
        f = f / np.linalg.norm(f)
        u = np.asarray(self.up, np.float64)
        r = np.cross(f, u)
        if np.linalg.norm(r) < 1e-9:
            raise ValueError(f"camera up {self.up} is parallel to forward {self.forward}")
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        aspect = width / height
        half_h = 0.5 * self.ortho_height_m if self.orthographic else math.tan(math.radians(0.5 * self.fov_y_deg))
        half_w = 0.5 * self.ortho_width_m if self.orthographic and self.ortho_width_m > 0 else half_h * aspect
        rec = np.zeros(16, np.float32)
        rec[0:3], rec[3:6], rec[6:9], rec[9:12] = self.eye, f, r * half_w, u * half_h
        rec[12] = 1.0 if self.orthographic else 0.0
        return rec


@dataclass(frozen=True)
class Settings:
    """width, height: pixels; samples: n x n sub-pixel samples per pixel (a
    fixed stratified grid); ao_rays: ambient-occlusion rays per covered
    sample (0: no AO, the channel is 1); ao_radius_m: occluders farther than
    this do not count; alpha_threshold: the alpha test of textured cards;
    seed: of the counter-based AO directions; max_depth_m: camera rays end
    there (a slab's far face: nothing behind it is traversed)."""

    width: int = 256
    height: int = 256
    samples: int = 2
    ao_rays: int = 0
    ao_radius_m: float = 1.0
    alpha_threshold: float = 0.5
    seed: int = 0
    max_depth_m: float = math.inf


@dataclass
class Scene:
    """positions, normals (n, 3) and uv (n, 2) per vertex row; triangles (m, 3)
    into the rows; tint (m, 3) linear albedo per triangle (multiplies the
    texture); texture (m,) index into `textures` (k, H, W, 4) or -1."""

    positions: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    tint: np.ndarray
    texture: np.ndarray
    textures: np.ndarray = field(default_factory=lambda: np.ones((1, 1, 1, 4), np.float32))

    def digest(self) -> str:
        """sha256 of everything a render of the scene reads (what a cache of
        its renders is keyed by)."""
        import hashlib

        h = hashlib.sha256()
        for a in (self.positions, self.normals, self.uv, self.triangles, self.tint, self.texture, self.textures):
            h.update(repr((a.dtype.str, a.shape)).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def __post_init__(self):
        self.positions = np.ascontiguousarray(self.positions, np.float32).reshape(-1, 3)
        self.normals = np.ascontiguousarray(self.normals, np.float32).reshape(-1, 3)
        self.uv = np.ascontiguousarray(self.uv, np.float32).reshape(-1, 2)
        self.triangles = np.ascontiguousarray(self.triangles, np.int32).reshape(-1, 3)
        m = len(self.triangles)
        self.tint = np.ascontiguousarray(np.broadcast_to(np.asarray(self.tint, np.float32), (m, 3)))
        self.texture = np.ascontiguousarray(np.broadcast_to(np.asarray(self.texture, np.int32), (m,)))
        self.textures = np.ascontiguousarray(self.textures, np.float32)
        if self.textures.ndim != 4 or self.textures.shape[3] != 4:
            raise ValueError(f"textures must be (k, H, W, 4), got {self.textures.shape}")
        if m and (self.triangles.min() < 0 or self.triangles.max() >= len(self.positions)):
            raise ValueError("triangles index outside the vertex rows")
        if m and self.texture.max() >= len(self.textures):
            raise ValueError("a triangle names a texture that is not in the stack")
        for name in ("positions", "normals", "uv", "tint", "textures"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"scene {name} hold NaN or Inf")

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @staticmethod
    def concat(scenes: list["Scene"]) -> "Scene":
        """One scene from several; their texture stacks must have one size."""
        scenes = [s for s in scenes if s.n_triangles]
        if not scenes:
            return Scene(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        shape = scenes[0].textures.shape[1:]
        texs, vo, to = [], 0, 0
        tris, tex_ids = [], []
        for s in scenes:
            if s.textures.shape[1:] != shape:
                raise ValueError("scenes with textures of different sizes cannot be joined")
            tris.append(s.triangles + vo)
            tex_ids.append(np.where(s.texture >= 0, s.texture + to, -1))
            texs.append(s.textures)
            vo += len(s.positions)
            to += len(s.textures)
        return Scene(np.concatenate([s.positions for s in scenes]), np.concatenate([s.normals for s in scenes]),
                     np.concatenate([s.uv for s in scenes]), np.concatenate(tris), np.concatenate([s.tint for s in scenes]),
                     np.concatenate(tex_ids), np.concatenate(texs))

    def transformed(self, matrix: np.ndarray) -> "Scene":
        """The scene under a 4x4 affine matrix (column vectors)."""
        m = np.asarray(matrix, np.float64)
        p = self.positions @ m[:3, :3].T + m[:3, 3]
        nrm = self.normals @ np.linalg.inv(m[:3, :3])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-20)
        return Scene(p, nrm, self.uv, self.triangles, self.tint, self.texture, self.textures)


@dataclass(frozen=True)
class Image:
    """The render's channels, each (height, width[, c]) float32:
    albedo: premultiplied linear RGB (mean over the samples of albedo x coverage);
    alpha: covered share of the samples; normal: mean world-space normal of the
    covered samples, facing the camera (0 where nothing is covered); depth:
    nearest hit distance along the ray (inf where nothing); ao: mean share of
    unoccluded AO rays over the covered samples (1 where nothing is covered)."""

    albedo: np.ndarray
    alpha: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    ao: np.ndarray

    def shaded(self, sun=(0.4, 0.8, 0.45), sky: float = 0.45, background=(0.55, 0.65, 0.8)) -> np.ndarray:
        """A display picture (linear RGB): albedo x (sun Lambert, a third of it
        through surfaces facing away, as thin leaves pass light, + sky x AO)
        over a background."""
        s = np.asarray(sun, np.float32)
        s /= np.linalg.norm(s)
        n = self.normal / np.maximum(np.linalg.norm(self.normal, axis=2, keepdims=True), 1e-6)
        cos = n @ s
        lam = np.clip(cos, 0.0, 1.0) + 0.33 * np.clip(-cos, 0.0, 1.0)
        light = (1.1 * lam + sky * self.ao)[..., None]
        bg = np.asarray(background, np.float32)[None, None, :]
        return self.albedo * light + (1.0 - self.alpha[..., None]) * bg


