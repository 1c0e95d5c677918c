"""Where stage runs execute: in this process, or on a Dask cluster.

A task is one planned step named by its recipe (the config's part of the
key); the same recipe needed by several worlds (variants sharing upstream
work) is one task. The task computes its key from its made inputs (early
cutoff) when its producers are done. On Dask, tasks
whose inputs are ready run in parallel on the workers, each worker building
its own OpenCL context; they write into the same store (a shared file system
for a real cluster), with the same rename-into-place rule, so a Dask bake
gives the same keys and the same files as a local one.
"""
from __future__ import annotations

import atexit
import os
import sys
import time
from typing import Any

from .bake import check_world, KeyedStep, PlannedStep, StepReport, key_step, plan_bake, publish_world, run_step, _progress_printer
from .config import WorldConfig
from .errors import InputError
from .graph import Graph
from .store import Store


def _run_or_reuse(store: Store, ps: PlannedStep, config: WorldConfig, graph: Graph, keys: dict[str, str],
                  log, head: str | None = None, verify: bool = False) -> StepReport:
    """Key the step from its made inputs, then reuse a stored run or run it.
    verify: re-hash every file of a stored run before reusing it (not only
    those whose size or mtime changed)."""
    ks = key_step(ps, store, graph, keys)
    cached = store.has(ps.stage.name, ks.key)
    if cached:
        damaged = store.damaged(ps.stage.name, ks.key, full=verify)
        if damaged:  # edited or removed since the run wrote it: never reused, made again under the same key
            print(f"worldbake: {ps.stage.name} {ks.key}: {', '.join(damaged[:3])}"
                  f"{f' and {len(damaged) - 3} more' if len(damaged) > 3 else ''} changed since the run wrote "
                  f"{'them' if len(damaged) > 1 else 'it'}; running the stage again", file=sys.stderr, flush=True)
            store.discard(ps.stage.name, ks.key)
            cached = False
    if head is not None:
        print(f"{head} {ks.key} {'cached' if cached else 'running'}", file=log, flush=True)
    if cached:
        return StepReport(ps.stage.name, ks.key, "cached", 0.0)
    t0 = time.perf_counter()
    manifest = run_step(store, ks, config, graph, _progress_printer(ps.stage.name, log))
    return StepReport(ps.stage.name, ks.key, "ran", time.perf_counter() - t0, manifest["metrics"])


def _keyed(store: Store, planned: list[PlannedStep], graph: Graph, keys: dict[str, str]) -> list[KeyedStep]:
    return [key_step(ps, store, graph, keys) for ps in planned]


def _dask_task(build_dir: str, ps: PlannedStep, config: WorldConfig, graph: Graph, verify: bool,
               *inputs_done: StepReport) -> StepReport:
    # the producers' reports give the keys their runs were stored under
    keys = {r.stage: r.key for r in inputs_done}
    return _run_or_reuse(Store(build_dir), ps, config, graph, keys, sys.stderr, verify=verify)


def _exit_without_native_teardown() -> None:
    """The last act of a Dask worker process: flush, then leave without running
    the native libraries' static destructors. With Intel's CPU OpenCL runtime
    and pymeshlab (its Qt and plugin libraries) loaded in one worker process,
    their destructors corrupt the heap at exit ("malloc_consolidate(): unaligned
    fastbin chunk detected", then an abort) after every task has finished and
    reported; a plain script doing the same in its main thread does not. The
    results are already written and renamed into place, and the worker's state
    is already reported to the scheduler, so nothing is lost by skipping them."""
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed stream: nothing to flush
            pass
    os._exit(0)


def _worker_plugin():
    from distributed import WorkerPlugin

    class ExitWithoutNativeTeardown(WorkerPlugin):
        name = "worldbake-exit-without-native-teardown"

        def setup(self, worker) -> None:
            # registered after distributed's own handlers, so it runs first (LIFO)
            atexit.register(_exit_without_native_teardown)

    return ExitWithoutNativeTeardown()


def _client(executor: str, workers: int = 2, worker_memory_gb: float | None = None):
    try:
        from distributed import Client, LocalCluster
    except ImportError as e:  # pragma: no cover - distributed is a dependency
        raise InputError(f"--executor {executor}: the 'distributed' package is not installed") from e
    if executor == "dask":
        memory = {} if worker_memory_gb is None else {"memory_limit": f"{worker_memory_gb}GB"}
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               **memory)
        client = Client(cluster)
        client.register_plugin(_worker_plugin())
        return client, cluster
    if "://" not in executor:
        raise InputError(f"--executor {executor!r}: use local, dask, or a scheduler address such as tcp://host:8786")
    client = Client(executor)
    client.register_plugin(_worker_plugin())
    return client, None


def bake_worlds(store: Store, configs: list[WorldConfig], graph: Graph, *, executor: str = "local",
                log=sys.stderr, checked: bool = False, verify: bool = False, workers: int = 2,
                worker_memory_gb: float | None = None) -> dict[str, list[StepReport]]:
    """Bake every config; returns the step reports per world name. Every
    planned stage's check runs first (unless the caller ran them: checked).
    verify: every stored run is re-hashed before it is reused. workers,
    worker_memory_gb: the embedded Dask cluster's (executor "dask")."""
    if not checked:
        for config in configs:
            check_world(graph, config)
    with store.baking():
        return _bake_worlds(store, configs, graph, executor, log, verify, (workers, worker_memory_gb))


def _bake_worlds(store: Store, configs: list[WorldConfig], graph: Graph, executor: str, log,
                 verify: bool = False, cluster_size: tuple[int, float | None] = (2, None)) -> dict[str, list[StepReport]]:
    store.clean_stale()
    plans = [(config, plan_bake(graph, config)) for config in configs]
    reports: dict[str, list[StepReport]] = {}
    if executor == "local":
        for config, planned in plans:
            print(f"baking world {config.name} from {config.path}", file=log, flush=True)
            done = []
            keys: dict[str, str] = {}
            for i, ps in enumerate(planned, 1):
                head = f"[{i}/{len(planned)}] {ps.stage.name}"
                report = _run_or_reuse(store, ps, config, graph, keys, log, head, verify)
                if report.status == "ran":
                    print(f"{head} {report.key} ran in {report.seconds:.2f} s", file=log, flush=True)
                keys[ps.stage.name] = report.key
                done.append(report)
            publish_world(store, config, _keyed(store, planned, graph, keys), done)
            reports[config.name] = done
        return reports

    client, cluster = _client(executor, *cluster_size)
    try:
        futures: dict[str, Any] = {}  # recipe -> future of its StepReport
        for config, planned in plans:
            recipe_of = {ps.stage.name: ps.recipe for ps in planned}
            for ps in planned:
                if ps.recipe in futures:
                    continue
                deps = [futures[recipe_of[producer]] for (_, producer) in ps.inputs.values()]
                futures[ps.recipe] = client.submit(_dask_task, str(store.build.resolve()), ps, config, graph, verify, *deps,
                                                   key=f"{ps.stage.name}-{ps.recipe}", pure=False)
        print(f"submitted {len(futures)} stage runs to {client.scheduler.address}", file=log, flush=True)
        results = {task: fut.result() for task, fut in futures.items()}  # re-raises a task's error
        for r in results.values():
            print(f"{r.stage} {r.key} {r.status}" + (f" in {r.seconds:.2f} s" if r.status == "ran" else ""), file=log)
        for config, planned in plans:
            reports[config.name] = [results[ps.recipe] for ps in planned]
            keys = {r.stage: r.key for r in reports[config.name]}
            publish_world(store, config, _keyed(store, planned, graph, keys), reports[config.name])
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return reports
