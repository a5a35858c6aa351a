"""Readers and writers: laser scans (NPZ, CSV, ROS bags), stem maps and observations (CSV,
GeoJSON), trajectories (CSV, TUM). Every writer is atomic (:func:`atomic_write`).

Point-cloud files (LAS/LAZ, PLY, PCD) live in :mod:`stemmap.io.clouds`.
"""

from stemmap.io.atomic import atomic_write
from stemmap.io.maps import (
    OBSERVATION_CSV_COLUMNS,
    TREE_CSV_COLUMNS,
    local_to_lonlat,
    lonlat_to_local,
    read_observations_csv,
    read_trees_csv,
    read_trees_geojson,
    write_observations_csv,
    write_trees_csv,
    write_trees_geojson,
)
from stemmap.io.trajectory import (
    read_trajectory_csv,
    read_trajectory_tum,
    write_trajectory_csv,
    write_trajectory_tum,
)

__all__ = [
    "OBSERVATION_CSV_COLUMNS",
    "TREE_CSV_COLUMNS",
    "atomic_write",
    "local_to_lonlat",
    "lonlat_to_local",
    "read_observations_csv",
    "read_trajectory_csv",
    "read_trajectory_tum",
    "read_trees_csv",
    "read_trees_geojson",
    "write_observations_csv",
    "write_trajectory_csv",
    "write_trajectory_tum",
    "write_trees_csv",
    "write_trees_geojson",
]
