"""DEM import: formats, resampling, and clear errors for bad files."""
import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline.errors import InputError
from worldlib.terrain import dem
from stages.heightmap.stage import HeightmapParams, heights


def write(path, data, fmt):
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], 1, fmt)
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(np.ascontiguousarray(data[:, :, None])), out.geterror()
    out.close()


def ramp(n=40, a=150.0, bx=3.0, bz=-2.0):
    """h = a + bx * col + bz * row at source pixel centres."""
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    return a + bx * c + bz * r


def expected_ramp(n_src, res, a=150.0, bx=3.0, bz=-2.0):
    """The ramp at target cell centres, in source pixel coordinates (clamped
    at the borders as the resampler does)."""
    s = np.clip((np.arange(res) + 0.5) * n_src / res - 0.5, 0, n_src - 1)
    return a + bx * s[None, :] + bz * s[:, None]


def dem_params(path, res, **kw):
    return HeightmapParams(generator="dem", dem_path=str(path), resolution=res, size_m=1000.0, **kw)


@pytest.mark.parametrize("res", [100, 23])  # up- and downsampling
@pytest.mark.parametrize("ext,fmt", [("exr", "float"), ("tif", "float"), ("exr", "half")])
def test_float_dem_ramp_stays_a_ramp(cl_env, tmp_path, ext, fmt, res):
    src = ramp()
    path = tmp_path / f"dem.{ext}"
    write(path, src.astype(np.float32), fmt)
    h, _ = heights(cl_env, dem_params(path, res), seed=0)
    assert h.dtype == np.float32 and h.shape == (res, res)
    tol = 0.13 if fmt == "half" else 1e-3  # half: 11-bit mantissa at values up to 270 m
    np.testing.assert_allclose(h, expected_ramp(40, res), atol=tol)


def test_16bit_png_maps_to_metres(cl_env, tmp_path):
    n = 40
    src = ramp(n)  # values 72 .. 267 m
    lo, hi = 0.0, 500.0
    path = tmp_path / "dem.png"
    write(path, ((src - lo) / (hi - lo)).astype(np.float32), "uint16")  # OIIO quantises to 0..65535
    h, _ = heights(cl_env, dem_params(path, 64, dem_min_m=lo, dem_max_m=hi), seed=0)
    np.testing.assert_allclose(h, expected_ramp(n, 64), atol=(hi - lo) / 65535)


def test_16bit_tiff_and_normalised_float(cl_env, tmp_path):
    src = ramp(32)
    t = (src - 0.0) / 400.0
    write(tmp_path / "a.tif", t.astype(np.float32), "uint16")
    write(tmp_path / "b.exr", t.astype(np.float32), "float")
    a, _ = heights(cl_env, dem_params(tmp_path / "a.tif", 50, dem_min_m=0.0, dem_max_m=400.0), seed=0)
    b, _ = heights(cl_env, dem_params(tmp_path / "b.exr", 50, dem_min_m=0.0, dem_max_m=400.0), seed=0)
    want = expected_ramp(32, 50)
    np.testing.assert_allclose(a, want, atol=400.0 / 65535)
    np.testing.assert_allclose(b, want, atol=1e-3)


def test_identity_resolution_returns_the_pixels(cl_env, tmp_path):
    src = np.random.default_rng(0).normal(500.0, 100.0, (37, 37)).astype(np.float32)
    write(tmp_path / "d.exr", src, "float")
    h, _ = heights(cl_env, dem_params(tmp_path / "d.exr", 37), seed=0)
    np.testing.assert_array_equal(h, src)


def test_dem_window_equals_crop(cl_env, tmp_path):
    src = np.random.default_rng(1).normal(500.0, 100.0, (50, 50)).astype(np.float32)
    write(tmp_path / "d.exr", src, "float")
    whole, _ = heights(cl_env, dem_params(tmp_path / "d.exr", 300), seed=0)
    tile, _ = heights(cl_env, dem_params(tmp_path / "d.exr", 300, window=(17, 260, 283, 40)), seed=0)
    assert tile.tobytes() == np.ascontiguousarray(whole[260:300, 17:300]).tobytes()


