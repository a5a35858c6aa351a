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
from stemmap.io.rosbag import (
    GnssLog,
    ImuLog,
    OdometryLog,
    TopicSummary,
    bag_summary,
    decode_pointcloud2,
    is_bag,
    iter_laser_scans,
    list_topics,
    read_imu,
    read_navsatfix,
    read_odometry,
    read_pointclouds,
    write_scans_bag,
)
from stemmap.io.scans import (
    SkippedFrame,
    iter_scans,
    read_scans,
    read_scans_indexed,
    stack_scans,
    write_scans_csv,
    write_scans_npz,
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
    "GnssLog",
    "ImuLog",
    "OdometryLog",
    "SkippedFrame",
    "TopicSummary",
    "atomic_write",
    "bag_summary",
    "decode_pointcloud2",
    "is_bag",
    "iter_laser_scans",
    "iter_scans",
    "list_topics",
    "local_to_lonlat",
    "lonlat_to_local",
    "read_imu",
    "read_navsatfix",
    "read_observations_csv",
    "read_odometry",
    "read_pointclouds",
    "read_scans",
    "read_scans_indexed",
    "read_trajectory_csv",
    "read_trajectory_tum",
    "read_trees_csv",
    "read_trees_geojson",
    "stack_scans",
    "write_observations_csv",
    "write_scans_bag",
    "write_scans_csv",
    "write_scans_npz",
    "write_trajectory_csv",
    "write_trajectory_tum",
    "write_trees_csv",
    "write_trees_geojson",
]
