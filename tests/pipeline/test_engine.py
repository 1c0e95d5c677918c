"""The engine on toy stages: planning, caching, atomic store, config validation."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline import exr, usdio
from pipeline.bake import plan_bake
from pipeline.executors import bake_worlds
from pipeline.config import load_config
from pipeline.contract import Artifact, Input, Stage
from pipeline.errors import InputError, StageError
from pipeline.graph import GraphError, build_graph
from pipeline.store import Store, StoreBusy

from . import toy_stages
from .toy_stages import TOY


@pytest.fixture
def project(tmp_path):
    (tmp_path / "configs").mkdir()
    toy_stages.CALLS.clear()
    return tmp_path


def write(project: Path, text: str, name: str = "w.toml") -> Path:
    p = project / "configs" / name
    p.write_text(text)
    return p


def load(project, path, **kw):
    return load_config(path, TOY, project_root=project, **kw)


def do_bake(project, path, **kw):
    config = load(project, path, **kw)
    store = Store(project / "build")
    reports = bake_worlds(store, [config], build_graph(TOY), log=open("/dev/null", "w"))[config.name]
    return {r.stage: r.status for r in reports}, store, config


def baked_keys(project, path, **kw) -> dict[str, str]:
    config = load(project, path, **kw)
    reports = bake_worlds(Store(project / "build"), [config], build_graph(TOY), log=open("/dev/null", "w"))[config.name]
    return {r.stage: r.key for r in reports}


BASE = 'name = "w"\nseed = 3\noutputs = ["assemble"]\n[source]\nsize = 8\n'


def test_plan_is_minimal_and_in_dependency_order(project):
    cfg = load(project, write(project, 'outputs = ["source.height"]\n'))
    assert [p.stage.name for p in plan_bake(build_graph(TOY), cfg)] == ["source"]
    cfg = load(project, write(project, BASE))
    assert [p.stage.name for p in plan_bake(build_graph(TOY), cfg)] == ["source", "shift", "assemble"]


def test_disabled_stage_falls_back_to_the_next_producer(project):
    cfg = load(project, write(project, BASE + "[shift]\nenabled = false\n"))
    steps = plan_bake(build_graph(TOY), cfg)
    assert [p.stage.name for p in steps] == ["source", "assemble"]
    assert steps[-1].inputs["terrain"][0] == "source.height"


def test_second_bake_runs_nothing_and_changes_rerun_only_downstream(project):
    path = write(project, BASE)
    status, store, _ = do_bake(project, path)
    assert status == {"source": "ran", "shift": "ran", "assemble": "ran"}
    status, _, _ = do_bake(project, path)
    assert set(status.values()) == {"cached"}
    status, _, _ = do_bake(project, path, sets=["assemble.label=other"])
    assert status == {"source": "cached", "shift": "cached", "assemble": "ran"}
    status, _, _ = do_bake(project, path, sets=["source.level_m=2.0"])
    assert status == {"source": "ran", "shift": "ran", "assemble": "ran"}
    status, _, _ = do_bake(project, path, sets=["seed=4"])  # only source uses the seed
    assert status["source"] == "ran"


def test_keys_are_stable_and_depend_on_what_matters(project):
    path = write(project, BASE)
    graph = build_graph(TOY)
    r1 = [p.recipe for p in plan_bake(graph, load(project, path))]
    assert r1 == [p.recipe for p in plan_bake(graph, load(project, path))]
    k1 = baked_keys(project, path)
    assert k1 == baked_keys(project, path)
    k2 = baked_keys(project, path, sets=["shift.amount_m=1.5"])
    assert k2["source"] == k1["source"] and k2["shift"] != k1["shift"] and k2["assemble"] != k1["assemble"]


def test_early_cutoff_an_upstream_rerun_with_the_same_bytes_reruns_nothing_downstream(project):
    """The source adds seed % 7: seeds 3 and 10 give the same bytes under
    two keys (the seed is in the source's key). Downstream keys hash the
    content of their inputs, so nothing downstream re-runs."""
    path = write(project, BASE)
    first = baked_keys(project, path, sets=["seed=3"])
    toy_stages.CALLS.clear()
    second = baked_keys(project, path, sets=["seed=10"])
    assert toy_stages.CALLS == ["source"]
    assert second["source"] != first["source"]
    assert second["shift"] == first["shift"] and second["assemble"] == first["assemble"]
    # the cached shift names the first source run as its input: gc keeps it for the world
    store = Store(project / "build")
    assert store.gc() == []
    assert store.has("source", first["source"]) and store.has("source", second["source"])


def test_artifacts_manifest_provenance_and_world(project):
    status, store, config = do_bake(project, write(project, BASE))
    keys = baked_keys(project, write(project, BASE))
    for stage, key in keys.items():
        folder = store.folder(stage, key)
        manifest = json.loads((folder / "manifest.json").read_text())
        assert manifest["key"] == key
        for f, digest in manifest["files"].items():
            assert (folder / f).is_file()
    attrs = exr.read_attributes(store.folder("source", keys["source"]) / "height.exr")
    assert attrs["worldbake:stage"] == "source" and attrs["worldbake:key"] == keys["source"]
    assert json.loads(attrs["worldbake:params"])["size"] == 8
    world = store.worlds / "w"
    assert usdio.validate(world / "world.usda") == []
    refs = json.loads((world / "manifest.json").read_text())["artifacts"]
    assert {r["stage"] for r in refs} == {"source", "shift", "assemble"}
    from pxr import Usd
    stage = Usd.Stage.Open(str(world / "world.usda"))
    assert stage.GetDefaultPrim().GetPath() == "/World"
    assert not Path(stage.GetRootLayer().subLayerPaths[0]).is_absolute()


def test_failed_run_leaves_nothing(project):
    path = write(project, BASE + "[shift]\nfail_after_write = true\n")
    with pytest.raises(RuntimeError):
        do_bake(project, path)
    store = Store(project / "build")
    assert not (store.artifacts / "shift").exists()
    assert not any(store.tmp.iterdir())
    for folder in store.artifacts.glob("*/*"):
        assert (folder / "manifest.json").is_file()


def test_non_finite_output_is_refused(project):
    with pytest.raises(StageError, match=r"source.*non-finite.*row 1, col 2"):
        do_bake(project, write(project, BASE + 'mode = "nan"\n'))
    assert not (project / "build" / "artifacts" / "source").exists()


@pytest.mark.parametrize("mode, message", [
    ("extra_file", r"source: wrote files no output declares: \['notes.txt'\]"),
    ("extra_channel", r"source.height has channels \['height2'\] that are not declared"),
])
def test_undeclared_files_and_channels_are_refused(project, mode, message):
    with pytest.raises(StageError, match=message):
        do_bake(project, write(project, BASE + f'mode = "{mode}"\n'))
    assert not (project / "build" / "artifacts" / "source").exists()


def test_channel_patterns_and_units():
    art = Artifact("v.maps", "grid", "maps.exr", units="1, 1/ha, 1, 1, 1",
                   channels=("suitability.{plant}", "density.{plant}", "yield.{plant}",
                             "suitability.{grass}", "density.{grass}"))
    good = ("suitability.oak", "density.oak", "yield.oak", "suitability.meadow", "density.meadow")
    assert art.channel_sets(good) is None
    assert art.channel_units(good)["density.oak"] == "1/ha" and art.channel_units(good)["density.meadow"] == "1"
    assert "not declared" in art.channel_sets(("suitability.oak",))  # an incomplete set
    assert "not declared" in art.channel_sets(good + ("height",))
    fixed = Artifact("v.h", "grid", "h.exr", channels=("height", "water"), units="m")
    assert "misses" in fixed.channel_sets(("height",))


def test_graph_compares_what_consumers_read_with_what_producers_write():
    src = _stage("a", outputs=(Artifact("a.h", "grid", "h.exr", channels=("height",), units="m"),))
    for inp, message in ((Input("t", ("a.h",), channels=("depth",)), "reads channel 'depth'"),
                         (Input("t", ("a.h",), channels=("height",), units="ft"), "expects 'height' in 'ft'")):
        with pytest.raises(GraphError, match=message):
            build_graph({"a": src, "b": _stage("b", inputs=(inp,))})
    build_graph({"a": src, "b": _stage("b", inputs=(Input("t", ("a.h",), channels=("height",), units="m"),))})
    same_shape = Artifact("a.m", "grid", "m.exr", channels=("d.{x}", "d.{y}"), units="1, m")
    with pytest.raises(GraphError, match="ambiguous"):
        build_graph({"a": _stage("a", outputs=(same_shape,))})


def test_gc_keeps_referenced_artifacts(project):
    path = write(project, BASE)
    do_bake(project, path)
    do_bake(project, path, sets=["assemble.label=two"])  # world w now points at the new assemble key
    store = Store(project / "build")
    assert len(list((store.artifacts / "assemble").iterdir())) == 2
    removed = store.gc()  # the first assemble run and the unit only it used
    assert [p.parent.parent.name for p in removed] == ["artifacts", "units"]
    assert len(list((store.artifacts / "assemble").iterdir())) == 1


def test_a_unit_is_reused_across_runs_trusted_only_whole_and_collected_with_its_runs(project):
    """A stage part whose material did not change is linked from the run
    that made it, though the stage's key changed; a damaged unit is made
    again; gc removes the units no kept run names."""
    path = write(project, BASE)
    store = Store(project / "build")
    do_bake(project, path)
    assert toy_stages.CALLS.count("assemble.label") == 1
    first = json.loads((store.worlds / "w" / "manifest.json").read_text())

    toy_stages.CALLS.clear()
    statuses, _, _ = do_bake(project, path, sets=["source.size=9"])  # new terrain, same label
    assert statuses["assemble"] == "ran" and "assemble" in toy_stages.CALLS
    assert "assemble.label" not in toy_stages.CALLS
    keys = {e["stage"]: e["key"] for e in json.loads((store.worlds / "w" / "manifest.json").read_text())["artifacts"]}
    old_keys = {e["stage"]: e["key"] for e in first["artifacts"]}
    assert keys["assemble"] != old_keys["assemble"]
    units = store.manifest("assemble", keys["assemble"])["units"]
    assert units == store.manifest("assemble", old_keys["assemble"])["units"]
    assert (store.folder("assemble", keys["assemble"]) / "label.txt").read_text() == \
        (store.folder("assemble", old_keys["assemble"]) / "label.txt").read_text()

    unit_dir = store.units / "assemble" / units["label"]
    (unit_dir / "label.txt").write_text("tampered\n")
    toy_stages.CALLS.clear()
    do_bake(project, path, sets=["source.size=10"])
    assert "assemble.label" in toy_stages.CALLS  # not trusted: made again
    assert (unit_dir / "label.txt").read_text().startswith("x ")

    do_bake(project, path, sets=["assemble.label=two"])
    assert len(list((store.units / "assemble").iterdir())) == 2
    store.gc()
    assert [p.name for p in (store.units / "assemble").iterdir()] == \
        [store.manifest("assemble", e["key"])["units"]["label"]
         for e in json.loads((store.worlds / "w" / "manifest.json").read_text())["artifacts"] if e["stage"] == "assemble"]


def test_a_stored_run_whose_file_changed_is_made_again_not_reused(project):
    """A cached run is reused only while its files are what it wrote: an
    edited file sends the stage to run again (same key, same bytes), and the
    steps after it stay cached; a file only touched is still reused."""
    import os

    path = write(project, BASE)
    statuses, store, _ = do_bake(project, path)
    keys = baked_keys(project, path)
    height = store.folder("source", keys["source"]) / "height.exr"
    original = height.read_bytes()
    os.utime(height, ns=(height.stat().st_atime_ns, height.stat().st_mtime_ns + 10**9))  # touched, same bytes
    toy_stages.CALLS.clear()
    assert set(do_bake(project, path)[0].values()) == {"cached"} and toy_stages.CALLS == []
    written_ns = height.stat().st_mtime_ns
    height.write_bytes(original[:-10] + b"x" * 10)  # edited in place: same size, later mtime
    os.utime(height, ns=(written_ns, written_ns + 2 * 10**9))  # later even on a file system with coarse times
    toy_stages.CALLS.clear()
    statuses, _, _ = do_bake(project, path)
    assert statuses == {"source": "ran", "shift": "cached", "assemble": "cached"}
    assert height.read_bytes() == original and baked_keys(project, path) == keys
    (store.folder("shift", keys["shift"]) / "height.exr").unlink()  # removed
    assert do_bake(project, path)[0]["shift"] == "ran"
    assert not list(store.tmp.glob("discarded-*"))


def test_gc_refuses_or_waits_while_a_bake_holds_the_store(project):
    path = write(project, BASE)
    do_bake(project, path)
    do_bake(project, path, sets=["assemble.label=two"])  # the first assemble is now unreferenced
    store = Store(project / "build")
    with store.baking():
        with pytest.raises(StoreBusy):
            store.gc(wait=False)
        assert len(list((store.artifacts / "assemble").iterdir())) == 2
    assert len([p for p in store.gc(wait=False) if p.parent.parent.name == "artifacts"]) == 1


def test_gc_during_a_bake_leaves_the_bakes_result_intact(project, monkeypatch):
    """The bake stops in its last stage, when its first stages' artifacts
    exist but no world names them yet; gc starts then and must wait."""
    import threading

    running, release = threading.Event(), threading.Event()
    monkeypatch.setitem(toy_stages.HOOKS, "assemble", lambda: (running.set(), release.wait(60)))
    path = write(project, BASE)
    bake = threading.Thread(target=do_bake, args=(project, path))
    bake.start()
    assert running.wait(60)
    removed: list = []
    gc = threading.Thread(target=lambda: removed.extend(Store(project / "build").gc()))
    gc.start()
    release.set()
    bake.join(60)
    gc.join(60)
    assert removed == []
    store = Store(project / "build")
    for entry in json.loads((store.worlds / "w" / "manifest.json").read_text())["artifacts"]:
        assert store.has(entry["stage"], entry["key"])


def test_stale_tmp_from_a_dead_run_is_removed(project):
    store = Store(project / "build")
    (store.tmp / "source-abc-999999999").mkdir(parents=True)
    do_bake(project, write(project, BASE))
    assert not (store.tmp / "source-abc-999999999").exists()


# ----------------------------------------------------------------- config validation


@pytest.mark.parametrize("text, pattern", [
    (BASE + "bogus = 1\n", r"w.toml: source.bogus: unknown key .*allowed in \[source\]"),
    (BASE + "[nope]\nx = 1\n", r"w.toml: nope: unknown key"),
    (BASE + 'level_m = "high"\n', r"w.toml: source.level_m: .*valid number, got 'high'; allowed: -100.0 .. 100.0 m"),
    (BASE.replace("size = 8", 'size = "8"'), r"w.toml: source.size: .*integer"),
    (BASE.replace("size = 8", "size = 1000"), r"w.toml: source.size: .*less than or equal to 64.*1000"),
    (BASE + 'mode = "spiral"\n', r"source.mode"),
    (BASE + 'data = "../../etc/passwd"\n', r"source.data: .*leaves the project"),
    (BASE + 'data = "/etc/passwd"\n', r"source.data: .*leaves the project"),
    (BASE + 'data = "missing.bin"\n', r"source.data: file 'missing.bin' not found"),
    ('seed = -1\n', r"seed: must be an integer"),
    ('outputs = ["nothing"]\n', r"outputs: 'nothing' is neither"),
    ('name = "a b"\n', r"name: must be"),
    ('extends = "../../outside.toml"\n', r"extends: .*leaves the project"),
    ('x = [1,\n', r"not valid TOML"),
])
def test_bad_config_names_file_and_key(project, text, pattern):
    with pytest.raises(InputError, match=pattern):
        cfg = load(project, write(project, text))
        plan_bake(build_graph(TOY), cfg)


def test_extends_variants_and_set(project):
    write(project, BASE + "level_m = 5.0\n", "base.toml")
    path = write(project, 'extends = "base.toml"\nname = "child"\n[source]\nsize = 16\n'
                          '[variants.high]\nsource.level_m = 9.0\n[variants.flat.source]\nmode = "flat"\n')
    cfg = load(project, path)
    assert cfg.name == "child" and cfg.params["source"].size == 16 and cfg.params["source"].level_m == 5.0
    high = load(project, path, variant="high")
    assert high.name == "child-high" and high.params["source"].level_m == 9.0
    assert load(project, path, variant="flat").params["source"].mode == "flat"
    assert load(project, path, sets=["source.size=4"]).params["source"].size == 4
    with pytest.raises(InputError, match="no variant 'low'"):
        load(project, path, variant="low")
    with pytest.raises(InputError, match=r"--set: source.size: .*greater than or equal to 2"):
        load(project, path, sets=["source.size=1"])


def test_error_in_extended_file_names_that_file(project):
    write(project, BASE.replace("size = 8", "size = 999"), "base.toml")
    with pytest.raises(InputError, match=r"configs/base.toml: source.size"):
        load(project, write(project, 'extends = "base.toml"\n'))


def test_extends_cycle(project):
    write(project, 'extends = "b.toml"\n', "a.toml")
    write(project, 'extends = "a.toml"\n', "b.toml")
    with pytest.raises(InputError, match="cycle"):
        load(project, project / "configs" / "a.toml")


def test_project_path_content_is_in_the_key(project):
    (project / "data.bin").write_bytes(b"abc")
    path = write(project, BASE + 'data = "data.bin"\n')
    k1 = plan_bake(build_graph(TOY), load(project, path))[0].recipe
    (project / "data.bin").write_bytes(b"abcd")
    assert plan_bake(build_graph(TOY), load(project, path))[0].recipe != k1


# ----------------------------------------------------------------- graph validation


def _stage(name, inputs=(), outputs=()):
    return Stage(name, 1, "", inputs, outputs, toy_stages.AssembleParams, lambda *a: {}, toy_stages.HERE)


def test_graph_rejects_bad_declarations():
    g = Artifact("a.x", "grid", "x.exr", channels=("x",))
    with pytest.raises(GraphError, match="two producers"):
        build_graph({"a": _stage("a", outputs=(g, Artifact("a.x", "grid", "y.exr")))})
    with pytest.raises(GraphError, match="no stage produces"):
        build_graph({"a": _stage("a", inputs=(Input("t", ("zz.y",)),))})
    with pytest.raises(GraphError, match="cycle"):
        build_graph({"a": _stage("a", (Input("t", ("b.y",)),), (Artifact("a.x", "grid", "x.exr"),)),
                     "b": _stage("b", (Input("t", ("a.x",)),), (Artifact("b.y", "grid", "y.exr"),))})
    with pytest.raises(GraphError, match="must be named"):
        build_graph({"a": _stage("a", outputs=(Artifact("b.x", "grid", "x.exr"),))})


def test_shared_params_are_set_once_and_must_agree(project, monkeypatch):
    import dataclasses
    stages = {n: dataclasses.replace(s, shared_params=("size",)) if n == "source" else s for n, s in TOY.items()}
    stages["twin"] = dataclasses.replace(TOY["source"], name="twin", shared_params=("size",))
    path = write(project, 'outputs = ["source"]\n[shared]\nsize = 12\n')
    cfg = load_config(path, stages, project_root=project)
    assert cfg.params["source"].size == cfg.params["twin"].size == 12
    with pytest.raises(InputError, match=r"source.size = 12, twin.size = 8: these must agree; set it once as shared.size"):
        load_config(write(project, '[source]\nsize = 12\n'), stages, project_root=project)
    with pytest.raises(InputError, match=r"shared.level_m: unknown key"):
        load_config(write(project, '[shared]\nlevel_m = 1.0\n'), stages, project_root=project)