def test_corrupt_file(cl_env, tmp_path):
    path = tmp_path / "corrupt.png"
    path.write_bytes(np.random.default_rng(2).bytes(4096))
    with pytest.raises(InputError, match="corrupt.png"):
        heights(cl_env, dem_params(path, 16), seed=0)


def test_truncated_png(cl_env, tmp_path):
    good = tmp_path / "good.png"
    write(good, np.random.default_rng(3).random((64, 64)).astype(np.float32), "uint16")
    bad = tmp_path / "truncated.png"
    bad.write_bytes(good.read_bytes()[:300])
    with pytest.raises(InputError, match="truncated.png"):
        heights(cl_env, dem_params(bad, 16, dem_min_m=0.0, dem_max_m=1.0), seed=0)


def test_missing_file(cl_env, tmp_path):
    with pytest.raises(InputError, match="missing_dem.exr"):
        heights(cl_env, dem_params(tmp_path / "missing_dem.exr", 16), seed=0)


def test_nan_in_exr(cl_env, tmp_path):
    src = ramp(20).astype(np.float32)
    src[3, 7] = np.nan
    path = tmp_path / "has_nan.exr"
    write(path, src, "float")
    with pytest.raises(InputError, match=r"has_nan.exr.*NaN.*row 3, column 7"):
        heights(cl_env, dem_params(path, 16), seed=0)


def test_inf_in_tiff(cl_env, tmp_path):
    src = ramp(20).astype(np.float32)
    src[0, 0] = np.inf
    path = tmp_path / "has_inf.tif"
    write(path, src, "float")
    with pytest.raises(InputError, match="has_inf.tif"):
        heights(cl_env, dem_params(path, 16), seed=0)


def test_integer_dem_needs_range(cl_env, tmp_path):
    path = tmp_path / "norange.png"
    write(path, np.zeros((8, 8), np.float32), "uint16")
    with pytest.raises(InputError, match="norange.png.*dem_min_m and dem_max_m"):
        heights(cl_env, dem_params(path, 16), seed=0)


def test_non_square_dem(cl_env, tmp_path):
    path = tmp_path / "wide.exr"
    write(path, np.zeros((8, 16), np.float32), "float")
    with pytest.raises(InputError, match="wide.exr.*16x8"):
        heights(cl_env, dem_params(path, 16), seed=0)


def test_text_file_with_image_extension(tmp_path):
    path = tmp_path / "notes.tif"
    path.write_text("this is not an image\n" * 20)
    with pytest.raises(InputError, match="notes.tif"):
        dem.read_dem(path)


def test_run_resolves_dem_path_against_project_root(cl_env, tmp_path):
    from pipeline.contract import RunContext
    from stages.heightmap import STAGE

    (tmp_path / "data").mkdir()
    write(tmp_path / "data" / "dem.exr", ramp(16).astype(np.float32), "float")
    ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path / "out", seed=0, provenance={}, project_root=tmp_path)
    p = HeightmapParams(generator="dem", dem_path="data/dem.exr", resolution=16, size_m=160.0)
    g = STAGE.run(ctx, {}, p)["heightmap.height"]
    np.testing.assert_allclose(g.data, ramp(16), atol=1e-3)
    assert "dem_seconds" in ctx.metrics


def _exr_with_cell_size(path, data, cell):
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], 1, "float")
    spec.attribute("worldbake:cell_size_m", float(cell))
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(np.ascontiguousarray(data[:, :, None].astype(np.float32))), out.geterror()
    out.close()


