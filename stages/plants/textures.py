"""Procedural textures of the plants: bark (tileable in both directions,
so it repeats around and along the branches), leaf blades and grass blades
(not tiled: they map once onto a leaf), and the writing of every texture
as a linear EXR (the data) with an 8-bit sRGB PNG copy of colour textures
(what DCC tools and UsdPreviewSurface readers expect for diffuse colour).

Tileable noise is band-limited white noise filtered in the Fourier domain:
a periodic grid's FFT filter is periodic by construction, so the left and
right (top and bottom) edges meet without a seam.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def periodic_noise(size: int, rng: np.random.Generator, scale_u: float, scale_v: float, slope: float = 2.0) -> np.ndarray:
    """(size, size) zero-mean, unit-variance periodic noise with a power-law
    spectrum ~ 1 / f^slope, stretched: frequencies along u are divided by
    scale_u and along v by scale_v (scale_v > scale_u makes streaks along v)."""
    white = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size)[:, None] * size / scale_v
    fx = np.fft.fftfreq(size)[None, :] * size / scale_u
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-0.5 * slope)
    amp[0, 0] = 0.0
    n = np.real(np.fft.ifft2(np.fft.fft2(white) * amp))
    return (n - n.mean()) / max(n.std(), 1e-12)


def normal_from_height(height: np.ndarray, strength: float) -> np.ndarray:
    """Tangent-space normals (x along u, y along v = up the image, z out) of
    a periodic height field, central differences wrapping around the edges."""
    dx = 0.5 * (np.roll(height, -1, 1) - np.roll(height, 1, 1))
    dy = 0.5 * (np.roll(height, 1, 0) - np.roll(height, -1, 0))  # rows run top to bottom, v up
    n = np.stack([-strength * dx, -strength * dy, np.ones_like(height)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def bark_texture(size: int, colour, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Bark as (albedo RGB linear, tangent-space normal), both (size, size, 3),
    tileable: vertical furrows (noise long along v), plates between them and
    lichen-grey speckle. u runs around the branch, v along it."""
    rng = np.random.default_rng(seed)
    furrows = periodic_noise(size, rng, 1.0, 8.0, 2.2)
    plates = periodic_noise(size, rng, 2.0, 3.0, 2.0)
    fine = periodic_noise(size, rng, 0.5, 0.7, 1.2)
    ridge = 1.0 - np.abs(np.tanh(0.9 * furrows))  # sharp bottoms where the furrow noise crosses zero
    height = 0.6 * ridge + 0.25 * np.tanh(plates) + 0.08 * fine
    h01 = (height - height.min()) / max(np.ptp(height), 1e-12)
    base = np.asarray(colour, np.float64)
    shade = 0.45 + 0.8 * h01  # furrow bottoms dark, plate tops lit
    tint = 1.0 + 0.12 * np.tanh(periodic_noise(size, rng, 6.0, 6.0, 2.0))[..., None] * np.array([1.0, 0.9, 0.6])
    lichen = np.clip(periodic_noise(size, rng, 1.5, 1.5, 1.5) - 1.6, 0, 1)[..., None]
    albedo = base * shade[..., None] * tint
    albedo = albedo * (1 - lichen) + lichen * np.array([0.33, 0.35, 0.3])
    return np.clip(albedo, 0, 1).astype(np.float32), normal_from_height(height * 6.0, 1.0).astype(np.float32)


def leaf_texture(size: int, base, tip, seed: int) -> np.ndarray:
    """A leaf blade's albedo (size, size, 3) linear over uv (u across, v from
    stalk to tip): colour from base to tip, a pale midrib and lateral veins
    running out and forward, faint mottling."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[size - 1:-1:-1, 0:size].astype(np.float64) / (size - 1)
    x = u - 0.5
    col = (1 - v)[..., None] * np.asarray(base) + v[..., None] * np.asarray(tip)
    midrib = np.exp(-(x / 0.018) ** 2)
    phase = (v - 1.6 * np.abs(x)) * 9.0  # veins leave the midrib toward the tip
    veins = np.exp(-((phase - np.round(phase)) / 0.08) ** 2) * (np.abs(x) > 0.02)
    mottle = 0.06 * periodic_noise(size, rng, 4.0, 4.0, 2.0)
    light = 1.0 + 0.35 * midrib + 0.18 * veins + mottle
    edge = 1.0 - 0.25 * np.clip(np.abs(x) * 2.0, 0, 1) ** 4
    return np.clip(col * (light * edge)[..., None], 0, 1).astype(np.float32)


def dilate_colour(rgb: np.ndarray, alpha: np.ndarray, passes: int = 8) -> np.ndarray:
    """Spread the colour of covered texels into the uncovered ones next to
    them (edge padding), so filtering and mipmaps of an alpha-tested card do
    not bleed the background's colour into its edges."""
    rgb = rgb.copy()
    have = alpha > 0
    for _ in range(passes):
        if have.all():
            break
        acc = np.zeros_like(rgb)
        cnt = np.zeros(alpha.shape)
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            h = np.roll(have, (dy, dx), (0, 1))
            acc += np.roll(rgb, (dy, dx), (0, 1)) * h[..., None]
            cnt += h
        grow = ~have & (cnt > 0)
        rgb[grow] = acc[grow] / cnt[grow, None]
        have = have | grow
    rgb[~have] = rgb[have].mean(0) if have.any() else 0.0
    return rgb


def write_exr(path: Path, pixels: np.ndarray, channels: tuple[str, ...], provenance: dict | None = None) -> None:
    """A linear half-float EXR texture (zip, tiled, mip-mapped by make_texture)."""
    import OpenImageIO as oiio

    data = np.ascontiguousarray(pixels, np.float32)
    if not np.isfinite(data).all():
        raise ValueError(f"texture {path.name} holds NaN or Inf")
    src = oiio.ImageBuf(data)
    spec = src.spec()
    spec.channelnames = channels
    if "A" in channels:
        spec.alpha_channel = channels.index("A")
    config = oiio.ImageSpec()
    config.attribute("compression", "zip")
    config.attribute("DateTime", "")
    config.attribute("oiio:ColorSpace", "Linear")
    for k, v in (provenance or {}).items():
        config.attribute(f"worldbake:{k}", v if isinstance(v, str) else json.dumps(v, sort_keys=True))
    config.set_format(oiio.HALF)
    if not oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, src, str(path), config):
        raise OSError(f"cannot write texture {path}: {oiio.geterror()}")


def blade_texture(size: int, base, tip, seed: int) -> np.ndarray:
    """A grass blade's albedo (size, size, 3) linear over uv (u across, v
    root to tip): colour from base to tip, parallel veins along the blade,
    a slightly paler keel and a dry tip."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[size - 1:-1:-1, 0:size].astype(np.float64) / (size - 1)
    col = (1 - v)[..., None] * np.asarray(base) + v[..., None] * np.asarray(tip)
    veins = 0.5 + 0.5 * np.cos(2 * np.pi * 7 * u)
    streak = periodic_noise(size, rng, 0.5, 16.0, 1.5)
    light = 0.88 + 0.14 * veins + 0.05 * streak + 0.15 * np.exp(-((u - 0.5) / 0.05) ** 2)
    dry = np.clip((v - 0.9) / 0.1, 0, 1)[..., None] * 0.5
    albedo = col * light[..., None]
    albedo = albedo * (1 - dry) + dry * np.array([0.35, 0.3, 0.12])
    return np.clip(albedo, 0, 1).astype(np.float32)
