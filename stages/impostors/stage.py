"""The impostors stage: for every plant asset the plants stage built for a
placed species (and nothing else), the far LODs a technical artist expects
from Amplify Impostors or UE's ImpostorBaker, baked headless, with their
error against the mesh published.

Per species, in the artifact's textures/:
  <species>_atlas.exr        the (hemi-)octahedral view atlas (atlas.py):
                             frames x frames frames, albedo.RGBA premultiplied
                             linear, normal.XYZ, depth.Z, ao.Y, per-frame mip
                             levels; header: layout, frames, frame size, the
                             bounding sphere, the held-out error
  <species>_atlas_albedo.png sRGB copy of the albedo (straight alpha, padded)
  <species>_slices.exr/.png  slice billboards (slices.py): seed 002's 3
                             vertical orientations and a horizontal one (the
                             views from above) x front/back x N slabs for trees
                             and shrubs, the sheet the Impostor prim draws
                             (drawn_slice_slabs, tiles of twice the frame
                             side, at most drawn_slice_px); for grass seed
                             001's 4 vertical plates (<species>_tuft) and the
                             top slice (<species>_tuft_top); _normal.png: the
                             normals alone, 0..1, for a material
  <species>_blend_slices.exr/.png  trees and shrubs, when slice_slabs or the
                             tiles differ from the drawn sheet's: the sheet of
                             slice_slabs slabs (tiles of half the frame side)
                             for an engine's shader that blends the two
                             slicings nearest the view (seed 002)
  <species>_card_{x,y,z}{pos,neg}.png  the six axis views of USD's cards draw mode
impostors.usda (usd_layer.py): overs on the plants layer's /Plants/<species>
  that the world composes over the prototypes: the `lod` variant set gains
  `impostor`, the Impostor prim (the slice billboards, purpose proxy)
  beside Geom (purpose render), the cards textures, and customData
  worldbake:impostor (atlas, error) and worldbake:lod_switch_m.

Frame size: an impostor is drawn where the plant is small on screen, so
its frames need no more texels than the plant has pixels there: each
plant's frames are its bounding sphere's diameter in pixels at
impostor_distance_m on the reference screen (plant_frame_px; 16 x 16 frames
of 64 px for the default conifer, 48 for the broadleaf, 32 for the shrub),
in the smallest power-of-two atlas that holds them. The held-out views are
that size too (one texel per pixel: the nearest the impostor is used), and
the measured error then sets the switch distances.

Steps (_bake_species per species, then run): read the asset's LOD0 into a render scene
(worldlib.render.usd_asset, the reader every USD picture shares); bake the atlas;
measure it from held-out views (measure.py: heldout.py's views, sampler.py); bake the slices and
measure them the same way, blended as seed 002's shader does (the blend
sheet) and all at once as a USD viewer draws the Impostor prim (its sheet;
the slices' switch distance holds for the worse of the two); render the
cards; derive the switch distances; write the textures (textures.py); write
the layer.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pydantic

from pipeline.contract import Artifact, Check, CheckContext, Input, Param, ParamError, Params, RunContext, Stage
from pipeline.errors import InputError, StageError
from pipeline.limits import leading_key
from pipeline.timing import StepTimes
from worldlib.render import Prepared, Settings
from worldlib.render.usd_asset import load_plant
from worldlib.plant_asset import PLANTS_ROOT, plant_asset_prim

from . import atlas, heldout, measure, slices, textures, usd_layer
from .screen import pixel_at_1m, switch_distance_m

Layout = Literal["hemi", "octahedral"]


class ImpostorsParams(Params):
    frames: int = Param(16, units="frames per side", description="N x N frames of the view atlas", ge=3, le=64)
    atlas_px: int = Param(2048, units="texels", description="side of the largest view atlas (a power of two): frames "
                          "are at most atlas_px / frames texels", ge=64, le=8192)
    impostor_distance_m: float = Param(120.0, units="m", description="the distance from which impostors are meant to "
                                       "be drawn: each plant's frames get the texels that keep one texel per screen "
                                       "pixel there (screen_px, screen_fov_deg), sized 2^k or 3 2^k so their mip "
                                       "levels halve exactly, in the smallest power-of-two atlas that holds them; a "
                                       "plant 20 px tall at that distance gets no 128 px frames", gt=0.0, le=100000.0)
    min_frame_px: int = Param(32, units="texels", description="the smallest frame side", ge=4, le=4096)
    small_plant_m: float = Param(1.0, units="m", description="plants lower than this (grass, flowers) get frames of at "
                                 "least small_plant_frame_px: their stalks and blades are a fraction of a texel at "
                                 "their screen size, and a 3-frame blend of sub-texel features loses them", ge=0.0,
                                 le=1000.0)
    small_plant_frame_px: int = Param(64, units="texels", description="the smallest frame side of plants lower than "
                                      "small_plant_m", ge=4, le=4096)
    layout: Layout = Param("hemi", description="hemi: views from above the horizon only (plants on the ground); "
                           "octahedral: the whole sphere")
    layouts: dict[str, Layout] = Param({}, description="per-species layout overriding `layout`")
    samples: int = Param(3, units="samples per side", description="n x n samples per atlas texel: 2 x 2 gives alpha "
                         "in quarters, and a 0.5 threshold then keeps every half-covered needle; more samples bring "
                         "the held-out IoU closer to the mesh's, with less to gain past 3", ge=1, le=8)
    ao_rays: int = Param(1, units="rays", description="ambient-occlusion rays per sample", ge=0, le=64)
    ao_radius: float = Param(0.08, units="bounding-sphere radii", description="occluders farther than this do not "
                             "darken the ao channel (a whole crown's radius would make every inner leaf black)",
                             gt=0.0, le=4.0)
    padding_px: int = Param(32, units="texels", description="padding of each frame: alpha = 0 texels take the nearest "
                            "covered texel's normal, depth, ao (and colour in the PNG) within this distance, the "
                            "frame's mean beyond", ge=0, le=4096)
    depth_steps: int = Param(2, units="steps", description="parallax steps of the depth-aware blend (0: plane only)",
                             ge=0, le=16)
    slice_slabs: int = Param(3, units="slabs", description="slabs per orientation of the tree slice billboards an "
                             "engine blends by view, the two slicings nearest it (seed 002: 1, 3 or 5; the sheet "
                             "blend_slices when it or its tiles differ from the drawn sheet's)", ge=1, le=16)
    drawn_slice_slabs: int = Param(16, units="slabs", description="slabs per orientation of the tree slice billboards "
                                   "the Impostor prim carries, which a USD viewer or DCC draws all at once (no "
                                   "blend by view): the nearest quad of any slicing shows, so each slab's content "
                                   "must lie near its quad seen from any side, which thin slabs keep; each slab is "
                                   "two quads 1 mm apart, so a ray across the crown crosses several times this "
                                   "many quads of one plant (a DCC's transparent bounces must allow them: the "
                                   "README's advice)", ge=1, le=16)
    slice_px: int = Param(128, units="texels", description="largest side of a tree slice tile: a tile has half the side "
                          "of the plant's atlas frames (slices are the LOD beyond the atlas), at most this",
                          ge=8, le=2048)
    drawn_slice_px: int = Param(128, units="texels", description="largest side of a tile of the sheet the Impostor "
                                "prim carries (drawn_slice_slabs): a tile has twice the side of the plant's atlas "
                                "frames, at most this: a DCC renders at film resolution and does not switch to the "
                                "mesh as its camera comes nearer, so the sheet keeps a texel per pixel at its "
                                "switch distance on a screen 4 x the reference (8K), or at half that distance",
                                ge=8, le=2048)
    grass_slice_px: int = Param(256, units="texels", description="texels per side of a grass tuft slice (seed 001: 256)",
                                ge=8, le=2048)
    card_px: int = Param(256, units="texels", description="largest side of a cards draw-mode texture: the power of two "
                         "at or above the plant's frame side (cards are its farthest stand-in), at most this",
                         ge=8, le=4096)
    heldout_px: int = Param(128, units="pixels", description="largest held-out error view: a view is the size of the "
                            "plant's frames (one atlas texel per pixel, where the impostor is first used), at most "
                            "this", ge=16, le=1024)
    heldout_samples: int = Param(6, units="samples per side", description="n x n samples per pixel of the mesh's "
                                 "held-out views (the reference): its alpha must be the true coverage, not a coarse "
                                 "estimate of it (a coarse reference understates the impostors' IoU; past 6 x 6 it "
                                 "changes little)", ge=1, le=16)
    heldout_stride: int = Param(18, units="views", description="the bake measures 1/stride of the held-out set "
                                "(azimuth every 5 deg x elevation every 10 deg; 36 views of 648 for hemi), every "
                                "elevation equally often, azimuths spread (heldout.lattice; 1: all; "
                                "bench/impostors.py --agreement compares the two)", ge=1, le=648)
    screen_px: int = Param(1080, units="pixels", description="screen height the LOD switch distances are for", ge=16, le=16384)
    screen_fov_deg: float = Param(60.0, units="deg", description="vertical field of view the LOD switch distances are for",
                                  gt=1.0, lt=179.0)
    error_px: float = Param(1.0, units="pixels", description="an LOD is used from the distance where its measured error "
                            "projects to at most this many screen pixels", gt=0.0, le=100.0)

    @pydantic.field_validator("atlas_px")
    @classmethod
    def _power_of_two(cls, v: int) -> int:
        if v & (v - 1):
            raise ValueError(f"atlas_px = {v} must be a power of two (mip levels halve it exactly)")
        return v


def _plant_names(plants_layer: Path, placed: dict | None) -> list[str]:
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(plants_layer))
    root = layer.GetPrimAtPath(PLANTS_ROOT) if layer else None
    names = [c.name for c in root.nameChildren] if root else []
    if placed is not None:
        names = [n for n in names if n in placed.get("placed", [])]
    return sorted(names)


def plant_frame_px(radius: float, height_m: float, params: "ImpostorsParams") -> int:
    """The frame side of a plant: its bounding sphere's diameter in screen
    pixels at impostor_distance_m (one texel per pixel there), as
    atlas.frame_size rounds it, between min_frame_px (small_plant_frame_px
    for plants lower than small_plant_m) and atlas_px / frames."""
    target = 2.0 * radius / (params.impostor_distance_m * pixel_at_1m(params))
    smallest = params.small_plant_frame_px if height_m < params.small_plant_m else params.min_frame_px
    return atlas.frame_size(target, params.frames, params.atlas_px, smallest)


def _polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))


@dataclass(frozen=True)
class _Plant:
    """A species' plant as the bake reads it."""

    name: str
    ps: Any  # worldlib.render.usd_asset.load_plant's: the scene, its bounds and bounding sphere, its parts
    prepared: Prepared  # the scene on the OpenCL device
    layout: Layout
    grass: bool  # a grass tuft (seed 001's slices), not a tree or shrub (seed 002's)
    seed: int

    @property
    def height_m(self) -> float:
        return float(self.ps.hi[1] - self.ps.lo[1])