def test_dem_stating_its_cell_size_is_baked_at_its_own_cells(cl_env, tmp_path):
    """A 40 x 30 DEM with worldbake:cell_size_m: the world is its 30 rows x 40
    columns at that cell size, the heights its values; the config's
    dem_cell_size_m overrides the file's; resolution and size_m are unused."""
    from pipeline.contract import RunContext
    from stages.heightmap import STAGE

    src = np.add.outer(np.arange(30) * -2.0, np.arange(40) * 3.0) + 150.0
    path = tmp_path / "rect.exr"
    _exr_with_cell_size(path, src, 12.5)
    assert dem.dem_cell_size(path) == 12.5
    ctx = RunContext(cl=cl_env, stage=STAGE, key="k", out_dir=tmp_path / "out", seed=0, provenance={}, project_root=tmp_path)
    g = STAGE.run(ctx, {}, dem_params(path, 16))["heightmap.height"]
    assert g.shape == (30, 40) and g.cell_size_m == 12.5 and g.size_m == (500.0, 375.0)
    np.testing.assert_array_equal(g.data, src.astype(np.float32))
    g = STAGE.run(ctx, {}, dem_params(path, 16, dem_cell_size_m=4.0))["heightmap.height"]
    assert g.shape == (30, 40) and g.cell_size_m == 4.0
    window = STAGE.run(ctx, {}, dem_params(path, 64, window=[5, 4, 20, 10]))["heightmap.height"]
    np.testing.assert_array_equal(window.data, src[4:14, 5:25].astype(np.float32))
    assert window.origin_m == (5 * 12.5, 4 * 12.5)


def test_geotiff_pixel_scale_is_the_cell_size(cl_env, tmp_path):
    tifffile = pytest.importorskip("tifffile")
    src = np.random.default_rng(0).random((30, 40)).astype(np.float32) * 100
    for name, scale, big in (("geo.tif", (10.0, 10.0, 0.0), False), ("big.tif", (2.5, 2.5, 0.0), True)):
        tifffile.imwrite(tmp_path / name, src, bigtiff=big, extratags=[(33550, 12, 3, scale, False)])
        assert dem.dem_cell_size(tmp_path / name) == scale[0]
        h, info = heights(cl_env, dem_params(tmp_path / name, 16), seed=0)
        assert h.shape == (30, 40) and info["dem_cell_size_m"] == scale[0]
    tifffile.imwrite(tmp_path / "plain.tif", src)
    assert dem.dem_cell_size(tmp_path / "plain.tif") is None
    tifffile.imwrite(tmp_path / "skew.tif", src, extratags=[(33550, 12, 3, (10.0, 5.0, 0.0), False)])
    with pytest.raises(InputError, match="skew.tif.*not square"):
        dem.dem_cell_size(tmp_path / "skew.tif")


@pytest.mark.parametrize("tile", [0, 16], ids=["scanlines", "tiles"])
@pytest.mark.parametrize("ext", ["exr", "tif"])
def test_scan_reads_in_bands_and_finds_what_read_dem_finds(tmp_path, monkeypatch, tile, ext):
    monkeypatch.setattr(dem, "SCAN_BAND_PIXELS", 40 * 5)  # bands of 5 rows (tiled: one row of tiles)
    src = np.random.default_rng(1).normal(500.0, 50.0, (37, 40)).astype(np.float32)
    src[31, 7], src[2, 39] = -900.0, 2000.0
    src[23, 11] = src[30, 0] = np.nan
    path = tmp_path / f"d.{ext}"
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(40, 37, 1, "float")
    if tile:
        spec.tile_width = spec.tile_height = tile
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(np.ascontiguousarray(src[:, :, None])), out.geterror()
    out.close()
    scan = dem.scan_raster(path)
    assert scan.shape == (37, 40) and (scan.lo, scan.lo_at, scan.hi, scan.hi_at) == (-900.0, (31, 7), 2000.0, (2, 39))
    assert scan.nonfinite == 2 and scan.first_nonfinite == (23, 11)
    with pytest.raises(InputError, match=r"contains 2 NaN or infinite value\(s\), the first at row 23, column 11"):
        dem.check_dem(path)
    with pytest.raises(InputError, match=r"contains 2 NaN .* row 23, column 11"):
        dem.read_dem(path)


def test_heights_beyond_the_range_are_refused_by_the_run_too(cl_env, tmp_path):
    path = tmp_path / "nodata.exr"
    src = np.full((16, 16), 300.0, np.float32)
    src[4, 9] = -3.4e38
    write(path, src, "float")
    with pytest.raises(InputError, match=r"nodata.exr holds a height of -3.4e\+38 m \(row 4, column 9\)"):
        heights(cl_env, dem_params(path, 16), seed=0)
    with pytest.raises(InputError, match=r"holds a height of -3.4e\+38 m \(row 4, column 9\)"):
        dem.check_dem(path)
