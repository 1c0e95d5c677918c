"""Writing a species' textures into the artifact's textures/ (images.py's
writers): the view atlas (EXR with its mips, sRGB PNG of the albedo), each
slice sheet (layered EXR, PNG, the normal alone) and the six cards views.

The layered EXRs (atlas, sheets) are an engine's data: their normal.XYZ hold
signed unit normals. The sheet's `_normal.png`, the one file a material's
normal input reads, holds them 0.5 n + 0.5 as the UsdPreviewSurface spec's
normal maps do (worldlib.materials.encode_normal), in 8 bits as the ground's
detail normals are: a DCC holds a half-float EXR as 16 bytes a texel, an
8-bit PNG as 4 (whose steps tilt a normal by at most half a degree)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from worldlib import images as worldlib_images
from worldlib import materials

from . import atlas, images


@dataclass(frozen=True)
class Written:
    """The file names written (relative to textures/)."""

    atlas: dict[str, str]  # "atlas" (the EXR), "atlas_png"
    sheets: dict[str, dict[str, str]]  # per sheet name: "albedo" (PNG), "exr", "normal"
    cards: dict[str, str]  # per axis (xpos, xneg, ...): the PNG

    def all(self) -> list[str]:
        return [*self.atlas.values(), *(f for v in self.sheets.values() for f in v.values()), *self.cards.values()]


def write(tex_dir: Path, name: str, provenance: dict, info: dict, at: atlas.Atlas, sheets: list, cards: dict) -> Written:
    """The textures of species `name`; `provenance` (the unit's) and `info`
    (the impostor's description) go into the EXR headers."""
    files = {"atlas": f"{name}_atlas.exr", "atlas_png": f"{name}_atlas_albedo.png"}
    attrs = {**provenance, "species": name, "impostor": info}
    images.write_exr(tex_dir / files["atlas"], at.levels, atlas.CHANNELS, attrs, float_channels=("depth.Z",))
    worldlib_images.write_png(tex_dir / files["atlas_png"], at.straight_rgb, at.levels[0][..., 3])
    sheet_files = {sheet.name: _write_sheet(tex_dir, name, provenance, sheet) for sheet in sheets}
    card_files = {}
    for axis, (rgb, alpha) in cards.items():
        card_files[axis] = f"{name}_card_{axis}.png"
        worldlib_images.write_png(tex_dir / card_files[axis], rgb, alpha)
    return Written(files, sheet_files, card_files)


def _write_sheet(tex_dir: Path, name: str, provenance: dict, sheet) -> dict[str, str]:
    stem = f"{name}_{sheet.name}"
    images.write_exr(tex_dir / f"{stem}.exr", [np.concatenate([sheet.rgba, sheet.normal], -1)],
                     ("albedo.R", "albedo.G", "albedo.B", "albedo.A", "normal.X", "normal.Y", "normal.Z"),
                     {**provenance, "species": name, "tiles": {"rows": sheet.rows, "cols": sheet.cols,
                                                               "tile_px": sheet.tile_px}})
    worldlib_images.write_png(tex_dir / f"{stem}.png", sheet.rgba[..., :3], sheet.rgba[..., 3])
    # the material's normal input reads R, G, B: the normal alone, not the layered file's first channels, stored
    # 0..1 as the spec's normal maps are (its UsdUVTexture decodes with scale 2, bias -1)
    worldlib_images.write_png(tex_dir / f"{stem}_normal.png", materials.encode_normal(sheet.normal), srgb=False)
    return {"albedo": f"{stem}.png", "exr": f"{stem}.exr", "normal": f"{stem}_normal.png"}
