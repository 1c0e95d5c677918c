"""report.html on a hand-made store (no bake): warnings, the stage table
and the run time against error series come from whatever the runs'
manifests hold, for any stage name; maps and warnings from what the stages
declare (Stage.report)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import exr
from pipeline.contract import Params, ReportMap, ReportWarning, Stage, ValueRange
from pipeline.grid import Grid
from pipeline.report import World, referenced_images, stage_rows, time_error_series, warnings, write_report
from pipeline.store import Store, write_json


def _run(store: Store, stage: str, key: str, metrics: dict, outputs: dict | None = None) -> None:
    folder = store.folder(stage, key)
    folder.mkdir(parents=True)
    write_json(folder / "manifest.json", {"stage": stage, "key": key, "params": {}, "inputs": {}, "files": {},
                                          "outputs": outputs or {}, "timings": {"run_s": 1.5}, "metrics": metrics})


def _stage(name: str, *report) -> Stage:
    return Stage(name, 1, "a hand-made stage", (), (), Params, lambda ctx, inputs, params: {}, Path("."),
                 report=tuple(report))


def test_warnings_table_and_series_from_any_stage(tmp_path):
    store = Store(tmp_path / "build")
    suitability = np.zeros((4, 5, 2), np.float32)
    suitability[..., 0] = 0.5  # fern finds land, cactus none
    _run(store, "flora", "k1", {"unplaced": ["cactus"], "lod_budget_ok": False, "fit_error": 0.25,
                                "chain": [{"seconds": 0.1, "max_error": 0.3}, {"seconds": 0.4, "max_error": 0.1}]},
         {"flora.maps": {"kind": "grid", "file": "maps.exr", "channels": ["suitability.cactus", "suitability.fern"],
                         "channel_units": {}}})
    exr.write_grid(store.folder("flora", "k1") / "maps.exr",
                   Grid(suitability[..., ::-1].copy(), 10.0, ("suitability.cactus", "suitability.fern")))
    _run(store, "brandnew", "k2", {"voxels": 12})
    manifest = {"world": "w", "config": "configs/x.toml", "seed": 1, "outputs": ["brandnew"],
                "overrides": {"flora.density": 2, "ghost.param": 1}, "params": {"flora": {}, "brandnew": {}},
                "artifacts": [{"stage": "flora", "key": "k1"}, {"stage": "brandnew", "key": "k2"}],
                "steps": [{"stage": "flora", "key": "k1", "status": "ran", "seconds": 1.6},
                          {"stage": "brandnew", "key": "k2", "status": "cached", "seconds": 0.0}]}
    stages = {"flora": _stage("flora", ReportWarning("flora.maps", "suitability.{plant}",
                                                     "species {plant} found no suitable land"))}
    world = World(store, manifest, stages)
    text = "\n".join(warnings(world))
    assert "cactus found no suitable land" in text and "fern" not in text
    assert "unplaced: cactus" in text and "lod_budget_ok is false" in text
    assert "ghost.param" in text and "flora.density" not in text
    rows = {r["stage"]: r for r in stage_rows(world)}
    assert rows["brandnew"]["status"] == "cached" and rows["brandnew"]["stats"] == {"voxels": 12}
    assert rows["flora"]["errors"] == {"fit_error": 0.25}
    (series,) = time_error_series(world)
    assert series["stage"] == "flora" and series["points"] == [(0.1, 0.3), (0.4, 0.1)]
    out = tmp_path / "page"
    out.mkdir()
    page = write_report(store, out, manifest, None, stages).read_text()
    assert "<td>brandnew</td>" in page and "cactus found no suitable land" in page


def test_maps_are_what_the_stages_declare(tmp_path):
    """A pattern gives a map per bound name; categories give one map with a
    legend; a later stage's map of the same name replaces an earlier one."""
    store = Store(tmp_path / "build")
    rows, cols = 6, 8
    ramp = np.linspace(0.0, 1.0, rows * cols, dtype=np.float32).reshape(rows, cols)
    for stage, key, file in (("rough", "k1", "a.exr"), ("fine", "k2", "b.exr")):
        channels = ["level", "cover.moss", "cover.rock"]
        _run(store, stage, key, {}, {f"{stage}.grid": {"kind": "grid", "file": file, "channels": channels,
                                                        "channel_units": {"level": "m"}}})
        exr.write_grid(store.folder(stage, key) / file,
                       Grid(np.stack([ramp * 100, ramp, 1 - ramp], -1), 5.0, tuple(channels)))
    level = {s: ReportMap(f"{s}.grid", "level", name="level", title="Level ({artifact})") for s in ("rough", "fine")}
    stages = {"rough": _stage("rough", level["rough"]),
              "fine": _stage("fine", level["fine"],
                             ReportMap("fine.grid", "cover.{kind}", name="cover_{kind}", title="Cover: {kind}",
                                       palette="greens", values=ValueRange(0.0, 1.0)),
                             ReportMap("fine.grid", "cover.{kind}", name="cover", title="Largest cover",
                                       categories=(("moss", (20, 200, 20)),)))}
    manifest = {"world": "w", "config": "c.toml", "seed": 1, "outputs": ["fine"], "params": {},
                "artifacts": [{"stage": "rough", "key": "k1"}, {"stage": "fine", "key": "k2"}], "steps": []}
    out = tmp_path / "page"
    out.mkdir()
    path = write_report(store, out, manifest, None, stages)
    page = path.read_text()
    assert "Level (fine.grid)" in page and "Level (rough.grid)" not in page
    assert "Cover: moss" in page and "Cover: rock" in page and "Largest cover" in page
    assert "rgb(20, 200, 20)" in page and "rgb(128, 128, 128)" in page  # rock has no colour: grey
    assert "moss 50.0 %" in page and "100 m" in page  # the level's declared units
    images = referenced_images(path)
    assert {"report_level.png", "report_cover_moss.png", "report_cover_rock.png", "report_cover.png"} <= set(images)
    assert all((out / i).is_file() for i in images)
    assert "<h2>Warnings</h2><p class=\"ok\">none</p>" in page


