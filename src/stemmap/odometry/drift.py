"""Drift estimate of a pose-output odometry as a random walk in the distance travelled.

A scan-to-map lidar odometry (each frame registered to the local map) and a keyframe visual
odometry (each frame tracked from its keyframe) both make their errors per stretch of path, not
per frame: consecutive frames between two map updates or two keyframes share nearly the same
error, and a new, independent one starts when the vehicle has moved on far enough. Summing a
per-frame step variance as independent steps therefore grows with the frame rate (the square
root of the frame count) while the real drift does not. The end position's x + y variance is
instead modelled as a random walk in distance::

    V(d) = c² d        (c: metres per sqrt(metre), the 1-sigma of the x, y error after 1 m)

optionally with each frame's share of the distance (its step) weighted by how much worse than
nominal that frame's measurement is. The constant ``c`` is each odometry's own, measured on
drives of it: :attr:`stemmap.odometry.lidar.LidarOdometryConfig.drift_xy_per_sqrt_m` and
:data:`stemmap.odometry.visual.VISUAL_DRIFT_XY_PER_SQRT_M` (docs/algorithms/odometry.md "Drift
estimate", visual-odometry.md "Drift estimate"). A random walk is blind to a constant scale
error, which grows linearly with the distance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["distance_random_walk_variance"]


def distance_random_walk_variance(
    per_sqrt_m: float, distance: float, step: Any = None, weight: Any = None
) -> float:
    """Variance (m², x + y) of the end position after ``distance`` metres: ``per_sqrt_m² *
    distance``, times the step-weighted mean of ``weight`` when both per-step arrays are given
    (``sum(step * weight) / sum(step)``; a non-finite weight counts as 1; no weights, or no
    distance in the steps, is weight 1)."""
    base = float(per_sqrt_m) ** 2 * max(float(distance), 0.0)
    if step is None or weight is None:
        return base
    s = np.asarray(step, dtype=np.float64)
    w = np.asarray(weight, dtype=np.float64)
    w = np.where(np.isfinite(w), w, 1.0)
    total = float(s.sum())
    return base * float(np.sum(s * w)) / total if total > 0 else base
