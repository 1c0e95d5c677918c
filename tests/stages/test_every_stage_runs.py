"""The landlab-style contract test: every registered stage runs on a tiny
world through the engine, and every file it wrote is checked against its
declaration from the file itself: exists, exactly the declared channels (by
name: OpenEXR stores them sorted), dtype, units, finite values; and no file
that no output declares. A new stage is in this test by being registered."""
from __future__ import annotations

import fnmatch
import json
import shutil

import numpy as np
import pytest

from pipeline import exr
from pipeline.config import load_config
from pipeline.executors import bake_worlds
from pipeline.graph import build_graph
from pipeline.registry import all_stages
from pipeline.store import MANIFEST, Store

from .test_sources import ROOT

STAGES = all_stages()
TINY = ["heightmap.resolution=64", "world.texture_size=64", "shared.mesh_max_vertices=33",
        "world.ground_texel_m=16", "world.ground_tile_texels=256",
        'plants.build=["grass", "shrub"]', "erosion.geological_years=20000", "erosion.geological_step_years=10000",
        "volumes.voxels=32", "volumes.mip_levels=3", "volumes.error_view_pixels=32",
        "impostors.frames=4", "impostors.atlas_px=64", "impostors.min_frame_px=8", "impostors.small_plant_frame_px=8",
        "impostors.samples=1",
        "impostors.ao_rays=1", "impostors.slice_px=16", "impostors.drawn_slice_px=16", "impostors.grass_slice_px=16", "impostors.card_px=16",
        "impostors.heldout_px=24", "impostors.heldout_samples=1", "impostors.heldout_stride=108"]


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """Every stage enabled, every stage wanted; the manifests of the runs."""
    project = tmp_path_factory.mktemp("contract")
    shutil.copytree(ROOT / "configs", project / "configs")
    sets = TINY + [f"outputs={json.dumps(sorted(STAGES))}"]
    config = load_config(project / "configs" / "default.toml", STAGES, project_root=project, sets=sets)
    store = Store(project / "build")
    reports = bake_worlds(store, [config], build_graph(STAGES), log=open("/dev/null", "w"))[config.name]
    return store, {r.stage: store.folder(r.stage, r.key) for r in reports}


def test_every_registered_stage_ran(baked):
    _, folders = baked
    assert set(folders) == set(STAGES)


@pytest.mark.parametrize("name", sorted(STAGES))
def test_every_output_is_as_declared(baked, name):
    store, folders = baked
    stage, folder = STAGES[name], folders[name]
    manifest = json.loads((folder / MANIFEST).read_text())
    written = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()} - {MANIFEST}
    claimed = set()
    for art in stage.outputs:
        meta = manifest["outputs"][art.name]
        if meta.get("absent"):
            assert art.optional, f"{art.name} is absent but not optional"
            continue
        path = folder / art.file
        assert path.is_file(), f"{art.name}: {art.file} missing"
        claimed.add(art.file)
        claimed |= {f for f in written for pat in art.beside if fnmatch.fnmatchcase(f, pat)}
        if art.kind == "grid":
            grid = exr.read_grid(path)
            assert art.channel_sets(tuple(grid.channels)) is None, (art.name, grid.channels)
            assert set(grid.channels) == set(art.expand(tuple(grid.channels)))
            assert grid.data.dtype == np.dtype(art.dtype)
            units = json.loads(exr.read_attributes(path)["worldbake:units"])
            assert units == art.channel_units(tuple(grid.channels)), art.name
            assert all(units.values()), f"{art.name}: a channel without units"
            bad = np.isinf(grid.data) if art.nodata_nan else ~np.isfinite(grid.data)
            assert not bad.any(), f"{art.name}: non-finite values"
        elif art.kind == "json":
            json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{art.name}: {c} in JSON"))
        elif art.kind == "image":
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        elif art.kind == "usd":
            from pxr import Sdf
            assert Sdf.Layer.FindOrOpen(str(path)) is not None
    assert written <= claimed, f"stage {name} wrote undeclared files {sorted(written - claimed)}"


def test_a_rebake_with_unchanged_plants_reuses_the_impostors(baked):
    """The impostors' key hashes the content of the plant assets (and the
    placed names) it reads, not the producers' keys: a re-bake whose change
    leaves the plants as they were does not re-bake the impostors."""
    store, folders = baked
    project = store.build.parent
    sets = TINY + [f"outputs={json.dumps(sorted(STAGES))}"]

    def rebake(*more):
        config = load_config(project / "configs" / "default.toml", STAGES, project_root=project, sets=sets + list(more))
        reports = bake_worlds(store, [config], build_graph(STAGES), log=open("/dev/null", "w"))[config.name]
        return {r.stage: r.status for r in reports}

    status = rebake("world.roughness=0.5")
    assert status["world"] == "ran" and status["plants"] == "cached" and status["impostors"] == "cached"
