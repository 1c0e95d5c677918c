"""worldlib.images: the texture files materials read."""
from __future__ import annotations

import numpy as np

from pipeline.exr import srgb8
from worldlib import images


def _stored(path) -> np.ndarray:
    """The PNG's bytes as stored (straight), not as OpenImageIO presents them (premultiplied)."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    return np.asarray(oiio.ImageBuf(str(path), 0, 0, config).get_pixels(oiio.UINT8))


def test_png_colour_is_srgb_data_is_raw(tmp_path):
    a = np.linspace(0, 1, 48, dtype=np.float32).reshape(4, 4, 3)
    images.write_png(tmp_path / "a.png", a, srgb=True)
    images.write_png(tmp_path / "n.png", a, srgb=False)
    np.testing.assert_array_equal(_stored(tmp_path / "a.png"), srgb8(a))
    np.testing.assert_array_equal(_stored(tmp_path / "n.png"), np.round(a * 255).astype(np.uint8))


def test_png_alpha_is_straight_as_png_defines_it(tmp_path):
    """A half-covered texel keeps its colour in the file (OpenImageIO would
    store colour / alpha unless told the pixels are unassociated), so Blender
    and every other PNG reader see the albedo we wrote."""
    rgb = np.full((4, 4, 3), 0.2, np.float32)
    alpha = np.linspace(0.1, 1.0, 16, dtype=np.float32).reshape(4, 4)
    images.write_png(tmp_path / "c.png", rgb, alpha)
    got = _stored(tmp_path / "c.png")
    np.testing.assert_array_equal(got[..., :3], srgb8(rgb))
    np.testing.assert_array_equal(got[..., 3], np.round(alpha * 255).astype(np.uint8))


def test_png_bytes_do_not_change_between_writes(tmp_path):
    rgb = np.random.default_rng(1).random((8, 8, 3), np.float32)
    images.write_png(tmp_path / "a.png", rgb, rgb[..., 0])
    images.write_png(tmp_path / "b.png", rgb, rgb[..., 0])
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
