"""What the stages declare for the report (Stage.report) names what they
write: every map and warning reads one of the stage's grids and a channel
(or pattern) it declares; every relief reads terrain grids some stage
writes; names are unique within a stage and palettes are the report's."""
from __future__ import annotations

import pytest

from pipeline.contract import DrawnMap, ReportMap, ReportPicture, ReportTable, ReportWarning
from pipeline.registry import all_stages
from pipeline.report import PALETTES

STAGES = all_stages()
GRIDS = {a.name: a for s in STAGES.values() for a in s.outputs if a.kind == "grid"}


def _pattern_head(pattern: str) -> str:
    return pattern.split("{")[0]


@pytest.mark.parametrize("name", sorted(STAGES))
def test_report_declarations_name_what_the_stage_writes(name):
    stage = STAGES[name]
    own = {a.name: a for a in stage.outputs}
    names = [d.name for d in stage.report if isinstance(d, (ReportMap, DrawnMap, ReportPicture))]
    assert len(names) == len(set(names)), names
    for d in stage.report:
        assert isinstance(d, (ReportMap, DrawnMap, ReportPicture, ReportTable, ReportWarning)), d
        if isinstance(d, (ReportMap, ReportWarning)):
            assert d.artifact in own and own[d.artifact].kind == "grid", d
            declared = own[d.artifact].channels
            if "{" in d.channel:  # a pattern: some declared channel (or pattern) has its head
                assert any(c.startswith(_pattern_head(d.channel)) for c in declared), (d.channel, declared)
            else:
                assert d.channel in declared, (d.channel, declared)
        if isinstance(d, ReportMap):
            assert isinstance(d.palette, tuple) or d.palette in PALETTES, d.palette
        relief = getattr(d, "relief", None)
        if relief is not None:
            assert relief.one_of and all(relief.channel in GRIDS[a].channels for a in relief.one_of), relief
        for callable_ in (getattr(d, attr, None) for attr in ("draw", "make")):
            if callable_ is not None:  # a function of the stage's own folder (or a library), not another stage's
                module = callable_.__module__
                assert not module.startswith("stages.") or module.startswith(f"stages.{name}."), module


def test_the_default_world_declares_maps_pictures_tables_and_warnings():
    kinds = {type(d) for s in STAGES.values() for d in s.report}
    assert kinds == {ReportMap, DrawnMap, ReportPicture, ReportTable, ReportWarning}
