"""The Dask side of the engine: a client on a local or remote cluster, and a task runner that
retries, reports and never lets one failed task stop the others.

This module is the only one that imports ``dask.distributed``; the task functions it runs are
plain functions of stemmap (picklable, pure but for the files they write).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from stemmap.errors import ConfigError

__all__ = ["Dep", "TaskOutcome", "dask_client", "run_graph", "run_tasks"]

log = logging.getLogger(__name__)

#: Dask settings of the local cluster. Its workers' monitoring is for a dashboard the
#: engine does not start: the statistical profiler (a stack sample every 10 ms), the 20 ms
#: event-loop tick and the 0.5 s system monitor cost an idle worker ~22 ms of CPU a second
#: (0.43 CPU-s in 20 s; 0.13 without them), more while it works, i.e. 2-4 CPU-s per worker
#: in a 100 M-point run (docs/algorithms/engine.md, "Fifth pass"). The memory monitor (which
#: enforces ``memory_limit``) is kept. A cluster at ``--scheduler`` keeps its own settings.
LOCAL_CLUSTER_CONFIG: dict[str, Any] = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
}

#: glibc malloc settings of the local cluster's worker processes (on top of Dask's own
#: ``distributed.nanny.pre-spawn-environ``, whose ``MALLOC_TRIM_THRESHOLD_=65536`` hands freed
#: memory back to the kernel at once and fixes malloc's mmap threshold at 128 kB). A chunk's
#: arrays (tens of MB each) were then fresh pages from the kernel in every task: page faults
#: and zeroing, 0.2 ms per MB on bare metal, 2-5 ms per MB of system CPU on the virtual machine
#: the benchmark runs on (docs/algorithms/engine.md, "Sixth pass") -- 30-40 % of a worker's
#: CPU. Here malloc never maps memory of its own (``MALLOC_MMAP_MAX_=0``: every block comes
#: from the heap) and keeps up to 1 GiB of freed heap, so each task reuses the previous
#: tasks' pages. A worker then holds on to its largest task's memory (peak RSS 0.72 GB
#: instead of 0.58 GB at 32 M points, 40 m chunks); the peak still follows the chunk and
#: the pilot's point budget, not the catalog.
WORKER_MALLOC_ENV: dict[str, int] = {
    "MALLOC_MMAP_MAX_": 0,
    "MALLOC_TRIM_THRESHOLD_": 1 << 30,
}


@dataclass(frozen=True)
class TaskOutcome:
    """How one task ended: ``value`` if it succeeded, else ``error`` (type and message)."""

    key: str
    ok: bool
    value: Any = None
    error: str = ""


@contextlib.contextmanager
def dask_client(
    workers: int | None = None,
    scheduler: str | None = None,
    *,
    memory_limit: str | int = "auto",
) -> Iterator[Any]:
    """A ``dask.distributed.Client``, closed (and its local cluster stopped) on exit.

    Parameters
    ----------
    workers : int, optional
        Worker processes of the local cluster (one thread each); default one per core
        (``os.cpu_count()``). Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a running scheduler (``tcp://HOST:PORT``): submit there instead of
        starting a local cluster.
    memory_limit : str or int
        Per-worker memory limit of the local cluster (Dask's ``"auto"``: the machine's memory
        divided among the workers).
    """
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a main dependency
        raise ConfigError(
            "the scale-out engine needs dask.distributed: pip install 'dask[distributed]'."
        ) from exc
    if scheduler is not None:
        if "://" not in scheduler:
            raise ConfigError(
                f"--scheduler must be an address like tcp://HOST:PORT, got {scheduler!r}."
            )
        try:
            client = Client(scheduler, timeout="30s")
        except OSError as exc:
            raise ConfigError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from exc
        try:
            yield client
        finally:
            client.close()
        return
    # a local cluster's start-up and shutdown chatter (INFO) is not the user's business
    for name in ("distributed", "distributed.nanny", "distributed.scheduler"):
        logging.getLogger(name).setLevel(logging.ERROR)
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 1:
        raise ConfigError(f"--workers must be >= 1, got {n}.")
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    settings = {
        **LOCAL_CLUSTER_CONFIG,
        "distributed.nanny.pre-spawn-environ": {**environ, **WORKER_MALLOC_ENV},
    }
    with dask.config.set(settings):  # the nannies pass it on to their workers
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            memory_limit=memory_limit,
        )
    try:
        client = Client(cluster)
        # a failed task is reported by run_tasks (with its error) in the client: the local
        # workers' own "Compute Failed" dumps (the task's arguments) would repeat it as noise
        client.run(_quiet_worker_logs)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _quiet_worker_logs() -> None:
    """In a local worker: log only critical messages of dask.distributed."""
    for name in ("distributed", "distributed.worker", "distributed.core", "distributed.nanny"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


@dataclass(frozen=True)
class Dep:
    """An argument of a :func:`run_graph` task that stands for the result of the earlier
    task named ``key`` (the task waits for it; Dask moves the value between workers)."""

    key: str


def run_graph(
    client: Any,
    tasks: Sequence[tuple[str, Callable[..., Any], tuple[Any, ...]]],
    *,
    retries: int = 2,
    priorities: dict[str, int] | None = None,
    on_done: Callable[[TaskOutcome], None] | None = None,
) -> list[TaskOutcome]:
    """Run a graph of tasks ``(key, fn, args)`` on the cluster; collect every outcome.

    Every task is submitted at once: an argument ``Dep(key)`` makes a task wait for an
    earlier task and receive its result, so independent work runs while a dependency is
    still being computed (no client-side barrier between stages). ``priorities`` (key ->
    int, default 0; Dask runs higher first among ready tasks). A task that raises is retried
    ``retries`` times (a worker that dies mid-task has its tasks rescheduled by the
    scheduler on another worker, Dask's ``allowed-failures``); one that still fails is
    reported as a failed :class:`TaskOutcome` while the others go on (a task depending on a
    failed one fails with its error). ``on_done`` is called in the client, in completion
    order, once per task.
    """
    from distributed import as_completed

    if not tasks:
        return []
    prio = priorities or {}
    futures: dict[str, Any] = {}
    for key, fn, args in tasks:
        a = tuple(futures[x.key] if isinstance(x, Dep) else x for x in args)
        futures[key] = client.submit(
            fn, *a, key=key, pure=False, retries=retries, priority=prio.get(key, 0)
        )
    outcomes: list[TaskOutcome] = []
    for fut in as_completed(list(futures.values())):
        # Not ``fut.status``: a future can come out of as_completed as "lost" (the worker
        # holding its result died) with no exception; result() waits for the scheduler's
        # recomputation and raises only for a real failure or a cancelled task.
        try:
            oc = TaskOutcome(str(fut.key), True, value=fut.result())
        except Exception as exc:  # every task error is reported, not raised
            oc = TaskOutcome(str(fut.key), False, error=f"{type(exc).__name__}: {exc}")
            log.error("task %s failed: %s", fut.key, oc.error)
        fut.release()
        outcomes.append(oc)
        if on_done is not None:
            on_done(oc)
    return outcomes


def run_tasks(
    client: Any,
    fn: Callable[..., Any],
    tasks: Sequence[tuple[str, tuple[Any, ...]]],
    *,
    retries: int = 2,
    on_done: Callable[[TaskOutcome], None] | None = None,
) -> list[TaskOutcome]:
    """Run ``fn(*args)`` for every independent ``(key, args)`` on the cluster
    (:func:`run_graph` with one function and no dependencies)."""
    return run_graph(client, [(k, fn, a) for k, a in tasks], retries=retries, on_done=on_done)
