"""Import a USD file into Blender and render one Cycles view:

    .venv-blender/bin/python tests/dcc/blender_scripts/render_view.py SCENE.usd OUT_PREFIX SPEC.json

SPEC: {"camera": {eye, forward, up, ortho_height_m | fov_y_deg} (y up, m, as
worldlib.render.Camera), "width", "height", "samples", optional "sun",
"sun_gain", "sky", "sun_shadows", "transparent_bounces", "threads"}. Writes OUT_PREFIX.exr (linear premultiplied
RGBA), OUT_PREFIX.png and OUT_PREFIX.json (import and render seconds, logs,
peak RSS)."""
from __future__ import annotations

import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bl_common  # noqa: E402


def render_one(src: str, prefix: str, spec: dict) -> None:
    bl_common.reset()
    info = {"import": bl_common.import_usd(os.path.abspath(src))}
    w, h = int(spec["width"]), int(spec["height"])
    bl_common.cycles(w, h, int(spec.get("samples", 16)), int(spec.get("threads", 0)),
                     int(spec.get("transparent_bounces", 0)))
    bl_common.camera(spec["camera"], w, h)
    bl_common.lights(tuple(spec.get("sun", bl_common.SUN)), float(spec.get("sun_gain", bl_common.SUN_GAIN)),
                     float(spec.get("sky", bl_common.SKY)), bool(spec.get("sun_shadows", True)))
    info.update(bl_common.render(prefix))
    bl_common.write_json(prefix + ".json", info)


def main() -> None:
    """SPEC may also hold "jobs": [{"scene", "prefix", and any key of SPEC
    to change}], rendered one after the other in this process (SCENE and
    OUT_PREFIX then name nothing: pass "-")."""
    src, prefix, spec_path = bl_common.args()[:3]
    with open(spec_path) as f:
        spec = json.load(f)
    for job in spec.get("jobs") or [{"scene": src, "prefix": prefix}]:
        render_one(job["scene"], job["prefix"], {**spec, **job})


if __name__ == "__main__":
    main()
