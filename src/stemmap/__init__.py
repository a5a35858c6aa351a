"""stemmap: tree stem maps from 2D laser, 3D lidar, cameras and odometry.

See docs/architecture.md for the data flow and docs/algorithms.md for each paper's method.
"""

from stemmap.errors import ConfigError, InputError, StemmapError
from stemmap.types import (
    LaserScan,
    PointCloud,
    Pose2,
    ScanBatch,
    StemMap,
    StemObservation,
    StemObservations,
    Trajectory,
    Tree,
)

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "InputError",
    "LaserScan",
    "PointCloud",
    "Pose2",
    "ScanBatch",
    "StemMap",
    "StemObservation",
    "StemObservations",
    "StemmapError",
    "Trajectory",
    "Tree",
    "__version__",
]
