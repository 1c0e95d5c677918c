"""`worldbake diff A B`: what differs between two worlds, for people and CI.

A and B are world names (build/worlds/<name>/), world folders, or a saved
world manifest.json (kept from an earlier bake, e.g. by CI). The diff says
- which parameters differ (stage params, seed, outputs, overrides);
- which stages' keys differ (the stages that re-ran between the two);
- for each artifact file whose bytes differ (when both runs are in the
  store): images (EXR by channel name, PNG): the share of pixels changed,
  the largest and the RMS difference per channel; USD layers: prims added,
  removed and changed, and instance counts of the PointInstancers; JSON:
  the top-level keys whose values differ.
Equal means no parameter differs and every artifact file has the same
bytes (keys may differ, e.g. on another OpenCL device, while the files
agree); `worldbake diff` exits 0 then and 1 otherwise.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .store import MANIFEST, Store

MAX_LISTED = 20  # prim paths listed per kind of change


def _load(store: Store, ref: str) -> tuple[str, dict]:
    path = Path(ref)
    for candidate in (store.worlds / ref / MANIFEST, path / MANIFEST, path):
        if candidate.is_file():
            try:
                manifest = json.loads(candidate.read_text())
            except (OSError, ValueError) as e:
                raise InputError(f"{candidate}: not a world manifest: {e}") from None
            if not isinstance(manifest, dict) or "artifacts" not in manifest:
                raise InputError(f"{candidate}: not a world manifest (no 'artifacts')")
            return str(candidate), manifest
    raise InputError(f"{ref}: no world of that name in {store.worlds}, nor a world folder or manifest.json")


def _params(store: Store, manifest: dict) -> dict[str, Any]:
    """Flat parameters of a world: stage.key -> value, plus seed and outputs."""
    per_stage = dict(manifest.get("params") or {})
    for entry in manifest["artifacts"]:  # older manifests: from the artifacts' own manifests
        if entry["stage"] not in per_stage and store.has(entry["stage"], entry["key"]):
            per_stage[entry["stage"]] = store.manifest(entry["stage"], entry["key"])["params"]
    flat = {"seed": manifest.get("seed"), "outputs": manifest.get("outputs")}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict) and value:
            for k, v in value.items():
                walk(f"{prefix}.{k}", v)
        else:
            flat[prefix] = value
    for stage, params in per_stage.items():
        walk(stage, params)
    return flat


# --------------------------------------------------------------------------- per file


def _read_image(path: Path) -> tuple[list[str], np.ndarray]:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read: {oiio.geterror()}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        names = list(spec.channelnames)
    finally:
        inp.close()
    return names, np.asarray(pixels, np.float32).reshape(spec.height, spec.width, spec.nchannels)


def image_change(a: Path, b: Path) -> dict:
    """Per channel (by name): share of pixels changed, max and RMS difference."""
    names_a, pa = _read_image(a)
    names_b, pb = _read_image(b)
    if pa.shape[:2] != pb.shape[:2]:
        return {"shape": [list(pa.shape[:2]), list(pb.shape[:2])]}
    channels = {}
    for name in names_a:
        if name not in names_b:
            continue
        x, y = pa[..., names_a.index(name)], pb[..., names_b.index(name)]
        both_nan = np.isnan(x) & np.isnan(y)
        d = np.where(both_nan, 0.0, np.abs(x.astype(np.float64) - y))
        nan_one = np.isnan(d)
        changed = (d != 0) | nan_one
        d = np.where(nan_one, 0.0, d)
        channels[name] = {"changed_share": float(changed.mean()), "max": float(d.max()),
                          "rms": float(np.sqrt((d * d).mean()))}
    out: dict[str, Any] = {"channels": channels}
    if names_a != names_b:
        out["channel_names"] = [names_a, names_b]
    return out


def _layer_summary(path: Path) -> tuple[dict[str, dict], dict[str, int]]:
    """prim path -> {property: value text}, and PointInstancer -> instance count."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(path))
    prims: dict[str, dict] = {}
    instances: dict[str, int] = {}

    def visit(p):
        if p.IsPrimPath():
            spec = layer.GetPrimAtPath(p)
            props = {}
            for prop in spec.properties:
                if isinstance(prop, Sdf.AttributeSpec):
                    value = prop.default if prop.HasDefaultValue() else None
                    props[prop.name] = repr(value) if not hasattr(value, "__len__") or isinstance(value, str) \
                        else _array_digest(value)
                else:
                    props[prop.name] = repr(list(prop.targetPathList.GetAddedOrExplicitItems()))
            props["(type, references)"] = repr((spec.typeName, spec.referenceList.GetAddedOrExplicitItems(),
                                                spec.payloadList.GetAddedOrExplicitItems()))
            prims[str(p)] = props
            if spec.typeName == "PointInstancer" and "protoIndices" in spec.attributes:
                value = spec.attributes["protoIndices"].default
                instances[str(p)] = len(value) if value is not None else 0
    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    # the layer itself (the root of its prims): what it composes and its metadata
    prims["/"] = {"subLayers": repr(list(layer.subLayerPaths)), "customLayerData": repr(layer.customLayerData)}
    return prims, instances


def _array_digest(value) -> str:
    import hashlib

    try:
        arr = np.asarray(value)
        return f"{arr.dtype}{arr.shape}:" + hashlib.sha256(np.ascontiguousarray(arr).tobytes()).hexdigest()[:16]
    except (TypeError, ValueError):
        return repr(value)


