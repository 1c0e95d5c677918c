"""One species from its shape to a measured LOD chain.

    L-system -> string -> turtle skeleton -> pipe-model radii -> tubes (kernel)
    -> manifold3d union -> collapse of 1e-10 m slivers -> checked solid
    leaves (kernel) + polygons;  grass: blades (kernel)
    LOD k: wood by quadric edge collapse to <= ratio x LOD k-1 triangles,
           foliage by card / nested thinning, grass by fewer segments, last the slice tuft;
           error = symmetric Hausdorff distance to LOD0 / LOD0's bounding-box diagonal.
"""
from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.errors import InputError, StageError

from . import cards, grass, leaves, lod, mesh
from .lsystem import compile_lsystem
from .mesh import Part
from .turtle import interpret, path_length, pipe_radii


@dataclass
class Settings:
    lod_count: int = 4
    lod_ratio: float = 0.5
    max_modules: int = 1_000_000
    min_radius: float = 0.0005
    hausdorff_samples: int = 20000
    leaf_area_compensation: float = 1.0
    lod_error_budget: tuple[float, ...] = (0.01, 0.03)
    use_opencl: bool = True
    check_lods: bool = True
    # the OpenCL device (pipeline.opencl.CL; the stage's ctx.cl) the renders run on, and the vertex
    # kernels when use_opencl; pickled to a worker process, it opens the same device there
    cl: Any = None

    @property
    def vertex_env(self):
        """The device of the vertex kernels: None runs their numpy references."""
        return self.cl if self.use_opencl else None


@dataclass
class PlantResult:
    name: str
    lods: list[dict[str, Part]]
    lod_info: list[dict]
    metrics: dict = field(default_factory=dict)
    cards: "cards.CardBake | None" = None  # the foliage card texture the Leaves carry
    bark: "np.ndarray | None" = None  # the bark albedo, once written (renders of the plant use it)
    slices: "cards.SliceBake | None" = None  # the grass slice tuft's atlas


