"""Foliage cards (seed 002's hierarchical simplification): per species a
high-detail cluster (a shoot of needle bundles, a spray of leaves, a stem
with leaves and a flower head) is built from the species' own leaf model,
rendered once with worldlib.render looking down the card's normal, and the
tree's foliage becomes alpha-tested cards carrying that picture.

The cluster lives in the leaf frame of leaves.py: x along L (across), y
along H (from the attachment point outward), z along U (the card's normal),
metres. The card is the cluster's bounding rectangle in x-y; its square texture
(size x size texels, stretched to the rectangle) is
    albedo RGB  linear, straight alpha, AO of the cluster baked in (the
                shadow leaves cast on each other inside a shoot);
    alpha       the covered share of 4 x 4 samples per texel;
    normal      tangent space (x = u, y = v, z = card normal), encoded 0.5 n + 0.5;
    thickness   metres of foliage along the card normal at each texel: from
                the first leaf seen from the front to the last one (a second
                render from the back), plus one leaf's own thickness; 0 where
                empty (EXR data, for a renderer's subsurface / thickness input);
    translucency the share of light the foliage passes at each texel (EXR
                data, 0..1): a single leaf's transmittance (LEAF_TRANSMITTANCE,
                by leaf shape) attenuated by exp(-thickness / TRANSLUCENT_DEPTH
                of the cluster's depth), 0 where empty.
A crossed card (a second quad through the cluster's axis, in the y-z plane)
makes the cluster read from the side too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worldlib.render import Camera, Scene, Settings, render

from . import leaves, textures


# Transmittance of one leaf (the share of light it lets through, diffusely):
# broad leaves pass about a third of the visible light, needles far less, as
# they are thick; grass blades and petals are thin.
LEAF_TRANSMITTANCE = {"ellipse": 0.35, "card": 0.35, "needles": 0.12, "blade": 0.4}
LEAF_THICKNESS_M = {"ellipse": 3e-4, "card": 3e-4, "needles": 1e-3, "blade": 3e-4}
TRANSLUCENT_DEPTH = 0.25  # light through the card falls by 1/e over this share of the cluster's depth


@dataclass
class CardBake:
    albedo: np.ndarray  # (n, n, 3) linear, colour dilated into transparent texels
    alpha: np.ndarray  # (n, n)
    normal: np.ndarray  # (n, n, 3) tangent space, unit vectors
    coverage: float  # share of the card's texels with alpha >= 0.5 (its leaf area per card area)
    template: leaves.Template  # the card(s) in the leaf frame, uv over the texture
    cluster_triangles: int
    leaf_texture: np.ndarray | None  # the leaf blade texture the cluster was rendered with
    thickness: np.ndarray | None = None  # (n, n) metres of foliage along the card normal, 0 where empty
    translucency: np.ndarray | None = None  # (n, n) share of light passed, 0..1, 0 where empty


def _frame(h: np.ndarray, toward: np.ndarray):
    """Leaf axes (L, H, U) with H = h and U as close to `toward` as H allows."""
    h = h / np.linalg.norm(h)
    u = toward - np.dot(toward, h) * h
    if np.linalg.norm(u) < 1e-6:
        u = np.array([1.0, 0.0, 0.0]) - h[0] * h
    u /= np.linalg.norm(u)
    return np.cross(h, u), h, u


def _place(tmpl: leaves.Template, origin, L, H, U, scale: float):
    r = tmpl.rows.astype(np.float64)
    p = origin + scale * (r[:, 0:1] * L + r[:, 1:2] * H + r[:, 2:3] * U)
    n = r[:, 3:4] * L + r[:, 4:5] * H + r[:, 5:6] * U
    return p, n, r[:, 6:8], r[:, 8], tmpl.tris


def cluster_scene(spec, seed: int, leaf_tex: np.ndarray | None) -> Scene:
    """The high-detail cluster of a species, as a render scene: a thin stem
    along +y with `leaves_per_card` leaves of the species' template placed
    along it (divergence angle about the stem, leaf_angle from it), an
    optional flower head at the tip. Colours vary per leaf between
    leaf_color and leaf_tip_color (seeded)."""
    f, leaf = spec.foliage, spec.leaf
    rng = np.random.default_rng(seed)
    if leaf.shape == "ellipse":  # the cluster is rendered once: its leaves can afford a smooth outline
        leaf = leaf.model_copy(update={"segments": max(leaf.segments, 10)})
    tmpl = leaves.make_template(leaf)
    P, N, UV, T, tint, tex = [], [], [], [], [], []
    n0 = 0

    def add(p, n, uv, tris, colour, texture):
        nonlocal n0
        P.append(p)
        N.append(n)
        UV.append(uv)
        T.append(np.asarray(tris) + n0)
        tint.append(np.broadcast_to(np.asarray(colour, np.float64), (len(tris), 3)))
        tex.append(np.full(len(tris), texture))
        n0 += len(p)

    stem_len = f.stem_length
    # stem: a thin strip toward the viewer, and one across, so it shows at any card angle
    w = f.stem_width
    for axis in (np.array([1.0, 0, 0]), np.array([0, 0, 1.0])):
        p = np.array([-w / 2 * axis, w / 2 * axis, w / 2 * axis * 0.4 + [0, stem_len, 0], -w / 2 * axis * 0.4 + [0, stem_len, 0]])
        add(p, np.tile(np.cross(axis, [0, 1.0, 0]), (4, 1)), np.zeros((4, 2)), [[0, 1, 2], [0, 2, 3]], spec.bark_color, -1)
    base, tip = np.asarray(spec.leaf_color), np.asarray(spec.leaf_tip_color)
    textured = leaf.shape in ("ellipse", "card") and leaf_tex is not None
    n_leaves = f.leaves_per_card if tmpl is not None else 0
    for i in range(n_leaves):
        t = (i + 0.5) / n_leaves if n_leaves > 1 else 0.9
        along = f.leaf_start + (1.0 - f.leaf_start) * t
        phi = math.radians(f.divergence) * i + math.radians(10.0) * rng.standard_normal()
        tilt = math.radians(f.leaf_angle + 8.0 * rng.standard_normal())
        h = np.array([math.sin(tilt) * math.cos(phi), math.cos(tilt), math.sin(tilt) * math.sin(phi)])
        # leaves turn their faces to the light: toward +z (the card's normal), a bit up
        L, H, U = _frame(h, np.array([0.0, 0.3, 1.0]))
        scale = (1.0 + leaf.size_jitter * (2 * rng.random() - 1)) * (1.0 - f.taper * t)
        p, n, uv, fl, tris = _place(tmpl, np.array([0.0, along * stem_len, 0.0]), L, H, U, scale)
        mix = rng.random()
        bright = 1.0 + 0.25 * (2 * rng.random() - 1)
        col_leaf = (1 - mix) * base + mix * tip
        tri_fl = fl[tris].mean(1)
        cols = bright * ((1 - tri_fl)[:, None] * col_leaf + tri_fl[:, None] * (0.6 * col_leaf + 0.4 * tip))
        P.append(p), N.append(n), UV.append(uv), T.append(tris + n0), tint.append(np.clip(cols, 0, 1))
        tex.append(np.full(len(tris), 0 if textured else -1))
        n0 += len(p)
    if tmpl is not None and leaf.shape == "needles":  # the shoot's tip bundle
        L, H, U = _frame(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))
        p, n, uv, fl, tris = _place(tmpl, np.array([0.0, stem_len, 0.0]), L, H, U, 1.0)
        add(p, n, uv, tris, tip, -1)
    if f.flower_petals > 0:
        centre = np.array([0.0, stem_len + 0.3 * f.flower_petal_length, 0.02 * stem_len])
        petal = leaves.make_template(leaf.model_copy(update={"shape": "ellipse", "length": f.flower_petal_length,
                                                            "width": 0.4 * f.flower_petal_length, "petiole": 0.0,
                                                            "fold": 10.0, "segments": 4}))
        for k in range(f.flower_petals):
            a = 2 * math.pi * (k + 0.5 * rng.random()) / f.flower_petals
            h = np.array([math.cos(a), math.sin(a), 0.25])
            L, H, U = _frame(h, np.array([0.0, 0.0, 1.0]))
            p, n, uv, fl, tris = _place(petal, centre, L, H, U, 1.0 + 0.15 * (2 * rng.random() - 1))
            col = np.asarray(f.flower_color) * (0.85 + 0.3 * rng.random())
            add(p, n, uv, tris, np.clip(col, 0, 1), -1)
        k = 12
        ang = 2 * np.pi * np.arange(k) / k
        r = 0.28 * f.flower_petal_length
        disc = np.concatenate([[centre + [0, 0, 0.3 * r]], centre + np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros(k)], 1)])
        tris = [[0, 1 + j, 1 + (j + 1) % k] for j in range(k)]
        add(disc, np.tile([0, 0, 1.0], (k + 1, 1)), np.zeros((k + 1, 2)), tris, f.flower_center_color, -1)
    textures_stack = (np.concatenate([leaf_tex, np.ones(leaf_tex.shape[:2] + (1,), np.float32)], -1)[None]
                      if leaf_tex is not None else np.ones((1, 1, 1, 4), np.float32))
    return Scene(np.concatenate(P), np.concatenate(N), np.concatenate(UV), np.concatenate(T), np.concatenate(tint),
                 np.concatenate(tex), textures_stack)


def bake(env, spec, seed: int, size: int = 256) -> CardBake:
    """Render the species' cluster into its card texture (on the OpenCL
    device `env`) and make the card template."""
    from pipeline.opencl import require

    require(env, "plants: the card bake")  # its renders are the device's (None would be the numpy reference's)
    f = spec.foliage
    leaf_tex = None
    if spec.leaf.shape in ("ellipse", "card"):
        leaf_tex = textures.leaf_texture(size, spec.leaf_color, spec.leaf_tip_color, seed)
    scene = cluster_scene(spec, seed, leaf_tex)
    p = scene.positions
    lo, hi = p[:, :2].min(0), p[:, :2].max(0)
    centre = 0.5 * (lo + hi)
    span = (hi - lo) * 1.04
    zmax = float(p[:, 2].max()) + 1.0
    # the card is the cluster's bounding rectangle; its square texture stretches to fit
    cam = Camera((float(centre[0]), float(centre[1]), zmax), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0),
                 ortho_height_m=float(span[1]), ortho_width_m=float(span[0]))
    img = render(env, scene, cam, Settings(size, size, samples=4, ao_rays=4, ao_radius_m=0.15 * float(span.max()),
                                           seed=seed & 0xFFFFFFFF))
    alpha = img.alpha
    thickness, translucency = _thickness(env, scene, spec.leaf.shape, img, centre, span, float(p[:, 2].min()) - 1.0, zmax,
                                         size, seed)
    straight = img.albedo / np.maximum(alpha, 1e-6)[..., None]
    straight *= (0.55 + 0.45 * img.ao)[..., None]  # the cluster's self-shadowing, baked in
    albedo = textures.dilate_colour(np.clip(straight, 0, 1), alpha)
    n = img.normal / np.maximum(np.linalg.norm(img.normal, axis=-1, keepdims=True), 1e-6)
    n[alpha <= 0] = (0.0, 0.0, 1.0)
    n[n[..., 2] < 0] *= -1.0  # the card's back face uses the mirrored normal
    coverage = float((alpha >= 0.5).mean())
    # the card(s): square around the cluster, uv over the whole texture
    x0, y0 = centre - span / 2
    x1, y1 = centre + span / 2
    quad = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    pos, uvs, tris = [quad], [uv], [[0, 1, 2], [0, 2, 3]]
    if f.crossed:
        cross = quad[:, [2, 1, 0]].copy()  # the same square turned into the y-z plane
        pos.append(cross)
        uvs.append(uv)
        tris += [[4, 5, 6], [4, 6, 7]]
    pos = np.concatenate(pos)
    tmpl = leaves.finish_template(pos, np.concatenate(uvs), np.clip((pos[:, 1] - max(y0, 0.0)) / max(y1 - max(y0, 0.0), 1e-9), 0, 1),
                         tris)
    return CardBake(albedo.astype(np.float32), alpha.astype(np.float32), n.astype(np.float32), coverage, tmpl,
                    scene.n_triangles, leaf_tex, thickness, translucency)


def _thickness(env, scene: Scene, shape: str, front, centre, span, zmin: float, zmax: float, size: int, seed: int):
    """Thickness (m) and translucency (0..1) per texel: the cluster seen
    from the back too; thickness is the distance from the first surface
    seen from the front to the first seen from the back (the whole depth of
    foliage along the card normal) plus one leaf's thickness."""
    cam = Camera((float(centre[0]), float(centre[1]), zmin), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0),
                 ortho_height_m=float(span[1]), ortho_width_m=float(span[0]))
    back = render(env, scene, cam, Settings(size, size, samples=4, ao_rays=0, seed=seed & 0xFFFFFFFF))
    back_depth = back.depth[:, ::-1]  # seen from behind, the image's x runs the other way
    hit = np.isfinite(front.depth) & np.isfinite(back_depth) & (front.alpha > 0)
    depth = (zmax - zmin) - np.where(hit, front.depth, 0.0) - np.where(hit, back_depth, 0.0)
    thickness = np.where(hit, np.maximum(depth, 0.0) + LEAF_THICKNESS_M.get(shape, 3e-4), 0.0)
    scale = TRANSLUCENT_DEPTH * max(float(thickness.max()), 1e-6)
    translucency = np.where(hit, LEAF_TRANSMITTANCE.get(shape, 0.3) * np.exp(-thickness / scale), 0.0)
    return thickness.astype(np.float32), translucency.astype(np.float32)


