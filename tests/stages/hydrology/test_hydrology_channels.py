"""River channels: hydraulic geometry, the water level, the carved ground,
the river ribbons on their beds and the water material of every water mesh."""
import numpy as np
import pytest

from pipeline.contract import RunContext
from pipeline.grid import Grid
from pipeline.opencl import get_cl
from stages.hydrology import STAGE, HydrologyParams
from stages.hydrology import channels
from stages.hydrology.routing import SECONDS_PER_YEAR

CLIMATE = dict(rain_mm_per_year=1500.0, runoff_coefficient=0.6)  # configs/default.toml [hydrology]


def test_hydraulic_geometry_formula():
    q = np.array([0.0, 0.5, 2.0, 50.0])
    w, d = channels.hydraulic_geometry(q, 4.33, 0.5, 0.22, 0.37)
    assert np.allclose(w, 4.33 * np.sqrt(q)) and np.allclose(d, 0.22 * q ** 0.37)
    assert w[2] == pytest.approx(6.1235, abs=1e-3)  # 4.33 sqrt(2)
    assert channels.bankfull_discharge(np.array([0.3]), 7.0)[0] == pytest.approx(2.1)
    # the default climate at 10 km^2: Q = 0.9 m/year x 1e7 m^2, bankfull 7 Q, width over 5 m
    p = HydrologyParams(**CLIMATE)
    q_mean = p.rain_mm_per_year / 1000 * p.runoff_coefficient * 1e7 / SECONDS_PER_YEAR
    w10, _ = channels.hydraulic_geometry(channels.bankfull_discharge(q_mean, p.bankfull_discharge_ratio),
                                         p.width_coefficient, p.width_exponent, p.depth_coefficient, p.depth_exponent)
    assert 5.0 <= float(w10) <= 10.0


def test_water_level_never_rises_and_lakes_hand_on_their_level():
    # a chain 0 -> 1 -> 2 -> 3 -> 4 -> outlet; cell 2 is a lake at level 5
    rcv = np.array([1, 2, 3, 4, -1])
    net = np.ones(5, bool)
    levels = [np.array([0]), np.array([1]), np.array([2]), np.array([3]), np.array([4])]
    h = np.array([10.0, 6.0, 2.0, 7.0, 4.0])
    lake = np.array([np.nan, np.nan, 5.0, np.nan, np.nan])
    full = channels.water_level(rcv, net, levels, h, lake, np.array([False, False, True, False, False]))
    assert full.tolist() == [10.0, 6.0, 5.0, 5.0, 4.0]  # the full lake's level cuts through the rim at 7
    dry = channels.water_level(rcv, net, levels, h, lake, np.zeros(5, bool))
    assert dry.tolist() == [10.0, 6.0, 5.0, 7.0, 4.0]  # a lake that does not spill: the river restarts below it


def basin(rows=200, cols=160, dx=20.0):
    """A V-shaped valley draining south, 16 x 20 cells ... 12.8 km^2 at 20 m cells."""
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
    h = 0.03 * (rows - r) * dx + 0.25 * np.abs(c - cols // 2) * dx + 0.002 * c * dx
    return h.astype(np.float32), dx


@pytest.fixture(scope="module")
def basin_bake(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("basin")
    h, dx = basin()
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="t", out_dir=tmp, seed=0, provenance={}, project_root=tmp)
    out = STAGE.run(ctx, {"terrain": Grid(h, dx)}, HydrologyParams(**CLIMATE, lake_min_area_m2=0.0))
    return h, dx, out


def test_width_at_least_5_m_past_10_km2(basin_bake):
    h, dx, out = basin_bake
    area = out["hydrology.accumulation"].channel("flow.accumulation")
    width = out["hydrology.rivers"].channel("river.width")
    big = area >= 1e7
    assert big.sum() >= 10, "the basin should drain 10 km^2"
    assert width[big].min() >= 5.0
    table = out["hydrology.stats"]["river_width_by_area"]
    row = next(r for r in table if r["area_km2_from"] == 10.0)
    assert row["width_min_m"] >= 5.0 and row["cells"] == int(big.sum())


@pytest.fixture(scope="module")
def bowl_bake(tmp_path_factory):
    """A bowl that holds one lake."""
    tmp = tmp_path_factory.mktemp("bowl")
    yy, xx = np.mgrid[0:48, 0:48]
    bowl = (((xx - 24.0) ** 2 + (yy - 24.0) ** 2) * 0.2 + 100).astype(np.float32)
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="t", out_dir=tmp, seed=0, provenance={}, project_root=tmp)
    out = STAGE.run(ctx, {"terrain": Grid(bowl, 8.0)}, HydrologyParams(lake_runoff_depth_m=2.0, lake_min_area_m2=0.0))
    return bowl, ctx, out


def _ribbon(out):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(out["hydrology.water"]))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Water/Rivers/Ribbons"))
    assert mesh, "no river surface mesh"
    pts = np.array(mesh.GetPointsAttr().Get(), np.float64)
    idx = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 4)
    return stage, pts, idx


