"""The stage graph, built from the declarations alone, and the planner.

build_graph checks the declarations of all registered stages: one producer
per artifact name, artifact names prefixed by their stage, every input
alternative produced by some stage with the same kind/dtype/channels rule,
and no cycle. plan() resolves each input to the first alternative whose
producer is enabled, then keeps only the stages the wanted outputs need.
"""
from __future__ import annotations

from dataclasses import dataclass

from .contract import Artifact, Input, Stage
from .errors import InputError


class GraphError(Exception):
    """A mistake in the stage declarations (a bug in the code, not the config)."""


@dataclass(frozen=True)
class Graph:
    stages: dict[str, Stage]
    producers: dict[str, tuple[Stage, Artifact]]


@dataclass(frozen=True)
class Step:
    stage: Stage
    inputs: dict[str, str]  # role -> artifact name chosen for this bake


def _compatible(consumer_rule: Artifact, produced: Artifact) -> bool:
    return consumer_rule.kind == produced.kind and consumer_rule.dtype == produced.dtype


def _check_channel_sets(stage: Stage, art: Artifact) -> None:
    """Channel names are unique, units are one or one per channel, and no
    two placeholder sets have the same shape (a written channel set could
    belong to either: its units would be ambiguous)."""
    if len(set(art.channels)) != len(art.channels):
        raise GraphError(f"stage {stage.name}: output {art.name} declares a channel twice")
    if len(art.unit_list()) != max(len(art.channels), 1):
        raise GraphError(f"stage {stage.name}: output {art.name} gives {len(art.unit_list())} units for "
                         f"{len(art.channels)} channels")
    shapes: dict[frozenset, str] = {}
    sets: dict[str, set[str]] = {}
    for pat in art.channels:
        if "{" in pat:
            var = pat[pat.index("{") + 1:pat.index("}")]
            sets.setdefault(var, set()).add(pat.replace("{" + var + "}", "{}"))
    for var, shape in sets.items():
        if frozenset(shape) in shapes:
            raise GraphError(f"stage {stage.name}: output {art.name}: the channel sets {{{shapes[frozenset(shape)]}}} "
                             f"and {{{var}}} have the same patterns; which one a channel belongs to is ambiguous")
        shapes[frozenset(shape)] = var


def _check_channels(stage: Stage, inp: Input, art: Artifact) -> None:
    """What the consumer expects to read is what the producer writes: each
    channel it names is a declared channel (not a pattern) with the units
    the consumer expects; an optional input's producer may write nothing,
    a required input's may not."""
    if art.optional and not inp.optional:
        raise GraphError(f"stage {stage.name}: input {inp.role} is required, but {art.name} may be absent")
    if not inp.channels:
        return
    if art.kind != "grid":
        raise GraphError(f"stage {stage.name}: input {inp.role} names channels, but {art.name} is a {art.kind}")
    produced = dict(zip(art.channels, art.unit_list()))
    wanted = tuple(u.strip() for u in inp.units.split(",")) if inp.units else ()
    if len(wanted) == 1:
        wanted = wanted * len(inp.channels)
    if wanted and len(wanted) != len(inp.channels):
        raise GraphError(f"stage {stage.name}: input {inp.role} gives {len(wanted)} units for {len(inp.channels)} channels")
    for i, ch in enumerate(inp.channels):
        if ch not in produced:
            raise GraphError(f"stage {stage.name}: input {inp.role} reads channel {ch!r}, which {art.name} does not "
                             f"declare (it writes {list(art.channels)})")
        if wanted and wanted[i] != produced[ch]:
            raise GraphError(f"stage {stage.name}: input {inp.role} expects {ch!r} in {wanted[i]!r}, "
                             f"{art.name} writes it in {produced[ch]!r}")


def build_graph(stages: dict[str, Stage]) -> Graph:
    producers: dict[str, tuple[Stage, Artifact]] = {}
    for stage in stages.values():
        for art in stage.outputs:
            if not art.name.startswith(stage.name + "."):
                raise GraphError(f"stage {stage.name}: output {art.name!r} must be named '{stage.name}.<what>'")
            if art.name in producers:
                raise GraphError(f"artifact {art.name!r} has two producers: {producers[art.name][0].name} and {stage.name}")
            producers[art.name] = (stage, art)
            if art.kind == "grid":
                _check_channel_sets(stage, art)
        files = [a.file for a in stage.outputs]
        if len(set(files)) != len(files):
            raise GraphError(f"stage {stage.name}: two outputs share a file name")
    for stage in stages.values():
        roles = [i.role for i in stage.inputs]
        if len(set(roles)) != len(roles):
            raise GraphError(f"stage {stage.name}: two inputs share a role")
        for inp in stage.inputs:
            if not inp.one_of:
                raise GraphError(f"stage {stage.name}: input {inp.role} names no artifact")
            first = None
            for name in inp.one_of:
                if name not in producers:
                    raise GraphError(f"stage {stage.name}: input {inp.role} wants {name!r}, which no stage produces")
                art = producers[name][1]
                _check_channels(stage, inp, art)
                if first is not None and not _compatible(first, art):
                    raise GraphError(f"stage {stage.name}: input {inp.role}: {first.name} and {name} differ in kind or dtype")
                first = first or art
    # No cycles, counting every alternative as an edge.
    state: dict[str, int] = {}

    def visit(name: str, path: tuple[str, ...]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            raise GraphError(f"cycle in the stage graph: {' -> '.join(path + (name,))}")
        state[name] = 1
        for inp in stages[name].inputs:
            for art in inp.one_of:
                visit(producers[art][0].name, path + (name,))
        state[name] = 2

    for name in stages:
        visit(name, ())
    return Graph(stages, producers)


def plan(graph: Graph, enabled: dict[str, bool], wanted: tuple[str, ...], config_name: str = "config") -> list[Step]:
    """The minimal list of steps, in dependency order, that gives `wanted`
    (stage names or artifact names) with the stages `enabled` says run."""
    resolved: dict[str, Step] = {}

    def resolve(stage_name: str, why: str) -> None:
        if stage_name in resolved:
            return
        stage = graph.stages[stage_name]
        if not enabled.get(stage_name, True):
            raise InputError(f"{config_name}: {stage_name}.enabled is false, but {why} needs it")
        chosen = {}
        for inp in stage.inputs:
            pick = next((a for a in inp.one_of if enabled.get(graph.producers[a][0].name, True)), None)
            if pick is None:
                if inp.optional:
                    continue
                raise InputError(f"{config_name}: stage {stage_name} needs {inp.role} from one of "
                                 f"{', '.join(inp.one_of)}, and every producer of it is disabled")
            chosen[inp.role] = pick
        for art in chosen.values():
            resolve(graph.producers[art][0].name, f"stage {stage_name}")
        resolved[stage_name] = Step(stage, chosen)  # after its producers: dependency order

    for want in wanted:
        if want in graph.stages:
            resolve(want, f"outputs = [{want!r}]")
        elif want in graph.producers:
            resolve(graph.producers[want][0].name, f"outputs = [{want!r}]")
        else:
            known = ", ".join(sorted(graph.stages) + sorted(graph.producers))
            raise InputError(f"{config_name}: outputs: {want!r} is neither a stage nor an artifact (known: {known})")
    return list(resolved.values())