@dataclass
class SliceBake:
    """The atlas of seed 001's slice tuft: a 4:1 strip, one quarter per
    vertical quad of grass.slice_cards (u in [i/4, (i+1)/4]), each the whole
    tuft seen orthographically through that quad. The horizontal quad's uv
    (v in [1, 2]) falls past the strip's top, where the clamped texture is
    transparent: seen from above the tuft is its vertical quads."""

    albedo: np.ndarray  # (n, 4n, 3) linear, straight alpha, dilated
    alpha: np.ndarray  # (n, 4n)
    normal: np.ndarray  # (n, 4n, 3) tangent space of each quad


def bake_grass_slices(env, blades_scene: Scene, slice_part, size: int = 128, seed: int = 0) -> SliceBake:
    """Render the tuft (blades_scene) through each vertical quad of the
    slice tuft, on the OpenCL device `env`."""
    from pipeline.opencl import require

    require(env, "plants: the grass slice bake")  # its renders are the device's
    albedo, alpha, normal = [], [], []
    v = slice_part.verts
    for i in range(4):
        q = v[4 * i: 4 * i + 4, 0:3].astype(np.float64)
        right, up = q[1] - q[0], q[3] - q[0]
        w, h = float(np.linalg.norm(right)), float(np.linalg.norm(up))
        right, up = right / w, up / h
        forward = np.cross(up, right)  # the camera's right is then the quad's u direction
        centre = q.mean(0)
        cam = Camera(tuple(centre - forward * (10.0 * max(w, h))), tuple(forward), tuple(up), ortho_height_m=h, ortho_width_m=w)
        img = render(env, blades_scene, cam, Settings(size, size, samples=4, ao_rays=4, ao_radius_m=0.1 * h, seed=seed + i))
        a = img.alpha
        rgb = img.albedo / np.maximum(a, 1e-6)[..., None] * (0.6 + 0.4 * img.ao)[..., None]
        # world normal to the quad's tangent frame (x = u, y = v, z = toward the viewer)
        n = img.normal @ np.stack([right, up, -forward], 1)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        n[a <= 0] = (0.0, 0.0, 1.0)
        n[n[..., 2] < 0] *= -1.0
        albedo.append(np.clip(rgb, 0, 1))
        alpha.append(a)
        normal.append(n)
    a = np.concatenate(alpha, 1)
    rgb = textures.dilate_colour(np.concatenate(albedo, 1), a)
    return SliceBake(rgb.astype(np.float32), a.astype(np.float32), np.concatenate(normal, 1).astype(np.float32))