@dataclass(frozen=True)
class _Slices:
    """The slice billboards: the sheets the Impostor prim draws, the sheets
    an engine blends by view and per slicing row of those (None: the grass
    tuft's quads together) the billboards as a render scene."""

    drawn: list
    blend: list
    billboards: dict
    tile_px: int  # the largest side of a tree's slice tile

    def written(self) -> list:
        """Every distinct sheet, for the textures."""
        return self.drawn + [s for s in self.blend if all(s is not d for d in self.drawn)]


@dataclass(frozen=True)
class _Errors:
    """The held-out error summaries (heldout.summarize) of the atlas, the
    blended slices and the slices as a USD viewer draws them."""

    atlas: dict
    slices: dict
    drawn: dict


def _bake_species(ctx: RunContext, name: str, plants_layer: Path, params: ImpostorsParams, tex_dir: Path) -> dict:
    """One species' impostors, the steps of the module docstring, or its
    earlier bake when neither its plant nor the params changed."""
    t0 = time.perf_counter()
    try:
        ps = load_plant(plants_layer, plant_asset_prim(name))
    except (LookupError, FileNotFoundError) as e:
        raise InputError(f"impostors: {e}") from e
    layout = params.layouts.get(name, params.layout)
    unit = _species_unit(ctx, name, ps, layout, params)
    saved = unit.restore(tex_dir)
    if saved is not None:
        return _from_saved(saved, {"load_s": time.perf_counter() - t0, "total_s": time.perf_counter() - t0})
    plant = _Plant(name, ps, Prepared(ctx.cl, ps.scene), layout, "Blades" in ps.parts,
                   (ctx.seed * 1_000_003 + sum(map(ord, name))) & 0xFFFFFFFF)
    timings = StepTimes(load_s=time.perf_counter() - t0)
    with timings.lap("atlas_s"):
        at = _atlas(plant, params)
        cutout = atlas.cutout_polygon(at.frame_alpha())
    with timings.lap("references_s"):
        views = heldout.held_out(heldout.lattice(layout, params.heldout_stride), at.directions)
        references = measure.References(plant.prepared, ps, views, min(at.frame_px, params.heldout_px),
                                        params.heldout_samples)
    with timings.lap("atlas_error_s"):
        atlas_view = measure.atlas_view(at, references.size, params.depth_steps)
        atlas_errors = heldout.summarize(references.measure(atlas_view), plant.height_m)
    with timings.lap("slices_s"):
        sliced = _slices(ctx, plant, at, params)
    with timings.lap("slices_error_s"):
        errors = _Errors(atlas_errors, *_slice_errors(ctx, plant, sliced, references, params))
    with timings.lap("cards_s"):
        card_px = min(params.card_px, atlas.atlas_side(1, at.frame_px))
        cards = usd_layer.card_views(plant.prepared, ps.lo, ps.hi, card_px, params.samples)
    error_m, switch_m = _switch_distances(plant, at, sliced.tile_px, references.size, errors, params)
    info = _info(plant, params, at, cutout, references, errors, slice_px=sliced.tile_px, card_px=card_px)
    written = textures.write(tex_dir, name, unit.provenance, info, at, sliced.written(), cards)
    timings["total_s"] = time.perf_counter() - t0
    baked = {"name": name, "info": info, "files": written.atlas, "sheets": sliced.drawn, "sheet_files": written.sheets,
             "card_files": written.cards, "lo": ps.lo, "hi": ps.hi, "grass": plant.grass, "switch_m": switch_m,
             "error_m": error_m, "timings": dict(timings), "triangles": int(ps.scene.n_triangles), "reused": False}
    unit.save(tex_dir, written.all(), _to_saved(baked))
    return baked


