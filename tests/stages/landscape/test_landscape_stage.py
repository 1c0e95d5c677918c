"""The landscape tiles: contract, shared borders (bitwise), the 16-bit round
trip over one global range, the sidecars' Unreal settings, weightmaps summing
to 255, refusals before any stage runs, non-square worlds and tiny tiles."""
import json
import re
import shutil

import numpy as np
import pydantic
import pytest

from pipeline import exr
from pipeline.config import load_config
from pipeline.contract import RunContext, Stage
from pipeline.errors import InputError
from pipeline.executors import bake_worlds
from pipeline.graph import build_graph
from pipeline.grid import Grid
from pipeline.registry import all_stages
from pipeline.store import Store
from stages.landscape import STAGE, LandscapeParams
from stages.landscape import files, tiling
from worldlib.ground import GROUND_TYPES, SPLAT_CHANNELS
from worldlib.terrain import GROUND_SOURCES

from ..test_sources import ROOT

TINY = dict(quads_per_section=7, sections_per_component=1, components_per_tile=2)  # 15-vertex tiles


def world(rows=40, cols=53, seed=0, dx=8.0):
    """A rough height field and normalised splat weights (a few cells with none)."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:rows, 0:cols]
    h = (400.0 + 3.0 * c - 2.0 * r + 50.0 * rng.standard_normal((rows, cols))).astype(np.float32)
    w = rng.random((rows, cols, len(GROUND_TYPES))) ** 3
    w /= w.sum(-1, keepdims=True)
    return Grid(h, dx, ("height",), (100.0, -50.0)), Grid(w.astype(np.float32), dx, SPLAT_CHANNELS, (100.0, -50.0))


def bake(tmp_path, ground, splat=None, **kw):
    ctx = RunContext(stage=STAGE, key="k", out_dir=tmp_path, seed=0, provenance={"stage": "landscape"},
                     project_root=tmp_path)
    inputs = {"ground": ground} if splat is None else {"ground": ground, "splat": splat}
    index = STAGE.run(ctx, inputs, LandscapeParams(**kw))["landscape.tiles"]
    return index, ctx.metrics


def tile_arrays(folder, index, what):
    """{(col, row): array} of every tile's height EXR, height PNG or a ground type's weightmap."""
    out = {}
    for t in index["tile_list"]:
        key = tuple(t["tile"])
        if what == "exr":
            out[key] = exr.read_grid(folder / t["height_exr"]).data
        elif what == "png":
            out[key] = files.read_png(folder / t["height_png"])[0]
        else:
            out[key] = files.read_png(folder / t["weightmaps"][what])[0]
    return out


def stitch(tiles, index):
    """The whole lattice from the tiles (a shared border is taken from either tile)."""
    n = index["tile_vertices"]
    stride = n - 1 if index["share_borders"] else n
    cols, rows = index["lattice_vertices"]
    first = next(iter(tiles.values()))
    out = np.zeros((rows, cols) + first.shape[2:], first.dtype)
    for (c, r), a in tiles.items():
        out[r * stride:r * stride + n, c * stride:c * stride + n] = a
    return out


def same_bits(a, b):
    return a.tobytes() == b.tobytes() and a.dtype == b.dtype


def unreal_coordinates(base):
    """Unreal's LandscapeImportHelper::ExtractCoordinates: the text after the
    last "_x" and the last "_y" (any case) must be numbers."""
    low = base.lower()
    x, y = low.rfind("_x"), low.rfind("_y")
    if x < 0 or y < 0 or x > y or not base[x + 2:y].isdigit() or not base[y + 2:].isdigit():
        return None
    return base[:x], int(base[x + 2:y]), int(base[y + 2:])


def test_contract():
    assert isinstance(STAGE, Stage) and STAGE.name == "landscape"
    assert STAGE.inputs[0].role == "ground" and STAGE.inputs[0].one_of == GROUND_SOURCES
    assert STAGE.inputs[1].one_of == ("vegetation.splat",) and STAGE.inputs[1].optional
    assert [a.name for a in STAGE.outputs] == ["landscape.tiles"]
    assert LandscapeParams().vertices == 1009 and LandscapeParams(**TINY).vertices == 15
    assert LandscapeParams(tile_vertices=2017).vertices == 2017
    assert LandscapeParams(quads_per_section=127, tile_vertices=8129).vertices == 8129


def test_every_declared_file_is_written_and_named_for_unreal(tmp_path):
    ground, splat = world()
    index, m = bake(tmp_path, ground, splat, **TINY)
    tx, ty = index["tiles"]
    assert (tx, ty) == (4, 3) and m["tiles"] == 12 and len(index["tile_list"]) == 12
    listed = set()
    for t in index["tile_list"]:
        listed |= {t["height_exr"], t["height_png"], t["sidecar"], *t["weightmaps"].values()}
        assert sorted(t["weightmaps"]) == sorted(GROUND_TYPES)
    written = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert written == listed
    # Unreal collects, recursively from the chosen PNG's folder, every file whose name before _x matches:
    # unreal/ holds only PNGs, and each set (heights, each ground type) has exactly one file per tile
    sets = {}
    for f in (tmp_path / files.UNREAL_DIR).rglob("*"):
        assert f.suffix == ".png"
        base, col, row = unreal_coordinates(f.stem)
        sets.setdefault(base, set()).add((col, row))
    assert set(sets) == {"landscape"} | {f"landscape_{g}" for g in GROUND_TYPES}
    assert all(v == {(c, r) for c in range(tx) for r in range(ty)} for v in sets.values())


def test_border_vertices_are_bitwise_equal_between_neighbours(tmp_path):
    ground, splat = world()
    index, _ = bake(tmp_path, ground, splat, **TINY)
    for what in ("exr", "png", "grass"):
        tiles = tile_arrays(tmp_path, index, what)
        pairs = 0
        for (c, r), a in tiles.items():
            if (c + 1, r) in tiles:
                right = tiles[(c + 1, r)]
                assert a.shape == right.shape == (15, 15)
                assert same_bits(a[:, -1], right[:, 0]), (what, c, r)
                pairs += 1
            if (c, r + 1) in tiles:
                assert same_bits(a[-1], tiles[(c, r + 1)][0]), (what, c, r)
                pairs += 1
        assert pairs == 3 * 3 + 4 * 2


def test_heights_are_the_world_cells_exactly_and_padded_by_edge_clamping(tmp_path):
    ground, _ = world()
    index, m = bake(tmp_path, ground, **TINY)
    lattice = stitch(tile_arrays(tmp_path, index, "exr"), index)
    rows, cols = ground.shape
    assert index["valid_vertices"] == [cols, rows] and lattice.shape == (43, 57)
    assert np.array_equal(lattice[:rows, :cols], ground.data)  # bitwise: no resampling at the world's cell
    assert np.array_equal(lattice[:rows, cols:], np.repeat(ground.data[:, -1:], 57 - cols, axis=1))
    assert np.array_equal(lattice[rows:, :cols], np.repeat(ground.data[-1:], 43 - rows, axis=0))
    assert 0 < m["padded_share"] < 0.2 and index["tile_list"][-1]["valid_vertices"] == [53 - 42, 40 - 28]
    g = exr.read_grid(tmp_path / index["tile_list"][1]["height_exr"])
    assert g.cell_size_m == 8.0 and g.origin_m == (100.0 + 14 * 8.0, -50.0)  # cell centres = vertices


def test_png_round_trip_within_half_a_step_over_one_global_range(tmp_path):
    ground, _ = world()
    index, m = bake(tmp_path, ground, **TINY)
    lo, hi = float(ground.data.min()), float(ground.data.max())
    assert (index["height_min_m"], index["height_max_m"], index["height_range_m"]) == (lo, hi, hi - lo)
    step = (hi - lo) / 65535
    exrs, pngs = tile_arrays(tmp_path, index, "exr"), tile_arrays(tmp_path, index, "png")
    for key, v in pngs.items():
        assert v.dtype == np.uint16
        err = np.abs(tiling.decode_heights(v, lo, hi - lo) - exrs[key])
        assert err.max() <= 0.5 * step * (1 + 1e-6) + 1e-9, key
    allv = np.concatenate([v.ravel() for v in pngs.values()])
    assert allv.min() == 0 and allv.max() == 65535  # one range for the world, not per tile
    assert m["quantisation_error_max_m"] <= 0.5 * step * (1 + 1e-6) + 1e-9
    for t in index["tile_list"]:  # every tile states the same range, in its PNG and its sidecar
        _, text = files.read_png(tmp_path / t["height_png"])
        assert float(text["worldbake:height_min_m"]) == lo and float(text["worldbake:height_range_m"]) == hi - lo
        side = json.loads((tmp_path / t["sidecar"]).read_text())
        assert (side["height_min_m"], side["height_max_m"]) == (lo, hi)


def test_sidecar_holds_unreal_import_settings(tmp_path):
    ground, _ = world()
    index, _ = bake(tmp_path, ground, **TINY)
    lo, span = index["height_min_m"], index["height_range_m"]
    for t in index["tile_list"]:
        side = json.loads((tmp_path / t["sidecar"]).read_text())
        u = side["unreal"]
        assert u["quads_per_section"] == 7 and u["sections_per_component"] == "1x1" and u["components"] == [2, 2]
        assert u["resolution"] == [15, 15] == side["vertices"]
        assert u["components"][0] * u["component_size_quads"] + 1 == 15
        c, r = side["tile"]
        assert u["location_cm"][:2] == pytest.approx([100 * (104.0 + 14 * 8 * c), 100 * (-46.0 + 14 * 8 * r)])
        assert u["scale_cm"][:2] == [800.0, 800.0]
        assert u["scale_cm"][2] == pytest.approx(span * 100 / 512, rel=3e-5)
        # Unreal's decode, Z + (v - 32768) Zscale / 128, is the sidecar's decode
        v = np.array([0, 1, 32768, 65535])
        unreal_cm = u["location_cm"][2] + (v - 32768) * u["scale_cm"][2] / 128
        np.testing.assert_allclose(unreal_cm, 100 * tiling.decode_heights(v, lo, span), rtol=1e-12, atol=1e-6)
        assert side["decode"] == index["decode"] and side["height_step_m"] == pytest.approx(span / 65535)


def test_weightmaps_sum_to_255_where_the_splat_sums_to_one(tmp_path):
    ground, splat = world()
    index, _ = bake(tmp_path, ground, splat, **TINY)
    maps = np.stack([stitch(tile_arrays(tmp_path, index, g), index) for g in GROUND_TYPES], -1).astype(np.int64)
    rows, cols = ground.shape
    assert (maps.sum(-1) == 255).all()
    err = np.abs(maps[:rows, :cols] / 255.0 - splat.data)
    assert err.max() <= 1.0 / 255 + 1e-6  # each weight within one 8-bit step of the splat at the cell


def test_quantise_weights_reference():
    w = np.array([[1 / 3, 1 / 3, 1 / 3, 0, 0, 0], [0, 0, 0, 0, 0, 0], [0.5, 0.5, 0, 0, 0, 0], [2, 1, 1, 0, 0, 0]])
    q = tiling.quantise_weights(w).astype(int)
    assert q.tolist() == [[85, 85, 85, 0, 0, 0], [0] * 6, [128, 127, 0, 0, 0, 0], [127, 64, 64, 0, 0, 0]]


def test_non_square_world_and_abutting_tiles(tmp_path):
    ground, splat = world(rows=23, cols=61, seed=3)
    for share in (True, False):
        out = tmp_path / str(share)
        out.mkdir()
        index, _ = bake(out, ground, splat, share_borders=share, **TINY)
        n = 15
        stride = n - 1 if share else n
        assert index["tiles"] == [-(-(61 - (n - stride)) // stride), -(-(23 - (n - stride)) // stride)]
        lattice = stitch(tile_arrays(out, index, "exr"), index)
        assert np.array_equal(lattice[:23, :61], ground.data)


def test_resample_fit_spans_the_world_and_is_exact_on_a_plane(tmp_path):
    r, c = np.mgrid[0:64, 0:64]
    plane = Grid((500.0 + 0.75 * c - 0.25 * r).astype(np.float32), 8.0)
    index, _ = bake(tmp_path, plane, fit="resample", **TINY)
    dl = index["cell_size_m"]
    assert dl == pytest.approx(63 * 8.0 / 70) and dl <= 8.0  # 5 tiles x 14 quads over 63 cells
    assert index["valid_vertices"] == index["lattice_vertices"] == [71, 71]
    lattice = stitch(tile_arrays(tmp_path, index, "exr"), index)
    j = np.arange(71) * dl / 8.0
    np.testing.assert_allclose(lattice, 500.0 + 0.75 * j[None, :] - 0.25 * j[:, None], atol=1e-4)


def test_tiny_tiles_stress_and_holes(tmp_path):
    ground, splat = world(rows=64, cols=64, seed=5)
    h = ground.data.copy()
    h[10:14, 20:30] = np.nan  # an imported DEM's hole
    holes = Grid(h, 8.0)
    index, m = bake(tmp_path, holes, splat, quads_per_section=7, sections_per_component=1, components_per_tile=1)
    assert index["tiles"] == [9, 9] and index["lattice_vertices"] == [64, 64] and m["padded_share"] == 0.0
    lattice = stitch(tile_arrays(tmp_path, index, "exr"), index)
    assert np.isfinite(lattice).all() and m["nodata_cells"] == 40
    assert (lattice[10:14, 20:30] == np.nanmin(h)).all()
    ok = np.isfinite(h)
    assert np.array_equal(lattice[ok], h[ok])
    pngs = tile_arrays(tmp_path, index, "png")
    assert all(np.array_equal(a[:, -1], pngs[(c + 1, r)][:, 0]) for (c, r), a in pngs.items() if (c + 1, r) in pngs)


def test_flat_world_gets_a_one_metre_range(tmp_path):
    index, m = bake(tmp_path, Grid(np.full((20, 20), 42.0, np.float32), 8.0), **TINY)
    assert index["height_range_m"] == 1.0 and m["quantisation_error_max_m"] == 0.0


@pytest.mark.parametrize("bad", [
    dict(tile_vertices=1000), dict(quads_per_section=64), dict(sections_per_component=3), dict(prefix="my tiles"),
    dict(prefix="-tiles"), dict(prefix=""), dict(cell_size_m=0.0), dict(fit="stretch"), dict(components_per_tile=0),
])
def test_bad_params_rejected(bad):
    with pytest.raises(pydantic.ValidationError):
        LandscapeParams(**bad)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    project = tmp_path_factory.mktemp("landscape")
    shutil.copytree(ROOT / "configs", project / "configs")
    return project


QUICK = ["heightmap.resolution=64", "erosion.enabled=false", "hydrology.enabled=false", "vegetation.enabled=false"]


@pytest.mark.parametrize("sets,key", [
    (["landscape.tile_vertices=1000"], "landscape.tile_vertices"),
    (["landscape.cell_size_m=0.0001"], "landscape.cell_size_m"),
    (["landscape.components_per_tile=64", "landscape.quads_per_section=255"], "landscape.components_per_tile"),
])
def test_bad_params_refused_before_any_stage_runs(project, sets, key):
    store = Store(project / "build_refused")
    with pytest.raises(InputError, match=re.escape(key)):
        config = load_config(project / "configs" / "default.toml", all_stages(), project_root=project,
                             sets=QUICK + ['outputs=["landscape"]'] + sets)
        bake_worlds(store, [config], build_graph(all_stages()), log=open("/dev/null", "w"))
    assert not (project / "build_refused" / "artifacts").exists() or not any((project / "build_refused" / "artifacts").iterdir())


def test_runs_only_when_asked_and_through_the_engine(project):
    stages = all_stages()
    default = load_config(project / "configs" / "default.toml", stages, project_root=project)
    assert "landscape" not in default.outputs
    config = load_config(project / "configs" / "default.toml", stages, project_root=project,
                         sets=QUICK + ['outputs=["landscape"]', "landscape.quads_per_section=7",
                                       "landscape.sections_per_component=1", "landscape.components_per_tile=4"])
    store = Store(project / "build")
    reports = bake_worlds(store, [config], build_graph(stages), log=open("/dev/null", "w"))[config.name]
    assert [r.stage for r in reports] == ["heightmap", "landscape"]
    folder = store.folder("landscape", reports[-1].key)
    index = json.loads((folder / "landscape.json").read_text())
    assert index["tiles"] == [3, 3] and index["ground_types"] == []  # no vegetation: heights only
    assert (folder / files.UNREAL_DIR / "landscape_x2_y2.png").is_file()


def test_a_prefix_holding_x_and_y_still_names_the_tiles(tmp_path):
    ground, splat = world(rows=20, cols=30)
    index, _ = bake(tmp_path, ground, splat, prefix="map_x1_y2", **TINY)
    for f in (tmp_path / files.UNREAL_DIR).iterdir():
        base, col, row = unreal_coordinates(f.stem)
        assert base in {"map_x1_y2"} | {f"map_x1_y2_{g}" for g in GROUND_TYPES}
        assert [col, row] in [t["tile"] for t in index["tile_list"]]


def test_check_plans_the_tiles_from_the_ground_size():
    from pipeline.contract import CheckContext, GridInfo
    from stages.landscape.stage import check

    ctx = CheckContext(seed=0, project_root=ROOT, inputs={"ground": GridInfo((1024, 1024), 8.0)})
    result = check(LandscapeParams(), ctx)
    assert result.work == 2017 * 2017 * 7 and "2 x 2 tiles of 1009^2" in result.work_how
    assert 100e6 < result.memory_bytes < 300e6  # the inputs (32 MB), a tile and a band: about 155 MB measured
    assert check(LandscapeParams(weightmaps=False, fit="resample"), ctx).work == 2017 * 2017


def test_a_rebake_writes_the_same_bytes(tmp_path):
    ground, splat = world(rows=30, cols=30)
    digests = []
    for k in range(2):
        out = tmp_path / str(k)
        out.mkdir()
        bake(out, ground, splat, **TINY)
        digests.append({p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()})
    assert len(digests[0]) == 9 * 9 and digests[0] == digests[1]  # 9 tiles x (EXR, sidecar, PNG, 6 weightmaps)


@pytest.mark.parametrize("tile_cells, kw", [(256, TINY), (256, dict(TINY, fit="resample", share_borders=False))])
def test_a_tiled_run_reads_windows_and_writes_the_same_files(tmp_path, tile_cells, kw):
    """run_tiled (a tiled world): the height range reduced over world tiles,
    each landscape tile sampled from windows of the input files; the files
    are run's byte for byte, holes and a splat stored in another channel order too."""
    from pipeline.tiles import GridFile, TileRunner

    ground, splat = world(rows=300, cols=520, seed=3)
    h = ground.data.copy()
    h[100:103, 300:340] = np.nan
    ground = Grid(h, ground.cell_size_m, ("height",), ground.origin_m)
    order = list(reversed(SPLAT_CHANNELS))
    splat = Grid(np.ascontiguousarray(splat.data[..., ::-1]), splat.cell_size_m, tuple(order), splat.origin_m)
    (tmp_path / "in").mkdir()
    exr.write_grid(tmp_path / "in" / "ground.exr", ground)
    exr.write_grid(tmp_path / "in" / "splat.exr", splat)
    whole_dir, tiled_dir = tmp_path / "whole", tmp_path / "tiled"
    whole_dir.mkdir(), tiled_dir.mkdir()
    params = LandscapeParams(**kw)
    whole = STAGE.run(RunContext(stage=STAGE, key="k", out_dir=whole_dir, seed=0, provenance={}, project_root=tmp_path),
                      {"ground": exr.read_grid(tmp_path / "in" / "ground.exr"),
                       "splat": exr.read_grid(tmp_path / "in" / "splat.exr")}, params)
    ctx = RunContext(stage=STAGE, key="k", out_dir=tiled_dir, seed=0, provenance={}, project_root=tmp_path)
    ctx.tiles = TileRunner(tile_cells, stage=STAGE, run_key="k", seed=0, project_root=tmp_path, units=None,
                           work=tmp_path / "work")
    tiled = STAGE.run_tiled(ctx, {"ground": GridFile(tmp_path / "in" / "ground.exr"),
                                  "splat": GridFile(tmp_path / "in" / "splat.exr")}, params)
    assert whole == tiled and ctx.tiles.passes[0]["tiles"] == 6
    names = sorted(p.relative_to(whole_dir) for p in whole_dir.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(tiled_dir) for p in tiled_dir.rglob("*") if p.is_file()) and names
    assert all((whole_dir / n).read_bytes() == (tiled_dir / n).read_bytes() for n in names)