def test_a_report_of_the_same_runs_reuses_its_figures(tmp_path, monkeypatch):
    """A bake with every run cached remakes the page (this bake's steps) from
    the last report's figures, carried into the new world folder; another
    run, or a changed figure file, makes them anew."""
    from pipeline import report

    store = Store(tmp_path / "build")
    ramp = np.linspace(0.0, 1.0, 48, dtype=np.float32).reshape(6, 8)
    for key in ("k1", "k2"):
        _run(store, "rough", key, {"fit_error": 0.5}, {"rough.grid": {"kind": "grid", "file": "a.exr",
                                                                       "channels": ["level"], "channel_units": {}}})
        exr.write_grid(store.folder("rough", key) / "a.exr", Grid(ramp[..., None] * (1 if key == "k1" else 2), 5.0,
                                                                  ("level",)))
    stages = {"rough": _stage("rough", ReportMap("rough.grid", "level", name="level", title="Level"))}

    def manifest(key, status):
        return {"world": "w", "config": "c.toml", "seed": 1, "outputs": ["rough"], "params": {},
                "artifacts": [{"stage": "rough", "key": key}],
                "steps": [{"stage": "rough", "key": key, "status": status, "seconds": 1.0 if status == "ran" else 0.0}]}

    made = []
    real = report._figures
    monkeypatch.setattr(report, "_figures", lambda *a: made.append(1) or real(*a))
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir(), second.mkdir()
    page1 = write_report(store, first, manifest("k1", "ran"), None, stages).read_text()
    report.carry_figures(first, second)
    page2 = write_report(store, second, manifest("k1", "cached"), None, stages).read_text()
    assert len(made) == 1 and "<td>cached</td>" in page2 and "<td>ran</td>" in page1
    assert page1.replace("<td>ran</td>", "") .split("<h2>")[1:3] == page2.replace("<td>cached</td>", "").split("<h2>")[1:3]
    assert all((second / i).is_file() for i in referenced_images(second / "report.html"))
    other = write_report(store, second, manifest("k2", "ran"), None, stages).read_text()
    assert len(made) == 2 and "k2" in other
    (second / "report_level.png").unlink()  # a figure gone: made anew
    write_report(store, second, manifest("k2", "cached"), None, stages)
    assert len(made) == 3 and (second / "report_level.png").is_file()


def test_a_big_grid_is_read_for_its_maps_as_block_means_band_by_band(tmp_path):
    from pipeline import exr
    from pipeline.grid import Grid
    from pipeline.report import read_for_map

    rng = np.random.default_rng(0)
    data = rng.random((1030, 301, 2)).astype(np.float32)
    exr.write_grid(tmp_path / "g.exr", Grid(data, 2.0, ("a", "b"), (10.0, 20.0)))
    small = read_for_map(tmp_path / "g.exr", cells=256)  # s = 5: 206 x 60 blocks
    want = data[:1030, :300].reshape(206, 5, 60, 5, 2).mean(axis=(1, 3))
    assert small.shape == (206, 60) and small.cell_size_m == 10.0 and set(small.channels) == {"a", "b"}
    for i, name in enumerate(("a", "b")):  # the file's channel order is not the writer's: read by name
        assert np.allclose(small.channel(name), want[..., i], rtol=1e-6, atol=1e-6)
        assert np.array_equal(read_for_map(tmp_path / "g.exr", cells=2048).channel(name), data[..., i])
