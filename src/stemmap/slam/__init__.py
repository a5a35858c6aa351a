"""Tree-landmark SLAM: the shared interface, motion models, association and back-ends.

Interface (``stemmap.slam.base``): :class:`Controls`, :class:`TreeFrames`, :class:`SlamProblem`,
:class:`SlamResult`, :data:`BACKENDS` / :func:`make_backend`, :func:`dead_reckoning`.
Motion models (``stemmap.slam.motion``): :class:`AckermannModel`, :class:`UnicycleModel`,
:class:`OdometryIncrementModel`, :func:`preintegrate`.
Back-ends are imported lazily by name (``make_backend("isam2")``), so importing this package
does not import GTSAM.
"""

from stemmap.slam.base import (
    BACKENDS,
    Controls,
    SlamBackend,
    SlamProblem,
    SlamResult,
    TreeFrames,
    dead_reckoning,
    duplicate_pairs,
    make_backend,
    observation_to_world,
    observe,
)
from stemmap.slam.motion import (
    AckermannModel,
    MotionModel,
    OdometryIncrementModel,
    UnicycleModel,
    preintegrate,
    rollout,
)

__all__ = [
    "BACKENDS",
    "AckermannModel",
    "Controls",
    "MotionModel",
    "OdometryIncrementModel",
    "SlamBackend",
    "SlamProblem",
    "SlamResult",
    "TreeFrames",
    "UnicycleModel",
    "dead_reckoning",
    "duplicate_pairs",
    "make_backend",
    "observation_to_world",
    "observe",
    "preintegrate",
    "rollout",
]