def test_ribbon_lies_on_its_bed_and_never_climbs(basin_bake):
    h, dx, out = basin_bake
    _, pts, idx = _ribbon(out)
    ground = out["hydrology.ground"].channel("height").astype(np.float64)
    dy = pts[:, 1] - channels.bilinear_at(ground, dx, (0.0, 0.0), pts[:, 0], pts[:, 2])
    assert np.abs(dy).max() <= 0.5, np.abs(dy).max()
    # quads (left i, right i, right i+1, left i+1): the far side never higher than the near side
    assert (pts[idx[:, 3], 1] <= pts[idx[:, 0], 1] + 1e-4).all()
    assert (pts[idx[:, 2], 1] <= pts[idx[:, 1], 1] + 1e-4).all()
    # every quad faces up (USD rightHanded: counter-clockwise seen from +Y)
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    assert (np.cross(b - a, c - a)[:, 1] > 0).mean() > 0.99
    # the banks are as far apart as the bankfull width at the reach's cells
    width = out["hydrology.rivers"].channel("river.width")
    span = np.linalg.norm((pts[idx[:, 0]] - pts[idx[:, 1]])[:, [0, 2]], axis=1)
    assert span.max() <= width.max() + 1e-3 and span.min() >= HydrologyParams().river_mesh_min_width_m - 1e-3
    assert out["hydrology.stats"]["river_segments_climbing"] == 0


def test_carved_ground_equals_terrain_away_from_rivers(basin_bake):
    from scipy import ndimage

    h, dx, out = basin_bake
    ground = out["hydrology.ground"].channel("height")
    p = HydrologyParams()
    width = out["hydrology.rivers"].channel("river.width")
    shown = width >= p.river_mesh_min_width_m
    reach = max(width.max() / 2, channels.BED_MIN_HALF_CELLS * dx) + p.river_floor_m + p.river_bank_m + 2 * dx
    far = ndimage.distance_transform_edt(~shown) * dx > reach
    assert far.sum() > 0.5 * h.size
    assert np.array_equal(ground[far], h[far])
    assert (ground <= h).all()
    # the bed is cut: at the channel cells, by about the centre depth
    depth = out["hydrology.stats"]["river_depth_max_m"]
    assert 0.0 < (h - ground)[shown].max() <= 1.5 * depth + 1e-3


def test_every_water_mesh_has_the_water_material(basin_bake, bowl_bake):
    from pxr import Usd, UsdGeom, UsdShade

    stage, _, _ = _ribbon(basin_bake[2])
    stages = [stage, Usd.Stage.Open(str(bowl_bake[2]["hydrology.water"]))]
    meshes = [p for s in stages for p in s.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert any("/Lakes/" in str(m.GetPath()) for m in meshes) and any("/Rivers/" in str(m.GetPath()) for m in meshes)
    for prim in meshes:
        mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        assert mat, f"{prim.GetPath()} has no material"
        surf = mat.ComputeSurfaceSource()[0]
        assert surf and surf.GetIdAttr().Get() == "UsdPreviewSurface"
        colour = surf.GetInput("diffuseColor").Get()
        assert colour is not None and max(colour) < 0.5
        assert surf.GetInput("roughness").Get() <= 0.1
        assert surf.GetInput("metallic").Get() == 0.0
        assert 0.0 < surf.GetInput("opacity").Get() < 1.0
        assert surf.GetInput("ior").Get() == pytest.approx(1.33)
    for s in stages:  # no BasisCurves left: a DCC gives them no material
        assert not any(p.IsA(UsdGeom.BasisCurves) for p in s.Traverse())


def test_lake_mesh_at_its_level(bowl_bake, tmp_path):
    from pxr import Usd, UsdGeom

    bowl, ctx, out = bowl_bake
    level = np.nanmax(out["hydrology.lakes"].channel("lake.level"))
    stage = Usd.Stage.Open(str(out["hydrology.water"]))
    lakes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and "/Lakes/" in str(p.GetPath())]
    assert len(lakes) == 1
    ys = np.array(UsdGeom.Mesh(lakes[0]).GetPointsAttr().Get())[:, 1]
    assert np.ptp(ys) == 0 and ys[0] == pytest.approx(level, abs=1e-3)
    # a lake smaller than lake_min_area_m2 is not drawn
    ctx = RunContext(cl=get_cl(), stage=STAGE, key="t", out_dir=tmp_path, seed=0, provenance={}, project_root=tmp_path)
    small = STAGE.run(ctx, {"terrain": Grid(bowl, 8.0)}, HydrologyParams(lake_runoff_depth_m=2.0, lake_min_area_m2=1e9))
    assert small["hydrology.stats"]["usd_lakes"] == 0


def test_width_table_in_the_report(basin_bake):
    from stages.hydrology.report_water import width_tables

    _, _, out = basin_bake
    (table,) = width_tables(out["hydrology.water"])
    stats = out["hydrology.stats"]["river_width_by_area"]
    assert len(table.rows) == len(stats)
    last = table.rows[-1]
    assert last[0].startswith("10 ") and last[2] == round(stats[-1]["width_min_m"], 2) >= 5.0
