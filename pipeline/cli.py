"""The `worldbake` command.

    worldbake bake CONFIG [--variant NAME | --all-variants] [--set KEY=VALUE ...] [--name WORLD] [--replace] [--json]
                          [--executor local|dask|ADDRESS] [--verify]
    worldbake plan CONFIG [--variant NAME | --all-variants] [--set KEY=VALUE ...] [--name WORLD] [--json]
    worldbake validate WORLD_DIR_OR_USD
    worldbake verify [WORLD]
    worldbake worlds [--json]
    worldbake gc [--dry-run]
    worldbake export WORLD DEST
    worldbake diff A B [--json]
    worldbake report WORLD
    worldbake describe
    worldbake devices [--json]

Exit status: 0 done (diff: equal), 1 a stage failed (diff: different) (numerical blow-up, broken invariant),
2 bad config or input file (nothing written), 3 no usable OpenCL device
(the message names each device tried and why it failed).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

from .bake import check_world, key_step, plan_bake
from .executors import bake_worlds
from .config import check_name, list_variants, load_config
from .errors import DeviceError, InputError, StageError
from .export import export_problems, export_world
from .graph import build_graph
from .registry import all_stages
from .store import Store, StoreBusy
from .worlds import check_replace, list_worlds


def _configs(args) -> list:
    """The worlds to bake, after every world of the config file (the base
    and each variant, baked or not) passed load_config and every planned
    stage's check: nothing runs before all of them are known good."""
    stages = all_stages()
    graph = build_graph(stages)
    root = Path(args.project).resolve()
    path = Path(args.config)
    every = [None] + list_variants(path, root)
    if args.variant is not None and args.variant not in every:
        load_config(path, stages, project_root=root, variant=args.variant, sets=args.set)  # names the problem
    wanted = every if args.all_variants else [args.variant]
    configs = {v: load_config(path, stages, project_root=root, variant=v, sets=args.set) for v in every}
    if args.name is not None:  # the world's name instead of the config's (variants: NAME-variant)
        check_name(args.name, "--name", "name", "the world name")
        configs = {v: dataclasses.replace(c, name=args.name if v is None else f"{args.name}-{v}")
                   for v, c in configs.items()}
    for config in configs.values():
        check_world(graph, config)
    return [configs[v] for v in wanted]


def _cmd_plan(args) -> int:
    graph = build_graph(all_stages())
    store = Store(Path(args.project) / args.build)
    out = []
    for config in _configs(args):
        rows = []
        keys: dict[str, str] = {}  # stages whose output is in the store now
        for ps in plan_bake(graph, config):
            if all(producer in keys for _, producer in ps.inputs.values()):
                ks = key_step(ps, store, graph, keys)
                cached = store.has(ps.stage.name, ks.key)
                if cached:
                    keys[ps.stage.name] = ks.key
                rows.append({"stage": ps.stage.name, "key": ks.key, "status": "cached" if cached else "will run",
                             "inputs": {r: f"{a}@{k}" for r, (a, _, k) in ks.inputs.items()}})
            else:  # the key hashes what its inputs will hold (early cutoff): known once they are made
                rows.append({"stage": ps.stage.name, "key": None, "status": "after inputs",
                             "inputs": {r: f"{a}@?" if p not in keys else f"{a}@{keys[p]}"
                                        for r, (a, p) in ps.inputs.items()}})
        out.append({"world": config.name, "steps": rows})
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for world in out:
            print(f"world {world['world']}:")
            for r in world["steps"]:
                inputs = ", ".join(f"{k} <- {v}" for k, v in r["inputs"].items())
                print(f"  {r['stage']:<12} {r['key'] or '-' * 20}  {r['status']:<12}  {inputs}")
    return 0


def _cmd_bake(args) -> int:
    if not 1 <= args.workers <= 256:
        raise InputError(f"--workers {args.workers}: must be 1 .. 256")
    if args.worker_memory is not None and not 0.1 <= args.worker_memory <= 1e5:
        raise InputError(f"--worker-memory {args.worker_memory:g}: must be 0.1 .. 100000 GB")
    graph = build_graph(all_stages())
    configs = _configs(args)  # every config validated before any work
    store = Store(Path(args.project) / args.build)
    check_replace(store, configs, args.replace)
    reports = bake_worlds(store, configs, graph, executor=args.executor, checked=True, verify=args.verify,
                          workers=args.workers, worker_memory_gb=args.worker_memory)
    summary = []
    for config in configs:
        world_dir = store.worlds / config.name
        summary.append({"world": config.name, "world_dir": str(world_dir),
                        "world_usda": str(world_dir / "world.usda") if (world_dir / "world.usda").exists() else None,
                        "steps": [{"stage": r.stage, "key": r.key, "status": r.status, "seconds": round(r.seconds, 3)}
                                  for r in reports[config.name]]})
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for world in summary:
            print(f"world {world['world']}: {world['world_usda'] or world['world_dir']}")
            for s in world["steps"]:
                print(f"  {s['stage']:<12} {s['status']:<7} {s['seconds']:8.2f} s  {s['key']}")
    return 0


