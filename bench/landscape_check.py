"""Read a baked world's landscape tiles back as a level designer's import
would, and check them: every tile the stated size, neighbours sharing their
border vertices bit for bit (float EXR, 16-bit PNG, every weightmap), each
PNG within half a 16-bit step of the float heights over the one stated
range, every weightmap texel summing to 255.

    python -m bench.landscape_check build/worlds/open_world
    python -m bench.landscape_check build/artifacts/landscape/<key>

Prints one line per check and exits 1 when one fails. For worlds too large
to bake in the tests (configs/open_world.toml); tests/stages/landscape
makes the same checks on small worlds."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from pipeline import exr
from stages.landscape import files, tiling


def landscape_folder(world: Path) -> Path:
    """The landscape artifact's folder of a published world (or that folder itself)."""
    if (world / "landscape.json").is_file():
        return world
    manifest = json.loads((world / "manifest.json").read_text())
    for step in manifest["steps"]:
        if step["stage"] == "landscape":
            return world.parent.parent / "artifacts" / "landscape" / step["key"]
    raise SystemExit(f"{world}: no landscape stage in its manifest (add \"landscape\" to outputs)")


def check(folder: Path, index: dict | None = None) -> list[str]:
    """The problems found in the tiles of `folder` (index: its landscape.json)."""
    index = index if index is not None else json.loads((folder / "landscape.json").read_text())
    n, tiles = index["tile_vertices"], index["tile_list"]
    lo, span = index["height_min_m"], index["height_range_m"]
    step = span / 65535
    problems, worst = [], 0.0
    by_place = {tuple(t["tile"]): t for t in tiles}
    grounds = sorted(tiles[0].get("weightmaps", {}))
    cache: dict = {}

    def read(t, what):
        key = (tuple(t["tile"]), what)
        if key not in cache:
            if what == "exr":
                cache[key] = exr.read_grid(folder / t["height_exr"]).data.reshape(n, n)
            elif what == "png":
                cache[key] = files.read_png(folder / t["height_png"])[0]
            else:
                cache[key] = files.read_png(folder / t["weightmaps"][what])[0]
        return cache[key]

    pairs = 0
    for (c, r), t in sorted(by_place.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        h, v = read(t, "exr"), read(t, "png")
        if h.shape != (n, n) or v.shape != (n, n) or v.dtype != np.uint16:
            problems.append(f"tile {c},{r}: {h.shape} {v.shape} {v.dtype}, expected {n} x {n} uint16")
        err = float(np.abs(tiling.decode_heights(v, lo, span) - h).max())
        worst = max(worst, err)
        if err > 0.5 * step * (1 + 1e-6) + 1e-9:
            problems.append(f"tile {c},{r}: 16-bit error {err:.4g} m over half a step {0.5 * step:.4g} m")
        if grounds:
            total = sum(read(t, g).astype(np.int64) for g in grounds)
            if not ((total == 255) | (total == 0)).all():
                problems.append(f"tile {c},{r}: weightmaps sum to {int(total.min())}..{int(total.max())}, not 255")
        if index["share_borders"]:
            for other, side in (((c + 1, r), "right"), ((c, r + 1), "lower")):
                if other not in by_place:
                    continue
                pairs += 1
                for what in ("exr", "png", *grounds):
                    a, b = read(t, what), read(by_place[other], what)
                    edge_a, edge_b = (a[:, -1], b[:, 0]) if side == "right" else (a[-1], b[0])
                    if edge_a.tobytes() != edge_b.tobytes():
                        problems.append(f"tile {c},{r} and its {side} neighbour differ on their shared {what} border")
        for key in [k for k in cache if k[0] == (c, r - 1)]:  # rows above are done: keep memory to two rows
            del cache[key]
    print(f"{len(tiles)} tiles of {n} x {n} vertices ({index['lattice_vertices'][0]} x "
          f"{index['lattice_vertices'][1]} lattice), {pairs} shared borders checked, {len(grounds)} weightmaps a tile")
    print(f"16-bit quantisation: worst {worst:.4g} m, half a step {0.5 * step:.4g} m over {span:.1f} m")
    return problems


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__)
        return 2
    problems = check(landscape_folder(Path(argv[0])))
    for p in problems:
        print("FAIL", p)
    print("ok" if not problems else f"{len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
