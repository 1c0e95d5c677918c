"""Are two baked worlds the same world, whatever their keys?

    python -m bench.same_world BUILD_A WORLD_A BUILD_B WORLD_B [--all]

For a refactor that may change keys but not content: every EXR the two
worlds use (matched by stage and path inside the artifact) has equal pixels
in every subimage and MIP level, every PNG equal pixels, and the composed
`world.usda` (payloads loaded, flattened) is the same text once artifact
keys and provenance are masked. Prints what differs; exit 1 when anything does.
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np

KEY = re.compile(r"\b[0-9a-f]{20}\b")


def _uses(build: Path, world: str) -> dict[str, Path]:
    manifest = json.loads((build / "worlds" / world / "manifest.json").read_text())
    return {e["stage"]: build / "artifacts" / e["stage"] / e["key"] for e in manifest["artifacts"]}


def _pixels(path: Path) -> list[np.ndarray]:
    import OpenImageIO as oiio

    out, inp = [], oiio.ImageInput.open(str(path))
    try:
        sub = 0
        while inp.seek_subimage(sub, 0):
            mip = 0
            while inp.seek_subimage(sub, mip):
                out.append(np.asarray(inp.read_image(sub, mip, 0, -1, oiio.UNKNOWN)))
                mip += 1
            sub += 1
    finally:
        inp.close()
    return out


def _same_pixels(a: Path, b: Path) -> bool:
    pa, pb = _pixels(a), _pixels(b)
    return len(pa) == len(pb) and all(x.shape == y.shape and x.dtype == y.dtype and
                                      np.array_equal(x, y, equal_nan=True) for x, y in zip(pa, pb))


def _digest(value, h) -> None:
    """Feed a value into a hash: numeric arrays by their bytes, anything
    else by its repr with artifact keys masked (asset paths name keys)."""
    try:
        array = np.asarray(value)
    except Exception:
        array = None
    if array is not None and array.dtype.kind in "biuf" and array.ndim > 0:
        h.update(str(array.shape).encode() + array.dtype.str.encode())
        h.update(np.ascontiguousarray(array).tobytes())
    else:
        h.update(KEY.sub("KEY", repr(_plain(value))).encode())


def _plain(value):
    """A value without what only locates it: asset paths as authored (not
    resolved into one build folder or another), list ops by their items
    (their repr is an address)."""
    from pxr import Sdf

    if isinstance(value, Sdf.AssetPath):
        return ("asset", value.path)
    if hasattr(value, "GetAddedOrExplicitItems"):
        return ("listop", [_plain(v) for v in value.GetAddedOrExplicitItems()])
    if isinstance(value, dict):
        return sorted((k, _plain(v)) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "__len__") and type(value).__name__.endswith("Array") and len(value) and \
            isinstance(value[0], Sdf.AssetPath):
        return [_plain(v) for v in value]
    return value


def _composed(build: Path, world: str) -> dict[str, str]:
    """Per prim of the composed world (payloads loaded, instances walked as
    proxies so no prototype naming enters): a digest of its type, metadata,
    attribute values and relationship targets, artifact keys masked. Layer
    metadata (provenance) is not composed content and is left out."""
    import hashlib

    from pxr import Usd

    stage = Usd.Stage.Open(str(build / "worlds" / world / "world.usda"), Usd.Stage.LoadAll)
    out = {}
    for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        h = hashlib.sha256()
        meta = {k: v for k, v in prim.GetAllAuthoredMetadata().items()
                if k not in ("specifier", "references", "payload", "inheritPaths", "variantSetNames", "instanceable")}
        _digest((str(prim.GetTypeName()), sorted(meta.items())), h)
        for attr in prim.GetAttributes():
            h.update(attr.GetName().encode())
            samples = attr.GetTimeSamples()
            for value in ([attr.Get(s) for s in samples] if samples else [attr.Get()]):
                _digest(value, h)
        for rel in prim.GetRelationships():
            _digest((rel.GetName(), [str(target) for target in rel.GetTargets()]), h)
        out[str(prim.GetPath())] = h.hexdigest()
    return out


def compare(build_a: Path, world_a: str, build_b: Path, world_b: str) -> list[str]:
    uses_a, uses_b = _uses(build_a, world_a), _uses(build_b, world_b)
    problems = [f"stage {s} is used by one world only" for s in sorted(set(uses_a) ^ set(uses_b))]
    counted = 0
    for stage in sorted(set(uses_a) & set(uses_b)):
        fa = {p.relative_to(uses_a[stage]).as_posix() for p in uses_a[stage].rglob("*") if p.is_file()}
        fb = {p.relative_to(uses_b[stage]).as_posix() for p in uses_b[stage].rglob("*") if p.is_file()}
        problems += [f"{stage}/{f}: in one world only" for f in sorted(fa ^ fb)]
        for rel in sorted(fa & fb):
            if rel.endswith((".exr", ".png")):
                counted += 1
                if not _same_pixels(uses_a[stage] / rel, uses_b[stage] / rel):
                    problems.append(f"{stage}/{rel}: pixels differ")
    ca, cb = _composed(build_a, world_a), _composed(build_b, world_b)
    problems += [f"prim {p}: in one world only" for p in sorted(set(ca) ^ set(cb))]
    problems += [f"prim {p}: differs" for p in sorted(set(ca) & set(cb)) if ca[p] != cb[p]]
    print(f"{counted} images compared, composed world: {len(ca)} prims", file=sys.stderr)
    return problems


def main(argv: list[str]) -> int:
    show_all = "--all" in argv
    argv = [a for a in argv if a != "--all"]
    if len(argv) != 4:
        print(__doc__, file=sys.stderr)
        return 2
    problems = compare(Path(argv[0]), argv[1], Path(argv[2]), argv[3])
    for p in problems if show_all else problems[:60]:
        print(p)
    if len(problems) > 60 and not show_all:
        print(f"... and {len(problems) - 60} more")
    print("same world" if not problems else f"{len(problems)} differences")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