def species_seeds(world_seed: int, name: str, n: int = 6) -> list[int]:
    """Independent 32-bit seeds for the parts of one species (L-system,
    turtle, leaves, wind phases, grass ...), from the world seed and the name."""
    ss = np.random.SeedSequence([int(world_seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])
    return [int(x) for x in ss.generate_state(n)]


def _combined(parts: dict[str, Part]) -> tuple[np.ndarray, np.ndarray]:
    return Part.concat([p for p in parts.values() if p.n_tris]).welded()


def build_plant(name: str, spec, world_seed: int, cfg: Settings, progress=None) -> PlantResult:
    seeds = species_seeds(world_seed, name)
    t_all = time.perf_counter()
    m: dict = {"kind": spec.kind, "name": name}
    if spec.kind == "grass":
        res = _build_grass(name, spec, seeds, cfg, m)
    else:
        res = _build_lsystem(name, spec, seeds, cfg, m, progress)
    m["seconds_total"] = time.perf_counter() - t_all
    res.metrics = m
    return res


def _measure(name, lods, cfg, m, times, known=None):
    """Hausdorff error of every level against LOD0, and the LOD table."""
    ref = _combined(lods[0])
    diag = lod.bbox_diagonal(ref[0])
    info = []
    for k, parts in enumerate(lods):
        tris = int(sum(p.n_tris for p in parts.values()))
        entry = {"level": k, "triangles": tris, "parts": {pn: int(p.n_tris) for pn, p in parts.items()}}
        if k == 0:
            entry.update(hausdorff_m=0.0, hausdorff_fraction=0.0)
        else:
            t = time.perf_counter()
            h = known[k] if known and known[k] is not None else lod.hausdorff(ref, _combined(parts), cfg.hausdorff_samples)
            entry.update(hausdorff_m=h["max"], hausdorff_fraction=h["max"] / max(diag, 1e-12), hausdorff_mean_m=h["mean"])
        info.append(entry)
    m["bbox_diagonal_m"] = diag
    m["lods"] = [dict(e, simplify_seconds=float(times[e["level"]])) for e in info]
    return info


def _build_lsystem(name, spec, seeds, cfg: Settings, m: dict, progress) -> PlantResult:
    ls = spec.lsystem
    t = time.perf_counter()
    system = compile_lsystem(ls, name)
    string = system.derive(ls.iterations, seeds[0], cfg.max_modules)
    m["modules"] = len(string)
    m["seconds_lsystem"] = time.perf_counter() - t

    t = time.perf_counter()
    sk = interpret(string, spec, seeds[1])
    if spec.wood.radius_model == "pipe":
        radius = pipe_radii(sk, spec.wood.tip_radius, spec.wood.pipe_exponent, spec.wood.leaf_weight)
    else:
        radius = sk.radius.copy()
    m["segments"] = sk.n_segments
    m["leaves"] = sk.n_leaves
    m["polygons"] = len(sk.polygons)
    m["seconds_turtle"] = time.perf_counter() - t
    if progress:
        progress(0.2, f"{name}: {sk.n_segments} segments, {sk.n_leaves} leaves")

    # wood
    t = time.perf_counter()
    tubes = mesh.build_tubes(sk, radius, spec.wood, cfg.min_radius, np.random.default_rng(seeds[2]))
    parts = mesh.tube_parts(cfg.vertex_env, tubes, spec.wood.cap_bulge)
    m["tubes"] = tubes.n_tubes
    m["segments_too_thin"] = int((radius < cfg.min_radius).sum()) if len(radius) else 0
    m["tube_triangles"] = int(sum(p.n_tris for p in parts))
    m["seconds_tubes"] = time.perf_counter() - t
    t = time.perf_counter()
    wood, uinfo = mesh.union(parts)
    diag0 = lod.bbox_diagonal(np.concatenate([sk.p0, sk.p1, sk.leaf_pos]) if sk.n_segments or sk.n_leaves else np.zeros((0, 3)))
    wood, collapsed = mesh.collapse_short_edges(wood, max(1e-7, 1e-6 * diag0))
    wood, flips = mesh.flip_needles(wood, max(1e-6, 2e-7 * diag0))
    m["union_needles_flipped"] = flips
    wood, fixed = mesh.fix_corner_normals(wood)
    m["union_corner_normals_fixed"] = fixed
    m["seconds_union"] = time.perf_counter() - t
    m["union"] = uinfo
    m["union_positions_collapsed"] = collapsed
    solid = mesh.check_solid(wood)
    m["wood_check"] = solid
    _require_solid(name, 0, solid)

    # leaves
    t = time.perf_counter()
    start_len, end_len = path_length(sk)
    bw_seg = np.clip(end_len / max(float(end_len.max()) if len(end_len) else 1.0, 1e-9), 0, 1) ** 1.5
    bake = None
    leaf_spec = spec.leaf
    if spec.foliage.cards and spec.leaf.shape != "none":
        t_cards = time.perf_counter()
        bake = cards.bake(cfg.cl, spec, seeds[3])
        tmpl = bake.template
        card_len = float(np.ptp(tmpl.rows[:, 1]))
        # a card droops over its own length as a leaf does over its blade
        leaf_spec = spec.leaf.model_copy(update={"length": card_len, "petiole": 0.0})
        m["seconds_foliage_textures"] = time.perf_counter() - t_cards
        m["card_coverage"] = bake.coverage
        m["card_cluster_triangles"] = bake.cluster_triangles
    else:
        tmpl = leaves.make_template(spec.leaf)
    rec = leaves.leaf_records(sk, leaf_spec, bw_seg, np.random.default_rng(seeds[3])) if tmpl is not None else None
    leaf0 = leaves.instance(cfg.vertex_env, tmpl, rec) if tmpl is not None and len(rec) else Part.empty()
    polys = leaves.polygon_part(sk, bw_seg)
    m["seconds_leaves"] = time.perf_counter() - t
    m["wood_lod_checks"] = []

    if wood.n_tris == 0 and leaf0.n_tris == 0 and polys.n_tris == 0:
        raise InputError(
            f"species {name!r} produced no geometry: {len(string)} modules after {ls.iterations} iterations gave "
            f"{sk.n_segments} segments ({m['segments_too_thin']} thinner than plants.min_radius = {cfg.min_radius} m), "
            f"{sk.n_leaves} leaves and {len(sk.polygons)} polygons")

    lods = [{"Wood": wood, "Leaves": Part.concat([leaf0, polys])}]
    times = [0.0]
    chosen, errors = _lod_chain(wood, tmpl, rec, polys, lods, times, cfg, seeds, m)
    m["lod_choices"] = chosen
    t = time.perf_counter()
    info = _measure(name, lods, cfg, m, times, errors)
    m["seconds_measure"] = time.perf_counter() - t
    return PlantResult(name, lods, info, cards=bake)


def _require_solid(name: str, level: int, c: dict) -> None:
    """The woody part must be one closed, oriented, non-degenerate solid (the
    voxelizer and the impostor baker rely on it): otherwise the stage fails."""
    if c["triangles"] and not (c["watertight"] and c["manifold"] and c["winding_consistent"] and c["degenerate"] == 0):
        raise StageError(f"plants: species {name!r} LOD{level}: the woody mesh is not a clean solid "
                         f"(watertight {c['watertight']}, manifold {c['manifold']}, winding consistent "
                         f"{c['winding_consistent']}, degenerate triangles {c['degenerate']})")


def _lod_chain(wood, tmpl, rec, polys, lods, times, cfg: Settings, seeds, m) -> tuple[list[dict], list]:
    """Levels 1..n-1. Each level gets at most lod_ratio x the triangles of the
    level before, split between wood (quadric edge collapse from LOD0, never
    more triangles than the level before) and foliage (the template, its
    card, or a nested subset of cards; never more than the level before).
    The splits are tried from the most foliage kept to the least (at most
    three): the first whose Hausdorff error is within half the level's budget
    is taken, else the one with the smallest error. A level that cannot be
    made (a solid cannot get that small) ends the chain."""
    ref = _combined(lods[0])
    n_leaves = len(rec) if rec is not None else 0
    fol = _Foliage(tmpl, rec, n_leaves, tmpl.n_tris if tmpl is not None else 0,
                   leaves.card_of(tmpl) if tmpl is not None else None,
                   np.random.default_rng(seeds[4]).permutation(n_leaves) if n_leaves else None)
    wood_at = _WoodDecimation(wood)
    W0 = wood.n_tris
    w_min = min(W0, max(64, int(0.02 * W0)))
    prev_total = sum(p.n_tris for p in lods[0].values())
    prev_card, prev_keep = False, 1.0
    prev_wood = W0
    poly = polys
    errors = [None]
    choices = []
    for k in range(1, cfg.lod_count):
        t0 = time.perf_counter()
        budget = int(np.floor(cfg.lod_ratio * prev_total))
        options = _foliage_options(fol, prev_card, prev_keep, cfg.lod_ratio)
        feasible = []
        while True:  # Lparser polygons stay as long as the budget allows, then are thinned
            feasible = _feasible(options, budget, poly.n_tris, W0, w_min, prev_wood)
            if feasible or poly.n_tris == 0:
                break
            poly = _thin_part(poly, cfg.lod_ratio)
        if not feasible:  # the wood cannot get small enough: give it what is left, no foliage
            feasible = [(True, 0.0, max(budget - poly.n_tris, 4))]
        best = _best_split(k, feasible, budget, ref, wood_at, fol, poly, cfg)
        if best is None:  # nothing this small keeps the solid closed: the chain ends here
            m["lod_chain_stopped"] = f"no LOD{k} within {budget} triangles"
            break
        h, use_card, keep, parts, total, wt = best
        errors.append(h)
        lods.append(parts)
        times.append(time.perf_counter() - t0)
        choices.append({"level": k, "budget": budget, "wood_target": int(wt), "foliage_card": bool(use_card),
                        "foliage_keep": float(keep), "candidates": len(feasible)})
        prev_total, prev_card, prev_keep = total, use_card or prev_card, keep
        prev_wood = parts["Wood"].n_tris
        if cfg.check_lods and parts["Wood"].n_tris:
            _check_wood_lod(parts["Wood"], k, m)
    return choices, errors


@dataclass(frozen=True)
class _Foliage:
    """LOD0's leaves as the chain thins them."""
    template: Any  # the leaf template Part, or None
    records: Any  # the leaf instances (leaves.subset's input), or None
    count: int  # leaves at LOD0
    template_tris: int
    card: Any  # the template's card Part, or None
    rank: Any  # the order leaves are dropped in (a seeded permutation), or None


class _WoodDecimation:
    """wood_at(target): the wood decimated from LOD0 to at most `target` triangles, each target once."""

    def __init__(self, wood):
        self.wood = wood
        self.cache: dict[int, tuple] = {}

    def __call__(self, target: int):
        wood, dec_cache = self.wood, self.cache
        if target >= wood.n_tris:
            return wood
        if target not in dec_cache:
            # Quadric collapse from LOD0 follows one order whatever the
            # target and stops at the first mesh of at most `target`
            # triangles: a decimation to a larger target that already ended
            # at <= target triangles is that same mesh (no need to redo it).
            # Only a first decimation (not the 0.9 x retry) qualifies.
            same = [w for t, (w, first) in dec_cache.items() if first and t >= target and w.n_tris <= target]
            if same:
                dec_cache[target] = (min(same, key=lambda w: w.n_tris), True)
            else:
                w = lod.decimate(wood, target)
                first = w.n_tris <= target
                if not first:
                    w = lod.decimate(wood, max(int(target * 0.9), 4))
                dec_cache[target] = (w, first)
        return dec_cache[target][0]


def _foliage_options(fol: _Foliage, prev_card: bool, prev_keep: float, lod_ratio: float) -> list:
    """(use_card, keep, foliage triangles) a level may take, the most foliage first."""
    n_leaves, t_leaf, card = fol.count, fol.template_tris, fol.card
    options = []
    if not n_leaves:
        options.append((False, 1.0, 0))
        return options
    if not prev_card and prev_keep >= 1.0:
        options.append((False, 1.0, n_leaves * t_leaf))
    keep = prev_keep
    while keep * n_leaves >= 1:
        nk = int(np.floor(keep * n_leaves))
        if card.n_tris < t_leaf or prev_card:
            options.append((True, keep, nk * card.n_tris))
        elif keep < prev_keep:
            options.append((False, keep, nk * t_leaf))
        keep *= lod_ratio
    options.append((True, 0.0, 0))
    return options


def _best_split(k: int, feasible: list, budget: int, ref, wood_at: _WoodDecimation, fol: _Foliage, poly,
                cfg: Settings):
    """(hausdorff, use_card, keep, parts, triangles, wood target) of the first
    split within half the level's error budget, else of the smallest error;
    None when no split fits the budget."""
    best = None
    diag = lod.bbox_diagonal(ref[0])
    budgets = cfg.lod_error_budget
    good_enough = 0.5 * (budgets[min(k, len(budgets)) - 1] if budgets else 0.01) * diag
    for use_card, keep, wt in feasible:
        wk = wood_at(wt) if wood_at.wood.n_tris else wood_at.wood
        if fol.count and keep > 0:
            rk = leaves.subset(fol.records, keep, fol.rank, cfg.leaf_area_compensation)
            fk = leaves.instance(cfg.vertex_env, fol.card if use_card else fol.template, rk)
        else:
            fk = Part.empty()
        parts = {"Wood": wk, "Leaves": Part.concat([fk, poly])}
        total = sum(p.n_tris for p in parts.values())
        if total > budget:
            continue
        h = lod.hausdorff(ref, _combined(parts), cfg.hausdorff_samples)
        if best is None or h["max"] < best[0]["max"]:
            best = (h, use_card, keep, parts, total, wt)
        if h["max"] <= good_enough:
            break  # the split that keeps the most foliage is good enough
    return best


def _check_wood_lod(wood_lod, k: int, m: dict) -> None:
    c = mesh.check_solid(wood_lod)
    _require_solid(m.get("name", "?"), k, c)
    m["wood_lod_checks"].append({"level": k, "watertight": c["watertight"], "manifold": c["manifold"],
                                 "degenerate": c["degenerate"], "winding_consistent": c["winding_consistent"]})


def _feasible(options, budget, poly_tris, W0, w_min, prev_wood):
    """The first three (use_card, keep, wood target) splits that fit the budget."""
    out = []
    for use_card, keep, ft in options:
        wt = budget - ft - poly_tris
        if W0 == 0:
            if wt >= 0:
                out.append((use_card, keep, 0))
        elif wt >= w_min:
            out.append((use_card, keep, min(wt, prev_wood)))  # the wood never grows back
        if len(out) == 3:
            break
    return out


def _thin_part(p: Part, ratio: float) -> Part:
    """The first `ratio` share of the triangles (whole polygons mostly): a
    crude thinning for the rare Lparser polygon leaves."""
    keep_n = int(np.floor(ratio * p.n_tris))
    tris = p.tris[:keep_n]
    used = np.unique(tris)
    remap = np.full(len(p.verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    return Part(p.verts[used], remap[tris], np.arange(len(used), dtype=np.int64))


def _build_grass(name, spec, seeds, cfg: Settings, m: dict) -> PlantResult:
    g = spec.grass
    t = time.perf_counter()
    rec = grass.blade_records(g, np.random.default_rng(seeds[5]))
    b0 = grass.blades(cfg.vertex_env, rec, g.segments, g.taper)
    m["blades"] = len(rec)
    m["seconds_blades"] = time.perf_counter() - t
    lods = [{"Blades": b0}]
    times = [0.0]
    plan = grass.grass_plan(g.segments, cfg.lod_count, cfg.lod_ratio)
    for kind, n, keep in plan[1:]:
        t = time.perf_counter()
        if kind == "cards":
            cards = grass.slice_cards(rec)
            if cards.n_tris > cfg.lod_ratio * sum(p.n_tris for p in lods[-1].values()):
                m["lod_chain_stopped"] = "the slice tuft would not halve the triangles"
                break
            lods.append({"Cards": cards})
        else:
            sub = rec[: max(1, int(np.floor(keep * len(rec))))]
            part = grass.blades(cfg.vertex_env, sub, n, g.taper)
            if part.n_tris > cfg.lod_ratio * sum(p.n_tris for p in lods[-1].values()):
                m["lod_chain_stopped"] = "fewer blade triangles are not possible"
                break
            lods.append({"Blades": part})
        times.append(time.perf_counter() - t)
    m["lod_plan"] = [list(p) for p in plan]
    slices = None
    card_parts = [p["Cards"] for p in lods if "Cards" in p]
    if card_parts:
        from . import measure  # the blades as a render scene, coloured as measure renders them
        from .cards import bake_grass_slices

        t = time.perf_counter()
        slices = bake_grass_slices(cfg.cl, measure.plant_scene({"Blades": b0}, spec, None, None), card_parts[0], seed=seeds[5] & 0xFFFF)
        m["seconds_foliage_textures"] = time.perf_counter() - t
    t = time.perf_counter()
    info = _measure(name, lods, cfg, m, times)
    m["seconds_measure"] = time.perf_counter() - t
    return PlantResult(name, lods, info, slices=slices)
