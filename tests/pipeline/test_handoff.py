"""Handing a world on: export (folder and .usdz), world history (--set
recorded, --name, worlds, gc --dry-run), diff, report.html in a headless
browser, and EXR channel names in the file's order. One small default-like
bake (module scoped) and two cheap ones on top of it serve every test."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from pipeline import exr, usdio

REPO = Path(__file__).resolve().parents[2]
# default.toml on a 2 km, 64^2 world (16x fewer plants than 8 km), 2 x 2 UDIM ground tiles, the grass asset
TINY = ["--set", "heightmap.resolution=64", "--set", "heightmap.size_m=2048", "--set", "world.texture_size=32",
        "--set", "shared.mesh_max_vertices=33", "--set", 'plants.build=["grass"]', "--set", "world.ground_texel_m=8",
        "--set", "world.ground_tile_texels=128"]
CHANGE = ["--set", "erosion.storm_hours=0.1"]


def worldbake(project: Path, *args: str, check: bool = True, report: bool = False) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True, cwd=project,
                          timeout=600, env={**os.environ, "WORLDBAKE_REPORT": "1" if report else "0"})
    if check and proc.returncode != 0:
        raise AssertionError(f"worldbake {' '.join(args)} exited {proc.returncode}:\n{proc.stderr}")
    return proc


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Path:
    """default (with its report), twin (the same config again: all cached)
    and rough (one erosion parameter changed, named)."""
    project = tmp_path_factory.mktemp("handoff")
    shutil.copytree(REPO / "configs", project / "configs")
    worldbake(project, "bake", "configs/default.toml", *TINY, report=True)
    worldbake(project, "bake", "configs/default.toml", *TINY, "--name", "twin")
    worldbake(project, "bake", "configs/default.toml", *TINY, *CHANGE, "--name", "rough")
    return project


def _asset_paths(layer_path: Path) -> list[str]:
    from pxr import Sdf, UsdUtils

    found: list[str] = []
    UsdUtils.ModifyAssetPaths(Sdf.Layer.FindOrOpen(str(layer_path)), lambda p: found.append(p) or p)
    return found


def test_export_folder_and_usdz_are_self_contained(baked, tmp_path):
    worldbake(baked, "export", "default", str(tmp_path / "copy"))
    worldbake(baked, "export", "default", str(tmp_path / "world.usdz"))
    folder = tmp_path / "copy"
    # readable names: a folder per stage, the root layer on top
    assert {"world.usda", "heightmap", "erosion", "hydrology", "vegetation", "plants", "world"} <= \
        {p.name for p in folder.iterdir()}
    layers = [p for p in folder.rglob("*") if p.suffix in (".usda", ".usdc")]
    for layer in layers:
        for asset in _asset_paths(layer):
            assert not os.path.isabs(asset) and asset.startswith(("./", "../")), (layer, asset)
            assert (layer.parent / asset.replace("<UDIM>", "1001")).resolve().is_relative_to(folder.resolve())
    for text in folder.rglob("*.usda"):
        assert str(baked) not in text.read_text()
    with zipfile.ZipFile(tmp_path / "world.usdz") as z:
        names = z.namelist()
    assert names[0] == "world.usda" and not [n for n in names if n.endswith(".exr")]
    assert [n for n in names if n.startswith("world/ground.1001.")] == ["world/ground.1001.png"]

    away = baked / "build.away"
    (baked / "build").rename(away)  # nothing may point back into the store
    try:
        from pxr import Ar, Usd, UsdGeom
        for path in (folder / "world.usda", tmp_path / "world.usdz"):
            assert usdio.validate(path) == [], path
            stage = Usd.Stage.Open(str(path))
            assert UsdGeom.Mesh(stage.GetPrimAtPath("/World/Terrain/Ground/Tile_x0_y0")).GetPointsAttr().Get()
            attr = stage.GetPrimAtPath("/World/Terrain/Looks/Ground/Albedo").GetAttribute("inputs:file")
            tex = attr.Get()
            assert "<UDIM>" in tex.path  # Ar resolves each tile, not the pattern
            tile = attr.GetPropertyStack()[0].layer.ComputeAbsolutePath(tex.path.replace("<UDIM>", "1001"))
            assert Ar.GetResolver().Resolve(tile), f"{path}: UDIM tile 1001 does not resolve"
    finally:
        away.rename(baked / "build")


def test_overrides_are_recorded_and_worlds_lists_them(baked):
    rows = {r["world"]: r for r in json.loads(worldbake(baked, "worlds", "--json").stdout)}
    assert set(rows) == {"default", "twin", "rough"}
    assert rows["rough"]["overrides"]["erosion.storm_hours"] == 0.1
    assert "erosion.storm_hours" not in rows["default"]["overrides"] and rows["default"]["world_usda"]
    from pxr import Sdf
    data = Sdf.Layer.FindOrOpen(str(baked / "build" / "worlds" / "rough" / "world.usda")).customLayerData
    assert json.loads(data["worldbake"]["overrides"])["erosion.storm_hours"] == 0.1
    # the earlier world is intact and loadable
    assert usdio.validate(baked / "build" / "worlds" / "default" / "world.usda") == []


def test_a_bake_with_other_overrides_does_not_replace_a_world(baked):
    world = baked / "build" / "worlds" / "default"
    before = (world / "manifest.json").read_text()
    proc = worldbake(baked, "bake", "configs/default.toml", *TINY, "--set", 'outputs=["hydrology"]', check=False)
    assert proc.returncode == 2 and "--name NAME" in proc.stderr and "Traceback" not in proc.stderr
    assert (world / "manifest.json").read_text() == before and (world / "world.usda").is_file()


def test_gc_dry_run_and_gc_keep_every_world(baked):
    out = worldbake(baked, "gc", "--dry-run").stdout
    assert "would be removed (dry run" in out
    worldbake(baked, "gc")
    store = baked / "build" / "artifacts"
    for name in ("default", "twin", "rough"):
        manifest = json.loads((baked / "build" / "worlds" / name / "manifest.json").read_text())
        for e in manifest["uses"]:
            assert (store / e["stage"] / e["key"] / "manifest.json").is_file(), (name, e)


def test_diff_equal_worlds_and_a_saved_manifest(baked, tmp_path):
    assert worldbake(baked, "diff", "default", "twin").returncode == 0
    saved = tmp_path / "saved.json"
    shutil.copy(baked / "build" / "worlds" / "default" / "manifest.json", saved)
    proc = worldbake(baked, "diff", str(saved), "default")
    assert proc.returncode == 0 and proc.stdout.strip().endswith("equal")


def test_diff_names_the_parameter_the_stages_and_the_artifacts(baked):
    proc = worldbake(baked, "diff", "default", "rough", "--json", check=False)
    assert proc.returncode == 1, proc.stderr
    d = json.loads(proc.stdout)
    assert [p["key"] for p in d["params"]] == ["erosion.storm_hours"]
    assert d["params"][0]["a"] == 0.15 and d["params"][0]["b"] == 0.1
    stages = {s["stage"] for s in d["stages"]}
    assert "erosion" in stages and "heightmap" not in stages
    height = next(a for a in d["artifacts"] if a["stage"] == "erosion" and a["file"] == "height.exr")
    h = height["channels"]["height"]
    assert 0 < h["changed_share"] <= 1 and h["max"] >= h["rms"] > 0
    world_usd = [a for a in d["artifacts"] if a.get("kind") == "usd"]
    assert world_usd and all({"prims_added", "prims_removed", "prims_changed", "instances"} <= set(a)
                             for a in world_usd)
    text = worldbake(baked, "diff", "default", "rough", check=False).stdout
    assert "erosion.storm_hours: 0.15 -> 0.1" in text and text.strip().endswith("different")


def test_every_exr_lists_its_channels_in_the_files_order(baked):
    manifest = json.loads((baked / "build" / "worlds" / "default" / "manifest.json").read_text())
    checked = 0
    for e in manifest["uses"]:
        folder = baked / "build" / "artifacts" / e["stage"] / e["key"]
        run = json.loads((folder / "manifest.json").read_text())
        files = sorted(f for f in run["files"] if f.lower().endswith(".exr"))
        assert sorted(run["exr_channels"]) == files
        for f in files:
            assert exr.channel_names(folder / f) == run["exr_channels"][f], (e, f)
            checked += 1
        for name, meta in run["outputs"].items():
            if meta.get("kind") == "grid" and not meta.get("absent"):
                assert meta["channels"] == exr.channel_names(folder / meta["file"]), name
                grid = exr.read_grid(folder / meta["file"])  # values follow the names
                assert list(grid.channels) == meta["channels"]
    assert checked >= 20


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def test_report_lists_what_a_user_must_see(baked):
    from pipeline.report import referenced_images

    world = baked / "build" / "worlds" / "default"
    page = (world / "report.html").read_text()
    images = referenced_images(world / "report.html")
    assert images and all((world / i).is_file() for i in images)
    for picture in ("report_view.png", "report_height.png", "report_change.png", "report_water.png",
                    "report_moisture.png", "report_ground.png", "report_density_grass.png"):
        assert picture in images
    for stage in ("heightmap", "erosion", "hydrology", "vegetation", "plants", "world"):
        assert f"<td>{stage}</td>" in page
    assert "LOD0 triangles" in page and "Run time against error" in page


def test_report_opens_in_headless_chromium_without_console_errors(baked, tmp_path):
    browser = _chromium()
    if browser is None:
        pytest.skip("no chromium on this machine (.ci/run installs it with apt-get)")
    world = baked / "build" / "worlds" / "default"
    # a copy that reports each image that failed to load, in the same folder (same relative paths)
    probe = world / "report_probe.html"
    probe.write_text((world / "report.html").read_text().replace("</body>", (
        "<script>window.addEventListener('load', () => { let bad = 0; for (const i of document.images) {"
        " if (!i.complete || i.naturalWidth === 0) { bad++; console.error('image failed: ' + i.src); } }"
        " console.log('images loaded: ' + (document.images.length - bad) + ' of ' + document.images.length); });"
        "</script></body>")))
    try:
        logs = {}
        for page in ("report.html", "report_probe.html"):
            proc = subprocess.run([browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
                                   "--v=0", "--virtual-time-budget=5000", f"--user-data-dir={tmp_path / 'profile'}",
                                   "--dump-dom", (world / page).as_uri()],
                                  capture_output=True, text=True, timeout=120)
            assert proc.returncode == 0, proc.stderr[-2000:]
            logs[page] = [line for line in proc.stderr.splitlines() if ":CONSOLE" in line]
    finally:
        probe.unlink()
    assert logs["report.html"] == []  # the page itself writes nothing to the console
    from pipeline.report import referenced_images
    n = len(referenced_images(world / "report.html"))
    assert len(logs["report_probe.html"]) == 1 and f"images loaded: {n} of {n}" in logs["report_probe.html"][0]