def usd_change(a: Path, b: Path) -> dict:
    pa, ia = _layer_summary(a)
    pb, ib = _layer_summary(b)
    added = sorted(set(pb) - set(pa))
    removed = sorted(set(pa) - set(pb))
    changed = sorted(p for p in set(pa) & set(pb) if pa[p] != pb[p])
    out = {"prims_added": len(added), "prims_removed": len(removed), "prims_changed": len(changed),
           "added": added[:MAX_LISTED], "removed": removed[:MAX_LISTED], "changed": changed[:MAX_LISTED]}
    counts = {p: [ia.get(p, 0), ib.get(p, 0)] for p in sorted(set(ia) | set(ib)) if ia.get(p, 0) != ib.get(p, 0)}
    out["instances"] = [sum(ia.values()), sum(ib.values())]
    out["instancers_changed"] = dict(list(counts.items())[:MAX_LISTED])
    return out


def json_change(a: Path, b: Path) -> dict:
    ja, jb = json.loads(a.read_text()), json.loads(b.read_text())
    if not (isinstance(ja, dict) and isinstance(jb, dict)):
        return {"keys_changed": ["(whole file)"]}
    return {"keys_changed": sorted(k for k in set(ja) | set(jb) if ja.get(k) != jb.get(k))}


def file_change(a: Path, b: Path) -> dict:
    suffix = a.suffix.lower()
    if suffix in (".exr", ".png", ".tif", ".tiff", ".jpg"):
        return {"kind": "image", **image_change(a, b)}
    if suffix in (".usda", ".usdc", ".usd"):
        return {"kind": "usd", **usd_change(a, b)}
    if suffix == ".json":
        return {"kind": "json", **json_change(a, b)}
    return {"kind": "bytes"}


# --------------------------------------------------------------------------- worlds


def diff_worlds(store: Store, ref_a: str, ref_b: str) -> dict:
    where_a, ma = _load(store, ref_a)
    where_b, mb = _load(store, ref_b)
    pa, pb = _params(store, ma), _params(store, mb)
    params = [{"key": k, "a": pa.get(k), "b": pb.get(k)} for k in sorted(set(pa) | set(pb)) if pa.get(k) != pb.get(k)]
    ka = {e["stage"]: e["key"] for e in ma["artifacts"]}
    kb = {e["stage"]: e["key"] for e in mb["artifacts"]}
    stages, artifacts, files_differ = [], [], False
    for stage in list(ka) + [s for s in kb if s not in ka]:
        a, b = ka.get(stage), kb.get(stage)
        if a == b:
            continue
        row = {"stage": stage, "a": a, "b": b}
        if a is None or b is None:
            row["status"] = "only in " + ("b" if a is None else "a")
            files_differ = True
        elif not (store.has(stage, a) and store.has(stage, b)):
            row["status"] = "key differs; artifacts not in the store to compare"
            files_differ = True
        else:
            fa, fb = store.manifest(stage, a)["files"], store.manifest(stage, b)["files"]
            changed = 0
            for name in sorted(set(fa) | set(fb)):
                if name == MANIFEST or fa.get(name) == fb.get(name):
                    continue
                changed += 1
                entry: dict[str, Any] = {"stage": stage, "file": name}
                if name not in fb:
                    entry["change"] = "removed"
                elif name not in fa:
                    entry["change"] = "added"
                else:
                    entry["change"] = "changed"
                    entry.update(file_change(store.folder(stage, a) / name, store.folder(stage, b) / name))
                artifacts.append(entry)
            row["status"] = f"{changed} files differ" if changed else "key differs; same files"
            files_differ = files_differ or changed > 0
        stages.append(row)
    return {"a": where_a, "b": where_b, "equal": not params and not files_differ,
            "params": params, "stages": stages, "artifacts": artifacts}


def _figure(entry: dict) -> str:
    if entry["change"] != "changed":
        return entry["change"]
    kind = entry.get("kind")
    if kind == "image":
        if "shape" in entry:
            return f"size {entry['shape'][0]} -> {entry['shape'][1]}"
        if not any(v["changed_share"] for v in entry["channels"].values()) and "channel_names" not in entry:
            return "pixels equal (the header differs: its provenance names the run's key)"
        parts = [f"{c}: {100 * v['changed_share']:.3g} % changed, max {v['max']:.4g}, rms {v['rms']:.4g}"
                 for c, v in entry["channels"].items()]
        if "channel_names" in entry:
            parts.append(f"channels {entry['channel_names'][0]} -> {entry['channel_names'][1]}")
        return "; ".join(parts)
    if kind == "usd":
        text = (f"prims +{entry['prims_added']} -{entry['prims_removed']} ~{entry['prims_changed']}"
                + (f" ({', '.join(entry['changed'][:3])}{', ...' if entry['prims_changed'] > 3 else ''})"
                   if entry["changed"] else ""))
        if entry["instances"][0] != entry["instances"][1] or entry["instancers_changed"]:
            text += f"; instances {entry['instances'][0]} -> {entry['instances'][1]}"
        return text
    if kind == "json":
        return "keys " + ", ".join(entry["keys_changed"][:8])
    return "bytes differ"


def format_diff(result: dict) -> str:
    lines = [f"a: {result['a']}", f"b: {result['b']}"]
    if result["params"]:
        lines.append(f"parameters that differ ({len(result['params'])}):")
        lines += [f"  {p['key']}: {json.dumps(p['a'])} -> {json.dumps(p['b'])}" for p in result["params"]]
    if result["stages"]:
        lines.append(f"stages whose keys differ ({len(result['stages'])}):")
        lines += [f"  {s['stage']:<12} {s['a'] or '-'} -> {s['b'] or '-'}  {s['status']}" for s in result["stages"]]
    if result["artifacts"]:
        lines.append(f"artifact files that differ ({len(result['artifacts'])}):")
        lines += [f"  {e['stage']}/{e['file']}: {_figure(e)}" for e in result["artifacts"]]
    lines.append("equal" if result["equal"] else "different")
    return "\n".join(lines) + "\n"
