"""The local cluster of ``dask_client``: its workers' environment."""

from __future__ import annotations

import os

from stemmap.engine import dask_client
from stemmap.engine.cluster import WORKER_MALLOC_ENV


def _environ() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k.startswith(("MALLOC_", "OMP_"))}


def test_local_workers_keep_freed_memory_and_dasks_variables() -> None:
    """The malloc settings reach the worker processes (they keep freed heap memory for the
    next task), on top of Dask's own pre-spawn variables, which are kept."""
    import dask
    import distributed  # noqa: F401 - loads Dask's distributed defaults

    dasks = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
    with dask_client(1) as client:
        (env,) = client.run(_environ).values()
    for k, v in WORKER_MALLOC_ENV.items():
        assert env[k] == str(v)
    kept = {k: v for k, v in dasks.items() if k.startswith("OMP_")}
    assert kept  # e.g. OMP_NUM_THREADS=1: one thread per worker process
    for k, v in kept.items():
        assert env[k] == str(v)
