"""The renderer in plain numpy, for tiny scenes: every ray against every
triangle (no BVH), float64, the same sub-pixel grid, alpha test, texel
lookup and counter-based AO directions as kernels.cl. Obviously right and
slow: tests compare the kernel with it."""
from __future__ import annotations

import numpy as np

from .scene import Camera, Image, Scene, Settings


def mix32(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.uint32).copy()
    x ^= x >> np.uint32(16)
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def unit_random(seed: int, pixel: np.ndarray, stream: np.ndarray) -> np.ndarray:
    h0 = mix32(np.array([(seed ^ 0x9E3779B9) & 0xFFFFFFFF], np.uint32))
    h = mix32(mix32(h0 ^ np.asarray(pixel, np.uint32)) ^ np.asarray(stream, np.uint32))
    return (h >> np.uint32(8)).astype(np.float64) / 16777216.0


def _texel(scene: Scene, tri: np.ndarray, b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """RGBA under the barycentric point (1 where the triangle has no texture)."""
    out = np.ones((len(tri), 4))
    k = scene.texture[tri]
    has = k >= 0
    if not has.any():
        return out
    _, th, tw, _ = scene.textures.shape
    uvc = scene.uv[scene.triangles[tri[has]]].astype(np.float64)  # (n, 3, 2)
    bb1, bb2 = b1[has], b2[has]
    uv = (1 - bb1 - bb2)[:, None] * uvc[:, 0] + bb1[:, None] * uvc[:, 1] + bb2[:, None] * uvc[:, 2]
    f = uv - np.floor(uv)
    x = np.minimum((f[:, 0] * tw).astype(np.int64), tw - 1)
    y = np.minimum(((1 - f[:, 1]) * th).astype(np.int64), th - 1)
    out[has] = scene.textures[k[has], y, x]
    return out


def trace(scene: Scene, o: np.ndarray, d: np.ndarray, tmin: float, tmax, alpha_threshold: float):
    """Closest alpha-passing hit of each ray: (tri or -1, t, b1, b2)."""
    n = len(o)
    best = np.full(n, -1, np.int64)
    tbest = np.broadcast_to(np.asarray(tmax, np.float64), (n,)).copy()
    bb1, bb2 = np.zeros(n), np.zeros(n)
    P = scene.positions.astype(np.float64)[scene.triangles]  # (m, 3, 3)
    for tri in range(scene.n_triangles):
        p0, p1, p2 = P[tri]
        e1, e2 = p1 - p0, p2 - p0
        pv = np.cross(d, e2)
        det = pv @ e1
        ok = np.abs(det) >= 1e-20
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = o - p0
        b1 = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        b2 = np.einsum("ij,ij->i", d, qv) * inv
        t = (qv @ e2) * inv
        ok &= (b1 >= 0) & (b1 <= 1) & (b2 >= 0) & (b1 + b2 <= 1) & (t > tmin) & (t < tbest)
        if not ok.any():
            continue
        idx = np.nonzero(ok)[0]
        a = _texel(scene, np.full(len(idx), tri), b1[idx], b2[idx])[:, 3]
        idx = idx[a >= alpha_threshold]
        best[idx], tbest[idx], bb1[idx], bb2[idx] = tri, t[idx], b1[idx], b2[idx]
    return best, tbest, bb1, bb2


def render(scene: Scene, camera: Camera, settings: Settings) -> Image:
    W, H, S = settings.width, settings.height, settings.samples
    cam = camera.frame(W, H).astype(np.float64)
    eye, fwd, right, up = cam[0:3], cam[3:6], cam[6:9], cam[9:12]
    py, px, sy, sx = np.meshgrid(np.arange(H), np.arange(W), np.arange(S), np.arange(S), indexing="ij")
    py, px, sy, sx = (a.ravel() for a in (py, px, sy, sx))
    x = 2.0 * ((px + (sx + 0.5) / S) / W) - 1.0
    y = 1.0 - 2.0 * ((py + (sy + 0.5) / S) / H)
    if camera.orthographic:
        o = eye + x[:, None] * right + y[:, None] * up
        d = np.broadcast_to(fwd, o.shape).copy()
    else:
        d = fwd + x[:, None] * right + y[:, None] * up
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(eye, d.shape).copy()
    tri, t, b1, b2 = trace(scene, o, d, 0.0, settings.max_depth_m, settings.alpha_threshold)
    hit = tri >= 0
    n_s = len(tri)
    col = np.zeros((n_s, 3))
    nrm = np.zeros((n_s, 3))
    ao = np.zeros(n_s)
    if hit.any():
        h = np.nonzero(hit)[0]
        th, hb1, hb2 = tri[h], b1[h], b2[h]
        col[h] = scene.tint[th] * _texel(scene, th, hb1, hb2)[:, :3]
        P = scene.positions.astype(np.float64)[scene.triangles[th]]
        N = scene.normals.astype(np.float64)[scene.triangles[th]]
        ng = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        ng /= np.linalg.norm(ng, axis=1, keepdims=True)
        ns = (1 - hb1 - hb2)[:, None] * N[:, 0] + hb1[:, None] * N[:, 1] + hb2[:, None] * N[:, 2]
        ln = np.linalg.norm(ns, axis=1, keepdims=True)
        ns = np.where(ln > 1e-12, ns / np.maximum(ln, 1e-300), ng)
        back = np.einsum("ij,ij->i", ng, d[h]) > 0
        ng[back], ns[back] = -ng[back], -ns[back]
        nrm[h] = ns
        if settings.ao_rays > 0:
            R = settings.ao_rays
            hitp = o[h] + t[h, None] * d[h] + 1e-4 * ng
            sgn = np.where(ns[:, 2] >= 0, 1.0, -1.0)
            a = -1.0 / (sgn + ns[:, 2])
            bb = ns[:, 0] * ns[:, 1] * a
            t1v = np.stack([1 + sgn * ns[:, 0] ** 2 * a, sgn * bb, -sgn * ns[:, 0]], 1)
            t2v = np.stack([bb, sgn + ns[:, 1] ** 2 * a, -ns[:, 1]], 1)
            pixel = (py[h] * W + px[h]).astype(np.uint32)
            sub = (sy[h] * S + sx[h]).astype(np.uint64)
            k = np.arange(R, dtype=np.uint64)
            stream = ((sub[:, None] * R + k[None, :]) * 2).astype(np.uint32)
            u1 = unit_random(settings.seed, np.repeat(pixel, R), stream.ravel())
            u2 = unit_random(settings.seed, np.repeat(pixel, R), stream.ravel() + np.uint32(1))
            r, phi = np.sqrt(u1), 2 * np.pi * u2
            T1, T2, NS = (np.repeat(v, R, axis=0) for v in (t1v, t2v, ns))
            dirs = (r * np.cos(phi))[:, None] * T1 + (r * np.sin(phi))[:, None] * T2 + np.sqrt(np.maximum(0, 1 - u1))[:, None] * NS
            occ, _, _, _ = trace(scene, np.repeat(hitp, R, axis=0), dirs, 0.0, settings.ao_radius_m, settings.alpha_threshold)
            ao[h] = (occ < 0).reshape(-1, R).mean(1)
    per = S * S
    cov = hit.reshape(H, W, per)
    n_cov = cov.sum(2)
    albedo = col.reshape(H, W, per, 3).sum(2) / per
    alpha = n_cov / per
    normal = nrm.reshape(H, W, per, 3).sum(2) / np.maximum(n_cov, 1)[..., None]
    depth = np.where(hit, t, np.inf).reshape(H, W, per).min(2)
    ao_img = np.where(n_cov > 0, ao.reshape(H, W, per).sum(2) / np.maximum(n_cov, 1), 1.0) if settings.ao_rays else np.ones((H, W))
    f = np.float32
    return Image(albedo.astype(f), alpha.astype(f), normal.astype(f), depth.astype(f), ao_img.astype(f))