def _species_unit(ctx: RunContext, name: str, ps, layout: Layout, params: ImpostorsParams):
    """The species' unit of work, keyed by everything its impostors depend on."""
    # a plant that did not change is not baked again when another species' did (the stage's key changes
    # with the whole plants layer)
    return ctx.unit(name, {"plant": ps.scene.digest(), "bounds": [ps.lo.tolist(), ps.hi.tolist()],
                           "parts": ps.parts, "layout": layout,
                           "params": {k: v for k, v in params.model_dump(mode="json").items()
                                      if k not in ("layouts", "enabled")}})


def _atlas(plant: _Plant, params: ImpostorsParams) -> atlas.Atlas:
    """The view atlas, its frames sized by plant_frame_px."""
    ps = plant.ps
    frame_px = plant_frame_px(ps.radius, plant.height_m, params)
    return atlas.build(plant.prepared, ps.centre, ps.radius, params.frames, params.atlas_px, plant.layout,
                       params.samples, params.ao_rays, params.padding_px, plant.seed, ao_radius=params.ao_radius,
                       frame_px=frame_px)


def _slices(ctx: RunContext, plant: _Plant, at: atlas.Atlas, params: ImpostorsParams) -> _Slices:
    """The slice sheets and their billboards on the OpenCL device ctx.cl."""
    slice_px = min(params.slice_px, max(at.frame_px // 2, 8))  # used beyond the atlas: at most half its texels
    if plant.grass:  # seed 001: the tuft's five quads are drawn together
        sheets = [*slices.grass_slices(plant.prepared, params.grass_slice_px, params.samples)]
        return _Slices(sheets, sheets, {None: Prepared(ctx.cl, slices.sheet_scene(sheets))}, slice_px)
    # what a USD viewer draws: every slicing at once, and thick slabs put their content off their quads from
    # oblique views (any view sees two of the three vertical slicings 30 deg or more from face-on)
    drawn_px = min(params.drawn_slice_px, 2 * at.frame_px)
    drawn = [slices.tree_slices(plant.prepared, params.drawn_slice_slabs, drawn_px, params.samples)]
    # seed 002 / Jakulin: the two slicings nearest the view, blended (each seen within 30 deg of face-on), from a
    # sheet of its own when its slabs or tiles differ from the drawn sheet's
    same = params.slice_slabs == params.drawn_slice_slabs and slice_px == drawn_px
    blend = drawn if same else \
        [slices.tree_slices(plant.prepared, params.slice_slabs, slice_px, params.samples, name="blend_slices")]
    return _Slices(drawn, blend, {r: Prepared(ctx.cl, slices.sheet_scene(blend, rows=(r,))) for r in range(blend[0].rows)},
                   slice_px)


def _slice_errors(ctx: RunContext, plant: _Plant, sliced: _Slices, references: measure.References,
                  params: ImpostorsParams) -> tuple[dict, dict]:
    """The slices' held-out errors, blended and as drawn (a grass tuft's are the same)."""
    size = references.size
    view_settings = Settings(size, size, samples=params.heldout_samples)
    blended = measure.blended_slices_view(sliced.billboards, plant.grass, plant.ps, size, view_settings)
    slice_errors = heldout.summarize(references.measure(blended), plant.height_m)
    if plant.grass:
        return slice_errors, slice_errors
    # What a USD viewer draws of the Impostor prim: every quad at once, alpha-tested at 0.5 (the
    # material's opacityThreshold), the nearest wins (so each slab pair shows its viewer's side); no blend.
    drawn = Prepared(ctx.cl, slices.sheet_scene(sliced.drawn))
    drawn_errors = heldout.summarize(references.measure(measure.drawn_view(drawn, plant.ps, view_settings)),
                                     plant.height_m)
    return slice_errors, drawn_errors


def _switch_distances(plant: _Plant, at: atlas.Atlas, slice_px: int, view_px: int, errors: _Errors,
                      params: ImpostorsParams) -> tuple[dict, dict]:
    """The impostors' errors in metres and the distances from which they are
    used (StageError when a held-out error is not finite)."""
    ps = plant.ps
    for summary in (errors.atlas, errors.slices, errors.drawn):
        for key in ("psnr_db", "alpha_iou"):
            if summary.get("views") and not math.isfinite(summary[key]["median"]):
                raise StageError(f"impostors: {plant.name}: the held-out {key} is not finite")
    atlas_error_m = measure.silhouette_error_m(errors.atlas, ps, view_px) if errors.atlas.get("views") else 0.0
    # the slices' distance holds for both ways of drawing them: the worse of the two
    slice_error_m = max((measure.silhouette_error_m(e, ps, view_px) for e in (errors.slices, errors.drawn)
                         if e.get("views")), default=0.0)
    texel_m = 2.0 * ps.radius / at.frame_px
    # an impostor is no sharper than its texels: it is used where they are at most a pixel too
    atlas_switch = switch_distance_m(max(atlas_error_m, texel_m), params)
    slice_switch = max(atlas_switch, switch_distance_m(max(slice_error_m, float((ps.hi - ps.lo).max()) / slice_px), params))
    return ({"impostor": atlas_error_m, "slices": slice_error_m, "atlas_texel": texel_m},
            {"impostor": atlas_switch, "slices": slice_switch})


def _info(plant: _Plant, params: ImpostorsParams, at: atlas.Atlas, cutout: np.ndarray,
          references: measure.References, errors: _Errors, *, slice_px: int, card_px: int) -> dict:
    """The impostor's description (the atlas EXR's header, customData
    worldbake:impostor)."""
    grass = plant.grass
    return {
        "layout": plant.layout, "frames": params.frames, "frame_px": at.frame_px, "atlas_px": at.atlas_px,
        "frame_mip_levels": at.frame_levels, "mip_levels": len(at.levels),
        "bounding_sphere": {"centre_m": [float(v) for v in plant.ps.centre], "radius_m": plant.ps.radius},
        "channels": list(atlas.CHANNELS), "grid": "vertex-centred: frame (i, j) looks from octahedral decode(i/(N-1), j/(N-1))",
        "sampling": "3 frames of the grid triangle, barycentric weights, premultiplied blend, frame-clamped bilinear",
        "depth": "metres from the frame's plane through the sphere centre toward the viewer",
        "held_out": {"views": len(references.views), "size_px": references.size,
                     "reference_samples": params.heldout_samples,
                     "set": "azimuth every 5 deg x elevation every 10 deg (0..80 hemi, -80..80 octahedral)",
                     "stride": params.heldout_stride,
                     "kept": "view (azimuth index i, elevation index e) where (i + 4 e) mod stride = 0"},
        "cutout": {"uv": [[round(float(u), 6), round(float(v), 6)] for u, v in cutout],
                   "area_fraction": round(_polygon_area(cutout), 6),
                   "space": "frame uv, u to the right and v down over one frame (0..1), counter-clockwise in (u, v)",
                   "what": "a convex polygon of at most 8 corners holding every covered texel of every frame (and "
                           "the texels next to them): draw the billboard on it instead of the square"},
        "slice_px": slice_px, "card_px": card_px,
        "frame_px_from": f"the bounding sphere's diameter in pixels at {params.impostor_distance_m} m on a "
                         f"{params.screen_px} px, {params.screen_fov_deg} deg screen",
        "error": errors.atlas, "slices_error": errors.slices, "slices_drawn_error": errors.drawn,
        "slices": {"kind": "grass tuft (seed 001)" if grass else "3 vertical orientations (seed 002) and 1 horizontal x front/back x slabs",
                   "slabs": None if grass else params.slice_slabs,
                   "drawn_slabs": None if grass else params.drawn_slice_slabs,
                   "sheets": "the Impostor prim draws `slices`; an engine that blends the two slicings nearest the "
                   "view reads `blend_slices` (`slices` when the slab counts are equal), rows and columns alike",
                   "error_measured_as": "the five quads together" if grass else
                   "Jakulin's blend of the two vertical slicings nearest the view's azimuth (w = 1 - |delta| / 60 "
                   "deg), handing over to the horizontal slicing from 30 to 60 deg of elevation (smoothstep)",
                   "drawn_error_measured_as": "every quad of the Impostor prim's sheet at once, alpha-tested at 0.5, "
                   "nearest first: what a USD viewer draws of the Impostor prim"},
    }


def _to_saved(baked: dict) -> dict:
    """A species' bake as JSON (what the layer and the stats need of it; the
    sheets' quads without their texels, which are in the files)."""
    out = {k: v for k, v in baked.items() if k not in ("sheets", "lo", "hi", "timings", "reused")}
    out["lo"], out["hi"] = [float(v) for v in baked["lo"]], [float(v) for v in baked["hi"]]
    out["sheets"] = [{"name": sh.name, "rows": sh.rows, "cols": sh.cols, "tile_px": sh.tile_px,
                      "positions": [np.asarray(q, np.float64).tolist() for q in sh.positions],
                      "uvs": [np.asarray(q, np.float64).tolist() for q in sh.uvs], "tiles": [list(t) for t in sh.tiles]}
                     for sh in baked["sheets"]]
    return json.loads(json.dumps(out))  # plain JSON types only


def _from_saved(saved: dict, timings: dict) -> dict:
    baked = dict(saved)
    baked["lo"], baked["hi"] = np.array(saved["lo"]), np.array(saved["hi"])
    baked["sheets"] = [slices.Sheet(sh["name"], sh["rows"], sh["cols"], sh["tile_px"], np.zeros((0, 0, 4), np.float32),
                                    np.zeros((0, 0, 3), np.float32), [np.array(q) for q in sh["positions"]],
                                    [np.array(q) for q in sh["uvs"]], [tuple(t) for t in sh["tiles"]])
                       for sh in saved["sheets"]]
    baked["timings"], baked["reused"] = timings, True
    return baked


def run(ctx: RunContext, inputs: dict[str, Any], params: ImpostorsParams) -> dict[str, Path]:
    plants_layer = inputs.get("plants")
    layer_path = ctx.path("impostors.layer")
    out_dir = Path(ctx.out_dir)
    tex_dir = out_dir / "textures"
    tex_dir.mkdir(exist_ok=True)
    names = _plant_names(plants_layer, inputs.get("placed")) if plants_layer is not None else []
    baked = []
    for k, name in enumerate(names):
        ctx.progress(k / max(len(names), 1), f"impostors: {name}")
        baked.append(_bake_species(ctx, name, plants_layer, params, tex_dir))
        if baked[-1]["reused"]:
            ctx.progress((k + 1) / max(len(names), 1), f"impostors: {name} unchanged, its impostors reused")
    stats = usd_layer.write(layer_path, ctx.provenance, baked, plants_layer, params)
    errors = []
    if baked:
        from pipeline import usdio

        errors = usdio.validate(layer_path)
    if errors:
        raise StageError("impostors: the layer fails USD validation: " + "; ".join(errors[:10]))
    species = {b["name"]: {"error": b["info"]["error"], "slices_error": b["info"]["slices_error"],
                           "slices_drawn_error": b["info"]["slices_drawn_error"],
                           "switch_m": b["switch_m"], "lod_switch_m": stats["lod_switch_m"].get(b["name"]),
                           "error_m": b["error_m"], "seconds": b["timings"], "triangles": b["triangles"],
                           "frame_px": b["info"]["frame_px"], "layout": b["info"]["layout"],
                           "reused": b["reused"]} for b in baked}
    ctx.metrics.update({"species": species, "built": names,
                        "seconds": float(sum(b["timings"]["total_s"] for b in baked))})
    ctx.progress(1.0, "impostors: done")
    content = {n: {k: v for k, v in s.items() if k not in ("seconds", "reused")} for n, s in species.items()}
    return {"impostors.layer": layer_path, "impostors.stats": {"species": content, "built": names}}  # run facts: metrics


MAX_RAYS = 1e10  # rays traced per species (the defaults: about 1e8)


def check(params: ImpostorsParams, ctx: CheckContext) -> Check:
    """The atlas levels held at once: 9 float32 channels, 4/3 for the mips,
    about 3x for the padding's distance transform; per species, one at a time.
    Work, in rays per species (a species at a time): the largest atlas's
    texels times samples^2 times (1 + ao_rays), and the held-out views'
    pixels times heldout_samples^2 (the mesh's reference), at most MAX_RAYS."""
    side = params.atlas_px
    if side // params.frames < 4:
        raise ParamError("frames", f"{params.frames} frames leave {side // params.frames} texels per frame in "
                         f"atlas_px = {side}; at least 4 are needed")
    texels = params.atlas_px ** 2
    atlas_rays = texels * params.samples ** 2 * (1 + params.ao_rays)
    views = max(len(heldout.lattice(layout, params.heldout_stride))
                for layout in {params.layout, *params.layouts.values()})
    heldout_rays = views * params.heldout_px ** 2 * params.heldout_samples ** 2
    return Check(memory_bytes=texels * 9 * 4 * 4.0, memory_how=f"atlas_px = {params.atlas_px}: {texels:,} texels x "
                 "9 channels x 4 B x (mips and padding)",
                 work=atlas_rays + heldout_rays, work_unit="rays per species", work_limit=MAX_RAYS,
                 work_how=f"{texels:,} atlas texels x {params.samples}^2 samples x (1 + {params.ao_rays} ao_rays) + "
                 f"{views} held-out views x {params.heldout_px}^2 pixels x {params.heldout_samples}^2 heldout_samples",
                 work_key=leading_key(params, grows=("atlas_px", "samples", "ao_rays", "heldout_px", "heldout_samples"),
                                      shrinks=("heldout_stride",)))


STAGE = Stage(
    name="impostors",
    version=1,
    description="impostors of every placed plant: (hemi-)octahedral view atlases, slice billboards, cards textures, "
    "the error against the mesh from held-out views, LOD switch distances",
    inputs=(Input("plants", one_of=("plants.assets",), optional=True, description="the plant assets (plants.usda)"),
            Input("placed", one_of=("vegetation.placed",), optional=True,
                  description="the species the vegetation map placed; only those get impostors")),
    outputs=(Artifact("impostors.layer", kind="usd", file="impostors.usda", shape="any",
                      beside=("textures/*.exr", "textures/*.png"),
                      description="overs on /Plants/<species>: lod variant `impostor`, the Impostor prim (slice "
                      "billboards, purpose proxy) beside Geom (purpose render), cards textures, customData "
                      "worldbake:impostor (atlas, held-out error) and worldbake:lod_switch_m; the textures beside"),
             Artifact("impostors.stats", kind="json", file="stats.json", shape="any",
                      description="per species: held-out error of the atlas and the slices (median, worst view), "
                      "switch distances (bake seconds and reuse are metrics)")),
    params=ImpostorsParams,
    run=run,
    check=check,
    source_dir=Path(__file__).parent,
    uses_seed=True,
    uses_opencl=True,
)