def _cmd_validate(args) -> int:
    path = Path(args.path)
    if path.is_dir():
        path = path / "world.usda"
    if not path.is_file():
        raise InputError(f"{path}: no such USD file")
    errors, notes = export_problems(path, _within(path))
    for e in notes:
        print(f"note: {e}")
    for e in errors:
        print(e)
    print(f"{path}: {len(errors)} validation errors")
    return 1 if errors else 0


def _within(root: Path) -> Path | None:
    """The folder a world's files must lie in: its own, unless it is a world
    of a build folder (worlds/<name> beside artifacts/, whose layers name
    the stored runs)."""
    folder = root.resolve().parent
    in_store = folder.parent.name == "worlds" and (folder.parent.parent / "artifacts").is_dir()
    return None if in_store or root.suffix == ".usdz" else folder


def _cmd_verify(args) -> int:
    """Re-hash every file the world(s) use; exit 1 naming each damaged one."""
    store = Store(Path(args.project) / args.build)
    names = [args.world] if args.world else [w["world"] for w in list_worlds(store)]
    if args.world and not (store.worlds / args.world / "manifest.json").is_file():
        raise InputError(f"verify: no world {args.world!r} in {store.worlds}")
    damaged = 0
    for name in names:
        problems, checked = store.verify_world(name)
        for problem in problems:
            print(f"{name}: {problem}")
        print(f"world {name}: {checked} files re-hashed, " + (f"{len(problems)} damaged" if problems else "all intact"),
              file=sys.stderr)
        damaged += len(problems)
    if damaged:
        print(f"worldbake: verify: {damaged} damaged; `worldbake bake CONFIG --verify` makes them again",
              file=sys.stderr)
    return 1 if damaged else 0


def _cmd_export(args) -> int:
    store = Store(Path(args.project) / args.build)
    dest = export_world(store, args.world, Path(args.dest))
    errors, notes = export_problems(dest, _within(dest))
    for e in notes:
        print(f"note: {e}")
    for e in errors:
        print(e)
    print(f"exported world {args.world} to {dest} ({len(errors)} validation errors)")
    return 1 if errors else 0


def _cmd_describe(args) -> int:
    from .docs import describe

    print(describe(all_stages()), end="")
    return 0


def _cmd_gc(args) -> int:
    store = Store(Path(args.project) / args.build)
    try:
        removed = store.gc(wait=not args.no_wait, dry_run=args.dry_run)
    except StoreBusy as e:
        print(f"worldbake: gc: {e}; nothing removed (without --no-wait, gc waits for it)", file=sys.stderr)
        return 1
    verb = "would remove" if args.dry_run else "removed"
    for p in removed:
        print(f"{verb} {p}")
    units = sum(1 for p in removed if p.parent.parent == store.units)
    print(f"{len(removed) - units} unreferenced artifact folders and {units} unused units "
          + ("would be removed (dry run: nothing removed)" if args.dry_run else "removed"))
    return 0


def _cmd_worlds(args) -> int:
    rows = list_worlds(Store(Path(args.project) / args.build))
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for r in rows:
        overrides = " ".join(f"{k}={json.dumps(v)}" for k, v in r["overrides"].items()) or "(no overrides)"
        variant = f" [variant {r['variant']}]" if r["variant"] else ""
        usd = "world.usda" if r["world_usda"] else "no world.usda"
        print(f"{r['world']:<20} {r['config']}{variant}  {usd}  {overrides}")
    print(f"{len(rows)} worlds")
    return 0


def _cmd_report(args) -> int:
    from .report import write_report
    from .worlds import world_manifest

    store = Store(Path(args.project) / args.build)
    manifest = world_manifest(store, args.world)
    if manifest is None:
        raise InputError(f"no baked world {args.world!r} in {store.worlds}")
    folder = store.worlds / args.world
    usd = folder / "world.usda"
    print(write_report(store, folder, manifest, usd if usd.is_file() else None))
    return 0


def _cmd_diff(args) -> int:
    from .diff import diff_worlds, format_diff

    result = diff_worlds(Store(Path(args.project) / args.build), args.a, args.b)
    print(json.dumps(result, indent=2) if args.json else format_diff(result), end="" if not args.json else "\n")
    return 0 if result["equal"] else 1


