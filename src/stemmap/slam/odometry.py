"""Moved to :mod:`stemmap.odometry.fusion` (the odometry front ends live in one package);
this name stays so that existing imports keep working."""

from stemmap.odometry.fusion import (
    FusedOdometry,
    OdometrySource,
    dead_reckon_source,
    fuse_odometry,
    fuse_sources,
    velocities_from_poses,
)

__all__ = [
    "FusedOdometry",
    "OdometrySource",
    "dead_reckon_source",
    "fuse_odometry",
    "fuse_sources",
    "velocities_from_poses",
]
