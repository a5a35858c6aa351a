"""stemmap: tree stem maps from 2D laser, 3D lidar, cameras and odometry.

See docs/architecture.md for the data flow and docs/algorithms.md for each paper's method.

The data types (:mod:`stemmap.types`, which imports numpy) are loaded on first use (PEP 562),
so importing the package -- which the ``stemmap`` command does before it can install its
Ctrl-C handling -- takes microseconds, not the ~0.1 s of numpy.
"""

from typing import TYPE_CHECKING, Any

from stemmap.errors import ConfigError, InputError, StemmapError

if TYPE_CHECKING:
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


def __getattr__(name: str) -> Any:
    if name in _TYPES:  # (the names of __all__ that stemmap.types defines)
        from stemmap import types

        return getattr(types, name)
    raise AttributeError(f"module 'stemmap' has no attribute {name!r}")


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

_TYPES = frozenset(__all__) - {"ConfigError", "InputError", "StemmapError", "__version__"}
