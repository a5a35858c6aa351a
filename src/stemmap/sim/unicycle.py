"""Pose algebra and the exact unicycle: the motion model of the simulated drives.

:func:`compose_poses` and :func:`relative_poses` are the SE(2) product and the relative pose on
``(..., 3)`` arrays ``(x, y, theta)`` (:func:`stemmap.slam.motion.compose` and ``between``);
:func:`integrate_unicycle` integrates piecewise-constant speed and yaw-rate controls exactly
(arc form), which is how :func:`stemmap.sim.trajectory.simulate_run` turns its controls into
the true path and how noise-free odometry reproduces the truth to rounding.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stemmap.slam.motion import between, compose
from stemmap.types import FloatArray, Trajectory, wrap_angle

if TYPE_CHECKING:
    from stemmap.sim.motion_sensors import Odometry

__all__ = ["compose_poses", "integrate_unicycle", "relative_poses"]


# The simulator's pose algebra is the SLAM one (one copy): ``compose_poses(a, b)`` is ``a * b``
# (``b`` given in ``a``'s frame, mapped to ``a``'s parent), ``relative_poses(a, b)`` is
# ``a^-1 * b`` (pose ``b`` in the frame of pose ``a``); both take (..., 3) arrays.
compose_poses = compose
relative_poses = between


def _arc_step(theta: FloatArray, v: FloatArray, w: FloatArray, dt: FloatArray) -> FloatArray:
    """Exact displacement (dx, dy) of a unicycle over ``dt`` at constant (v, w) from ``theta``.

    Uses ``v/w (sin(th + d) - sin th) = v dt sinc(d/2) cos(th + d/2)`` (and the cosine twin)
    with ``d = w dt``: exact, and free of the cancellation of the ``v/w`` form when ``w -> 0``.
    """
    dth = w * dt
    chord = v * dt * np.sinc(dth / (2.0 * np.pi))  # np.sinc(x) = sin(pi x) / (pi x)
    mid = theta + dth / 2.0
    return np.stack((chord * np.cos(mid), chord * np.sin(mid)), axis=-1)


def integrate_unicycle(
    pose0: ArrayLike, speed: ArrayLike, yaw_rate: ArrayLike, dt: ArrayLike
) -> FloatArray:
    """Exact integration of piecewise-constant unicycle controls.

    Parameters
    ----------
    pose0 : array_like of shape (3,)
    speed, yaw_rate, dt : array_like of shape (K,)
        Controls held over intervals of length ``dt`` (s).

    Returns
    -------
    ndarray of shape (K + 1, 3)
        Poses at the interval boundaries, starting with ``pose0``.

    Notes
    -----
    Over one interval ``theta' = theta + w dt``, ``x' = x + v/w (sin theta' - sin theta)``,
    ``y' = y + v/w (cos theta - cos theta')``, evaluated in the cancellation-free chord form
    ``v dt sinc(w dt / 2) (cos, sin)(theta + w dt / 2)`` (exact; straight line when w = 0).
    Headings accumulate without wrapping before the trig, then are wrapped to (-pi, pi].
    """
    p0 = np.asarray(pose0, dtype=np.float64).reshape(3)
    v = np.asarray(speed, dtype=np.float64).reshape(-1)
    w = np.asarray(yaw_rate, dtype=np.float64).reshape(-1)
    d = np.broadcast_to(np.asarray(dt, dtype=np.float64), v.shape)
    theta = p0[2] + np.concatenate(([0.0], np.cumsum(w * d)))
    steps = _arc_step(theta[:-1], v, w, d)
    xy = p0[:2] + np.concatenate((np.zeros((1, 2)), np.cumsum(steps, axis=0)))
    return np.column_stack((xy, wrap_angle(theta)))


def _poses_at(true_path: Trajectory, odo: Odometry, tq: FloatArray) -> FloatArray:
    """Exact vehicle poses at arbitrary times inside the run (arc from the previous sample)."""
    k = np.clip(np.searchsorted(odo.times, tq, side="right") - 1, 0, len(odo) - 1)
    base = true_path.poses[k]
    dt = tq - odo.times[k]
    d = _arc_step(base[:, 2], odo.speed[k], odo.yaw_rate[k], dt)
    return np.column_stack(
        (base[:, 0] + d[:, 0], base[:, 1] + d[:, 1], wrap_angle(base[:, 2] + odo.yaw_rate[k] * dt))
    )
