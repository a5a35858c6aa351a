"""Shared fixtures: a small simulated TLS stand written as LAZ tiles (built once per session)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from _laz_tiles import stand_cloud, write_tiles


@pytest.fixture(scope="session")
def stand_tiles(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A 30 x 30 m stand (24 trees, 4 TLS stations) cut into nine 10 m LAZ tiles; returns the
    tile folder and the whole cloud as the tiles store it (1 mm grid, tile order)."""
    root = tmp_path_factory.mktemp("stand")
    xyz = stand_cloud(size=30.0, n_trees=24, seed=5, stations=2)
    paths = write_tiles(root / "tiles", xyz, 10.0)
    import laspy

    whole = []
    for p in paths:  # the order a catalog reads them in: sorted paths
        las = laspy.read(p)
        whole.append(np.column_stack((las.x, las.y, las.z)))
    return root / "tiles", np.concatenate(whole)


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    """An in-process Dask cluster: one worker with two threads (tasks run concurrently)."""
    from distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
        ) as cluster,
        Client(cluster) as cl,
    ):
        yield cl