def _cmd_devices(args) -> int:
    from . import opencl

    want = os.environ.get("WORLDBAKE_CL_DEVICE", "").strip()
    candidates, chosen = opencl.probe_all(want, stop_at_first=False)
    if args.json:
        print(json.dumps({"WORLDBAKE_CL_DEVICE": want or None,
                          "order": "WORLDBAKE_CL_DEVICE, then GPUs with float64, then CPU runtimes "
                                   f"({', '.join(opencl.CPU_RUNTIME_ORDER)}), then others",
                          "devices": [c.as_dict() for c in candidates],
                          "used": chosen.index if chosen else None}, indent=2))
    else:
        print("OpenCL devices, in the order a bake tries them"
              + (f" (WORLDBAKE_CL_DEVICE={want!r})" if want else "") + ":")
        for c in candidates:
            mark = "*" if c is chosen else " "
            status = f"ok ({c.probe_ms:.0f} ms)" if c.ok else f"FAILED: {c.error}"
            print(f" {mark} {c.index:<4} {c.kind:<5} {c.platform} / {c.name}  [{c.reason}]  probe {status}")
        if chosen is not None:
            print(f"a bake uses {chosen.index} {chosen.platform} / {chosen.name} (the first whose probe passes)")
    if chosen is None:
        raise DeviceError(opencl.no_device_message(candidates, want))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="worldbake", description="Bake outdoor worlds from a config file.")
    parser.add_argument("--project", default=".", help="project root: configs and paths are checked against it (default: .)")
    parser.add_argument("--build", default="build", help="build folder, relative to the project (default: build)")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, helptext in (("bake", "bake a world"), ("plan", "print what a bake would run and what is cached")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("config", help="a world config (TOML)")
        group = p.add_mutually_exclusive_group()
        group.add_argument("--variant", help="bake the variant [variants.NAME]")
        group.add_argument("--all-variants", action="store_true", help="bake the base world and every variant")
        p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="override a config key, e.g. --set heightmap.octaves=8 (repeatable)")
        p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
        p.add_argument("--name", help="the world's name (default: the config's name); with variants, NAME-variant")
        if name == "bake":
            p.add_argument("--replace", action="store_true",
                           help="replace a world of the same name baked from another config, variant or overrides "
                                "(without it such a bake is refused)")
            p.add_argument("--executor", default="local", metavar="local|dask|ADDRESS",
                           help="local: in this process (default); dask: an embedded Dask LocalCluster "
                                "(2 worker processes); tcp://HOST:PORT: a running Dask scheduler")
            p.add_argument("--workers", type=int, default=2, metavar="N",
                           help="--executor dask: worker processes of the embedded cluster (default 2)")
            p.add_argument("--worker-memory", type=float, default=None, metavar="GB",
                           help="--executor dask: each worker's memory limit in GB (default: Dask's, the machine's "
                                "memory shared among the workers); a worker past it is restarted by Dask")
            p.add_argument("--verify", action="store_true",
                           help="re-hash every stored file before reusing it (not only those whose size or "
                                "mtime changed): a damaged run is made again")
    p = sub.add_parser("verify", help="re-hash every file a world uses against its manifests; exit 1 naming the damaged")
    p.add_argument("world", nargs="?", help="a world's name (default: every world in the build folder)")
    p = sub.add_parser("validate", help="run every pxr.UsdValidation validator on a world, and name every file it "
                                        "needs that is missing (an export: also every file outside it)")
    p.add_argument("path", help="a world folder or USD file")
    p = sub.add_parser("gc", help="remove artifacts no world references (waits for running bakes)")
    p.add_argument("--no-wait", action="store_true", help="refuse (exit 1) instead of waiting while a bake runs")
    p.add_argument("--dry-run", action="store_true", help="print what would be removed; remove nothing")
    p = sub.add_parser("worlds", help="list the baked worlds with their config and overrides")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p = sub.add_parser("report", help="(re)write build/worlds/WORLD/report.html (a bake writes it unless WORLDBAKE_REPORT=0)")
    p.add_argument("world", help="the world's name (a folder in build/worlds/)")
    p = sub.add_parser("diff", help="what differs between two worlds: parameters, stage keys, artifacts "
                                    "(exit 0 equal, 1 different)")
    p.add_argument("a", help="a world name, a world folder, or a saved world manifest.json")
    p.add_argument("b", help="a world name, a world folder, or a saved world manifest.json")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p = sub.add_parser("export", help="a self-contained copy of a baked world: a folder, or a .usdz file")
    p.add_argument("world", help="the world's name (a folder in build/worlds/)")
    p.add_argument("dest", help="a new folder, or a path ending in .usdz")
    sub.add_parser("describe", help="print every stage's inputs, outputs and config keys (markdown)")
    p = sub.add_parser("devices", help="every OpenCL device, its probe result, and which one a bake uses")
    p.add_argument("--json", action="store_true", help="print as JSON")
    args = parser.parse_args(argv)
    handlers = {"bake": _cmd_bake, "plan": _cmd_plan, "validate": _cmd_validate, "gc": _cmd_gc, "export": _cmd_export,
                "describe": _cmd_describe, "devices": _cmd_devices, "worlds": _cmd_worlds, "diff": _cmd_diff,
                "report": _cmd_report, "verify": _cmd_verify}
    try:
        return handlers[args.command](args)
    except InputError as e:  # a bad config or input file
        print(f"worldbake: error: {e}", file=sys.stderr)
        return 2
    except DeviceError as e:  # no OpenCL device can run the kernels
        print(f"worldbake: OpenCL device error: {e}", file=sys.stderr)
        return 3
    except StageError as e:
        print(f"worldbake: stage failed: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("worldbake: interrupted; nothing half-written was kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
