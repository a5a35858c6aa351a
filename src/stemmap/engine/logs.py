"""Drive logs on the engine: which inputs are logs, one output folder per log, one task per log.

``stemmap detect`` and ``stemmap map`` given several logs (files, a folder, a glob, a list
file) run each log as one Dask task (:func:`stemmap.engine.cluster.run_tasks`: retried, then
reported while the others finish). A log is a scans file (``.npz`` / ``.csv``, e.g. from
``stemmap sim scans``), a ROS 1 bag, a ROS 2 bag file (``.db3`` / ``.mcap``) or a ROS 2 bag
folder (it holds ``metadata.yaml``: one log, never a list). In a folder, the companion files
``stemmap sim scans`` writes beside a log (``<stem>_odometry.csv``, ``_poses.csv``,
``_trees.csv``, ``_gnss.csv``, ``_truth.npz``) are not logs.

The task function itself (what a log is turned into) belongs to the caller; this module only
expands, names and schedules.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stemmap.engine.catalog import expand_inputs
from stemmap.engine.cluster import TaskOutcome, dask_client, run_tasks
from stemmap.io.rosbag import BAG_SUFFIXES

__all__ = [
    "COMPANION_SUFFIXES",
    "LOG_EXTENSIONS",
    "LogOutcome",
    "expand_logs",
    "is_companion",
    "is_ros2_bag",
    "log_names",
    "run_logs",
]

log = logging.getLogger(__name__)

#: File types of a drive log (scans NPZ/CSV, ROS 1 bag, ROS 2 bag files).
LOG_EXTENSIONS: tuple[str, ...] = (".npz", ".csv", *BAG_SUFFIXES)
#: Files that ``stemmap sim scans`` writes beside a log: part of that log, not logs.
COMPANION_SUFFIXES = ("_odometry.csv", "_poses.csv", "_trees.csv", "_gnss.csv", "_truth.npz")


def is_ros2_bag(path: Path) -> bool:
    """A ROS 2 bag is a folder with a ``metadata.yaml`` (and .db3 / .mcap files)."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def is_companion(path: Path) -> bool:
    """True for a log's side file (odometry, poses, trees, GNSS CSV), see the module doc."""
    return path.name.lower().endswith(COMPANION_SUFFIXES)


def expand_logs(inputs: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Resolve files, folders, globs and list files into a sorted list of distinct logs.

    :func:`~stemmap.engine.catalog.expand_inputs` with the log file types; a ROS 2 bag folder
    is one log (given directly or met inside a folder).

    Raises
    ------
    InputError
        As :func:`~stemmap.engine.catalog.expand_inputs`.
    """
    return expand_inputs(
        inputs,
        extensions=LOG_EXTENSIONS,
        unit_dir=is_ros2_bag,
        companion=is_companion,
        what="log",
    )


def log_names(logs: Sequence[Path]) -> list[str]:
    """One distinct output-folder name per log: its file stem (a bag folder: its name), with
    ``_2``, ``_3``... appended when two logs share a stem (``a/run.npz``, ``b/run.npz``)."""
    names: list[str] = []
    seen: set[str] = set()
    for p in logs:
        base = p.name if p.is_dir() else p.stem
        name, k = base, 1
        while name in seen:
            k += 1
            name = f"{base}_{k}"
        seen.add(name)
        names.append(name)
    return names


@dataclass(frozen=True)
class LogOutcome:
    """How one log's task ended (``value``: what the task returned, when ``ok``)."""

    name: str
    path: Path
    ok: bool
    value: Any = None
    error: str = ""


def run_logs(
    fn: Callable[..., Any],
    tasks: Sequence[tuple[str, Path, tuple[Any, ...]]],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    retries: int = 1,
    on_done: Callable[[LogOutcome], None] | None = None,
) -> list[LogOutcome]:
    """Run ``fn(*args)`` for every ``(name, log, args)`` on a Dask cluster, one task per log.

    The cluster is a local one with ``workers`` processes or the scheduler at ``scheduler``
    (:func:`~stemmap.engine.cluster.dask_client`). A task that raises is retried ``retries``
    times (default once: a damaged log fails the same way again; a worker that dies has its
    task rescheduled by the scheduler regardless), then reported with its error while the
    others finish. Returns the outcomes in the order of ``tasks``.
    """
    by_key = {f"log-{name}": (name, path) for name, path, _ in tasks}

    def convert(oc: TaskOutcome) -> LogOutcome:
        name, path = by_key[oc.key]
        return LogOutcome(name, path, oc.ok, oc.value, oc.error)

    def done(oc: TaskOutcome) -> None:
        if on_done is not None:
            on_done(convert(oc))

    with dask_client(workers, scheduler) as client:
        outcomes = run_tasks(
            client,
            fn,
            [(f"log-{name}", args) for name, _, args in tasks],
            retries=retries,
            on_done=done,
        )
    got = {oc.key: convert(oc) for oc in outcomes}
    return [got[f"log-{name}"] for name, _, _ in tasks]
