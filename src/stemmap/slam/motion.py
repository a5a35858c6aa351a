"""Vehicle motion models with noise models and Jacobians, and odometry pre-integration.

State convention: a planar pose ``(x, y, theta)`` of the *vehicle reference point* in the world
frame (for :class:`AckermannModel` the centre of the rear axle). Controls ``u`` are model
specific (see each class). Every ``predict`` is vectorised over poses: ``states`` of shape (3,)
or (P, 3), ``u`` of shape (n_u,) or (P, n_u), ``dt`` a scalar or (P,).

Arc models (Ackermann, unicycle) move the pose along a chord with the mid-point heading::

    x' = x + ds * cos(theta + dtheta / 2)
    y' = y + ds * sin(theta + dtheta / 2)
    theta' = theta + dtheta

where ``(ds, dtheta)`` is the distance and heading change over ``dt``. This is second-order
accurate in ``dt`` (the Euler update used by Guivant & Nebot is first-order); at the 40 Hz
odometry rate of Victoria Park the two differ by millimetres per second of driving.

Noise model
-----------
Control noise is continuous-time white noise: ``sigma_speed`` and ``sigma_steer`` are the
standard deviations of the *one-second average* of the control error, so the control covariance
for a step of length ``dt`` is ``diag(sigma**2) * (1 s) / dt`` and the propagated pose
covariance grows linearly with driving time, independently of the odometry sampling rate.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, wrap_angle

if TYPE_CHECKING:
    from stemmap.slam.base import Controls

__all__ = [
    "AckermannModel",
    "MotionModel",
    "OdometryIncrementModel",
    "Preintegrated",
    "UnicycleModel",
    "between",
    "compose",
    "preintegrate",
    "preintegrate_spans",
    "rollout",
]

#: Reference time over which sigma_speed / sigma_steer are defined (s).
NOISE_TIME_S = 1.0


@runtime_checkable
class MotionModel(Protocol):
    """What every motion model offers (all array arguments follow the module conventions)."""

    n_controls: int

    def predict(self, states: ArrayLike, u: ArrayLike, dt: ArrayLike) -> FloatArray:
        """Poses after applying ``u`` for ``dt`` seconds, same leading shape as ``states``."""
        ...

    def jacobians(self, state: ArrayLike, u: ArrayLike, dt: float) -> tuple[FloatArray, FloatArray]:
        """``(F_x (3, 3), F_u (3, n_u))``: derivatives of ``predict`` at one state."""
        ...

    def noise(self, u: ArrayLike, dt: float, state: ArrayLike | None = None) -> FloatArray:
        """``Q (3, 3)``: control noise mapped to the state (``F_u C_u F_u^T``)."""
        ...


# --------------------------------------------------------------------------------------------
# Pose algebra (vectorised)
# --------------------------------------------------------------------------------------------


def compose(poses: ArrayLike, deltas: ArrayLike) -> FloatArray:
    """``poses ⊕ deltas``: apply body-frame increments ``(dx, dy, dtheta)`` to world poses.

    Both arguments broadcast over a leading axis; shapes (3,) or (N, 3).
    """
    p = np.asarray(poses, dtype=np.float64)
    d = np.asarray(deltas, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    out = np.empty(np.broadcast_shapes(p.shape, d.shape))
    out[..., 0] = p[..., 0] + c * d[..., 0] - s * d[..., 1]
    out[..., 1] = p[..., 1] + s * d[..., 0] + c * d[..., 1]
    out[..., 2] = wrap_angle(p[..., 2] + d[..., 2])
    return out


def between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a⁻¹ ⊕ b``: pose ``b`` expressed in the frame of pose ``a``; shapes (3,) or (N, 3)."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    dx = pb[..., 0] - pa[..., 0]
    dy = pb[..., 1] - pa[..., 1]
    out = np.empty(np.broadcast_shapes(pa.shape, pb.shape))
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = wrap_angle(pb[..., 2] - pa[..., 2])
    return out


# --------------------------------------------------------------------------------------------
# Arc models (Ackermann, unicycle)
# --------------------------------------------------------------------------------------------


def _as_controls(u: ArrayLike, n: int) -> FloatArray:
    arr = np.asarray(u, dtype=np.float64)
    if arr.shape[-1:] != (n,):
        raise InputError(f"controls must have a last axis of length {n}, got shape {arr.shape}.")
    return arr


class _ArcModel:
    """Shared machinery: subclasses define the arc ``(ds, dtheta)`` and its control Jacobian."""

    n_controls = 2
    kind: str = ""
    sigma_speed: float
    sigma_steer: float

    # -- to be provided by subclasses (vectorised over a leading axis) --
    def arc(self, u: ArrayLike, dt: ArrayLike) -> tuple[FloatArray, FloatArray]:
        raise NotImplementedError

    def arc_jacobian(self, u: ArrayLike, dt: ArrayLike) -> FloatArray:
        """d(ds, dtheta)/du, shape (..., 2, 2)."""
        raise NotImplementedError

    # -- shared --
    def control_cov(self, u: ArrayLike, dt: ArrayLike) -> FloatArray:
        """Covariance (..., 2, 2) of the control error over a step of ``dt`` s (see module)."""
        uu = _as_controls(u, 2)
        d = np.asarray(dt, dtype=np.float64)
        shape = np.broadcast_shapes(uu.shape[:-1], d.shape)
        scale = np.where(d > 0, NOISE_TIME_S / np.where(d > 0, d, 1.0), 0.0)
        out = np.zeros((*shape, 2, 2))
        out[..., 0, 0] = self.sigma_speed**2 * scale
        out[..., 1, 1] = self.sigma_steer**2 * scale
        return out

    def predict(self, states: ArrayLike, u: ArrayLike, dt: ArrayLike) -> FloatArray:
        x = np.asarray(states, dtype=np.float64)
        ds, dth = self.arc(u, dt)
        m = x[..., 2] + 0.5 * dth
        out = np.empty(np.broadcast_shapes(x.shape, (*np.shape(m), 3)))
        out[..., 0] = x[..., 0] + ds * np.cos(m)
        out[..., 1] = x[..., 1] + ds * np.sin(m)
        out[..., 2] = wrap_angle(x[..., 2] + dth)
        return out

    def jacobians(self, state: ArrayLike, u: ArrayLike, dt: float) -> tuple[FloatArray, FloatArray]:
        x = np.asarray(state, dtype=np.float64).reshape(3)
        ds_a, dth_a = self.arc(u, dt)
        ds, dth = float(ds_a), float(dth_a)
        m = x[2] + 0.5 * dth
        c, s = math.cos(m), math.sin(m)
        F_x = np.array([[1.0, 0.0, -ds * s], [0.0, 1.0, ds * c], [0.0, 0.0, 1.0]])
        G = np.array([[c, -0.5 * ds * s], [s, 0.5 * ds * c], [0.0, 1.0]])
        F_u = G @ self.arc_jacobian(u, dt).reshape(2, 2)
        return F_x, F_u

    def noise(self, u: ArrayLike, dt: float, state: ArrayLike | None = None) -> FloatArray:
        st = np.zeros(3) if state is None else np.asarray(state, dtype=np.float64)
        _, F_u = self.jacobians(st, u, dt)
        C = self.control_cov(u, dt).reshape(2, 2)
        Q: FloatArray = F_u @ C @ F_u.T
        _, dth = self.arc(u, dt)
        return Q + self._lateral_cov(st[2] + 0.5 * np.asarray(dth).reshape(()), dt)

    def _lateral_cov(self, heading: ArrayLike, dt: ArrayLike) -> FloatArray:
        """``σ_lat² dt n nᵀ`` with ``n = (-sin, cos, 0)`` of ``heading``: a sideways velocity
        error (white, ``sigma_lateral`` its one-second average), zero for a wheeled vehicle."""
        m = np.asarray(heading, dtype=np.float64)
        sig = float(getattr(self, "sigma_lateral", 0.0))
        var = sig**2 * np.maximum(np.asarray(dt, dtype=np.float64), 0.0)
        n = np.stack((-np.sin(m), np.cos(m), np.zeros_like(m)), axis=-1)
        out: FloatArray = np.asarray(var)[..., None, None] * n[..., :, None] * n[..., None, :]
        return out

    def noise_batch(self, u: ArrayLike, dt: ArrayLike, headings: ArrayLike) -> FloatArray:
        """World-frame noise (N, 3, 3) of many steps at once (used by :func:`preintegrate`)."""
        uu = _as_controls(u, 2)
        d = np.asarray(dt, dtype=np.float64)
        ds, dth = self.arc(uu, d)
        m = np.asarray(headings, dtype=np.float64) + 0.5 * dth
        c, s = np.cos(m), np.sin(m)
        G = np.zeros((*np.shape(m), 3, 2))
        G[..., 0, 0], G[..., 0, 1] = c, -0.5 * ds * s
        G[..., 1, 0], G[..., 1, 1] = s, 0.5 * ds * c
        G[..., 2, 1] = 1.0
        F_u = G @ self.arc_jacobian(uu, d)
        out: FloatArray = F_u @ self.control_cov(uu, d) @ np.swapaxes(F_u, -1, -2)
        if getattr(self, "sigma_lateral", 0.0) > 0.0:
            out = out + self._lateral_cov(m, d)
        return out


@dataclass(frozen=True)
class AckermannModel(_ArcModel):
    """Car-like vehicle with the speed encoder on a rear wheel (Guivant & Nebot, Victoria Park).

    Controls ``u = (v_e, alpha)``: encoder (left rear wheel) speed in m/s and front steering
    angle in rad (positive = turning left). The state is the pose of the rear-axle centre.

    Parameters
    ----------
    L : float, m
        Wheelbase (rear axle to front axle). Victoria Park: 2.83.
    H : float, m
        Lateral offset of the encoder wheel from the rear-axle centre, positive to the left.
        Victoria Park: 0.76 (encoder on the left rear wheel).
    a, b : float, m
        Laser position in the vehicle frame: ``a`` forward of the rear axle, ``b`` to the left.
        Victoria Park: a = 3.78 (= L + 0.95 m, info.txt measures 0.95 m from the front axle),
        b = 0.50.
    sigma_speed : float, m/s
        Std of the one-second average of the encoder speed error.
    sigma_steer : float, rad
        Std of the one-second average of the steering angle error.
    steer_offset : float, rad
        Constant added to the measured steering angle (sensor calibration; Victoria Park:
        +0.0055 rad, estimated without GPS by
        :func:`stemmap.datasets.victoria_park.estimate_steer_offset`).

    Notes
    -----
    Rear-axle centre speed from the left-wheel encoder (the left wheel runs on a circle of radius
    ``R - H`` when the centre runs on ``R = L / tan(alpha)``)::

        v_c = v_e / (1 - tan(alpha) * H / L),   ds = v_c dt,   dtheta = v_c dt tan(alpha) / L

    Guivant & Nebot write the same model for the laser position ``(x_L, y_L)`` instead of the
    axle centre (their ``x' = v_c cos(phi) - v_c/L tan(alpha) (a sin(phi) + b cos(phi))``); here
    the laser offset is applied in the observation model (``SlamProblem.sensor_offset``).

    References
    ----------
    J. Guivant, E. Nebot, "Optimization of the simultaneous localization and map-building
    algorithm for real-time implementation", IEEE T-RA 17(3), 2001 (vehicle model, §VI).
    """

    L: float = 2.83
    H: float = 0.76
    a: float = 3.78
    b: float = 0.50
    sigma_speed: float = 0.10
    sigma_steer: float = 0.02
    kind: str = "ackermann"
    steer_offset: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.L) and self.L > 0):
            raise ConfigError(f"AckermannModel.L (wheelbase) must be > 0 m, got {self.L}.")
        if not (math.isfinite(self.H) and abs(self.H) < self.L):
            raise ConfigError(f"AckermannModel.H must satisfy |H| < L, got {self.H}.")
        for name in ("sigma_speed", "sigma_steer"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"AckermannModel.{name} must be >= 0, got {v}.")
        if not (math.isfinite(self.steer_offset) and abs(self.steer_offset) < 0.5):
            raise ConfigError(
                f"AckermannModel.steer_offset must be a small angle (rad), got {self.steer_offset}."
            )

    @property
    def sensor_offset(self) -> tuple[float, float]:
        """Laser position (a, b) in the vehicle frame, metres."""
        return (self.a, self.b)

    def centre_speed(self, v_e: ArrayLike, alpha: ArrayLike) -> FloatArray:
        """Rear-axle-centre speed from the encoder wheel speed (see Notes)."""
        return np.asarray(v_e, dtype=np.float64) / (1.0 - np.tan(alpha) * self.H / self.L)

    def arc(self, u: ArrayLike, dt: ArrayLike) -> tuple[FloatArray, FloatArray]:
        uu = _as_controls(u, 2)
        d = np.asarray(dt, dtype=np.float64)
        t = np.tan(uu[..., 1] + self.steer_offset)
        ds = uu[..., 0] / (1.0 - t * self.H / self.L) * d
        return ds, ds * t / self.L

    def arc_jacobian(self, u: ArrayLike, dt: ArrayLike) -> FloatArray:
        uu = _as_controls(u, 2)
        d = np.asarray(dt, dtype=np.float64)
        v, al = uu[..., 0], uu[..., 1] + self.steer_offset
        t = np.tan(al)
        sec2 = 1.0 + t * t
        k = 1.0 - t * self.H / self.L
        ds = v / k * d
        dds_dv = d / k
        dds_da = v * d * (self.H / self.L) * sec2 / (k * k)
        out = np.zeros((*np.broadcast_shapes(v.shape, d.shape), 2, 2))
        out[..., 0, 0] = dds_dv
        out[..., 0, 1] = dds_da
        out[..., 1, 0] = dds_dv * t / self.L
        out[..., 1, 1] = (dds_da * t + ds * sec2) / self.L
        return out


@dataclass(frozen=True)
class UnicycleModel(_ArcModel):
    """Differential-drive / unicycle vehicle: controls ``u = (v, omega)`` in m/s and rad/s.

    ``ds = v dt``, ``dtheta = omega dt``; ``sigma_steer`` is the yaw-rate error (rad/s, one-second
    average) and ``sigma_speed`` the speed error (m/s, one-second average). ``sigma_lateral``
    (m/s, one-second average) is a sideways velocity error, perpendicular to the mid heading:
    0 for a wheeled vehicle's own odometry (it cannot slide); a pose-output odometry's position
    error has no preferred direction, so :func:`stemmap.slam.munjer.controls_from_trajectory`
    sets it to ``sigma_speed`` (docs/algorithms/slam.md, "Controls from a pose trajectory").
    """

    sigma_speed: float = 0.05
    sigma_steer: float = 0.01
    kind: str = "unicycle"
    sigma_lateral: float = 0.0

    def __post_init__(self) -> None:
        for name in ("sigma_speed", "sigma_steer", "sigma_lateral"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"UnicycleModel.{name} must be >= 0, got {v}.")

    @property
    def sensor_offset(self) -> tuple[float, float]:
        return (0.0, 0.0)

    def arc(self, u: ArrayLike, dt: ArrayLike) -> tuple[FloatArray, FloatArray]:
        uu = _as_controls(u, 2)
        d = np.asarray(dt, dtype=np.float64)
        return uu[..., 0] * d, uu[..., 1] * d

    def arc_jacobian(self, u: ArrayLike, dt: ArrayLike) -> FloatArray:
        uu = _as_controls(u, 2)
        d = np.asarray(dt, dtype=np.float64)
        out = np.zeros((*np.broadcast_shapes(uu.shape[:-1], d.shape), 2, 2))
        out[..., 0, 0] = d
        out[..., 1, 1] = d
        return out


# --------------------------------------------------------------------------------------------
# Generic odometry-increment model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryIncrementModel:
    """Body-frame odometry increments ``u = (dx, dy, dtheta)`` (e.g. from scan matching or a
    wheel-odometry topic differenced between frames); ``dt`` is ignored.

    Noise grows with the increment (the classic "error per metre travelled" model)::

        sigma_xy = sigma_xy_min + k_xy * |d|,   sigma_theta = sigma_theta_min + k_theta * |d|
                                                                 + k_theta_rot * |dtheta|

    with ``|d| = hypot(dx, dy)``; the noise is applied in the body frame of the start pose.
    """

    k_xy: float = 0.02
    k_theta: float = 0.005
    k_theta_rot: float = 0.02
    sigma_xy_min: float = 1e-3
    sigma_theta_min: float = 1e-4
    n_controls: int = 3

    def __post_init__(self) -> None:
        for name in ("k_xy", "k_theta", "k_theta_rot", "sigma_xy_min", "sigma_theta_min"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"OdometryIncrementModel.{name} must be >= 0, got {v}.")

    def predict(self, states: ArrayLike, u: ArrayLike, dt: ArrayLike = 0.0) -> FloatArray:
        return compose(states, _as_controls(u, 3))

    def jacobians(
        self, state: ArrayLike, u: ArrayLike, dt: float = 0.0
    ) -> tuple[FloatArray, FloatArray]:
        x = np.asarray(state, dtype=np.float64).reshape(3)
        d = _as_controls(u, 3).reshape(3)
        c, s = math.cos(x[2]), math.sin(x[2])
        F_x = np.array(
            [
                [1.0, 0.0, -s * d[0] - c * d[1]],
                [0.0, 1.0, c * d[0] - s * d[1]],
                [0.0, 0.0, 1.0],
            ]
        )
        F_u = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return F_x, F_u

    def control_cov(self, u: ArrayLike, dt: ArrayLike = 0.0) -> FloatArray:
        d = _as_controls(u, 3)
        dist = np.hypot(d[..., 0], d[..., 1])
        sxy = self.sigma_xy_min + self.k_xy * dist
        sth = self.sigma_theta_min + self.k_theta * dist + self.k_theta_rot * np.abs(d[..., 2])
        out = np.zeros((*dist.shape, 3, 3))
        out[..., 0, 0] = sxy**2
        out[..., 1, 1] = sxy**2
        out[..., 2, 2] = sth**2
        return out

    def noise(self, u: ArrayLike, dt: float = 0.0, state: ArrayLike | None = None) -> FloatArray:
        st = np.zeros(3) if state is None else np.asarray(state, dtype=np.float64)
        _, F_u = self.jacobians(st, u, dt)
        Q: FloatArray = F_u @ self.control_cov(u).reshape(3, 3) @ F_u.T
        return Q


# --------------------------------------------------------------------------------------------
# Integration of a control stream
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Preintegrated:
    """Odometry between consecutive query times, from :func:`preintegrate`.

    Attributes
    ----------
    times : ndarray (F,)
        Query (frame) times, s.
    poses : ndarray (F, 3)
        Dead-reckoned poses at ``times`` starting from ``initial_pose``.
    deltas : ndarray (F-1, 3)
        Body-frame increments ``poses[f]⁻¹ ⊕ poses[f+1]``.
    covs : ndarray (F-1, 3, 3)
        Covariance of each increment in the body frame of ``poses[f]`` (control noise propagated
        through the motion model, first order); without covariance (``with_covariance=False``)
        a read-only all-NaN view.
    distance : ndarray (F-1,)
        Path length driven in each interval (m, >= 0).
    """

    times: FloatArray
    poses: FloatArray
    deltas: FloatArray
    covs: FloatArray
    distance: FloatArray


def _segments(
    controls: Controls, times: FloatArray
) -> tuple[FloatArray, FloatArray, np.ndarray, np.ndarray]:
    """Split [times[0], times[-1]] at every control and query time (zero-order hold).

    Returns (u (S, 2), dt (S,), interval (S,) query interval of each segment, ends (F,) index of
    the first segment starting at or after each query time).
    """
    ct = controls.times
    t0, t1 = float(times[0]), float(times[-1])
    inner = ct[(ct > t0) & (ct < t1)]
    grid = np.union1d(inner, times)
    starts = grid[:-1]
    dt = np.diff(grid)
    k = np.searchsorted(ct, starts, side="right") - 1
    u = np.zeros((starts.shape[0], 2))
    ok = k >= 0
    u[ok, 0] = controls.speed[k[ok]]
    u[ok, 1] = controls.steer[k[ok]]
    interval = np.searchsorted(times, starts, side="right") - 1
    interval = np.clip(interval, 0, max(times.shape[0] - 2, 0))
    ends = np.searchsorted(grid, times, side="left")
    return u, dt, interval, ends


ROLLOUT_BLOCK = 1 << 14
"""Grid points per block of :func:`preintegrate`'s pose-only path (at most twice this many)."""


def _running(carry: float, w: FloatArray, started: bool) -> FloatArray:
    """``np.cumsum`` of a whole stream, one block ``w`` at a time: the sum starts FROM the
    previous blocks' sum ``carry`` (cumsum is sequential, so the roundings are those of the
    whole-array sum; adding ``carry`` afterwards would round differently)."""
    if not started:
        return np.cumsum(w)
    out: FloatArray = np.cumsum(np.concatenate(([carry], w)))[1:]
    return out


def _poses_blocked(
    model: Any, controls: Controls, tq: FloatArray, p0: FloatArray, block: int = ROLLOUT_BLOCK
) -> tuple[FloatArray, FloatArray]:
    """Poses (F, 3) at ``tq`` and distance (F-1,) per interval, as :func:`preintegrate`'s
    whole-array integration (:func:`_segments`, cumulative sums of ``dtheta`` and mid-point
    chords) computes them, bit for bit, in memory bounded by ``block`` and F.

    The grid (every control and query time) is cut at every ``block``-th control and query
    time, so a block holds at most ``2 * block`` grid points; each block's segments start at
    the previous block's last grid point, its running sums start from the previous block's
    (:func:`_running`) and so does the distance of the interval it continues.
    """
    ct = controls.times
    nf = tq.shape[0]
    # ct is non-decreasing (Controls checks it): this view is ct[(ct > t0) & (ct < t1)]
    inner = ct[np.searchsorted(ct, tq[0], side="right") : np.searchsorted(ct, tq[-1], side="left")]
    cuts = np.union1d(inner[::block], tq[::block])
    ii = np.append(np.searchsorted(inner, cuts, side="left"), inner.shape[0])
    qi = np.append(np.searchsorted(tq, cuts, side="left"), nf)
    poses = np.empty((nf, 3))
    dist = np.zeros(nf - 1)
    sums = [0.0, 0.0, 0.0]  # raw running sums of dtheta, chord x, chord y
    state = [float(p0[0]), float(p0[1]), float(p0[2])]  # pose at the last grid point so far
    started = False
    prev_t: float | None = None
    for k in range(cuts.shape[0]):
        g = np.union1d(inner[ii[k] : ii[k + 1]], tq[qi[k] : qi[k + 1]])
        pts = g if prev_t is None else np.concatenate(([prev_t], g))
        starts = pts[:-1]
        kk = np.searchsorted(ct, starts, side="right") - 1
        u = np.zeros((starts.shape[0], 2))
        ok = kk >= 0
        u[ok, 0] = controls.speed[kk[ok]]
        u[ok, 1] = controls.steer[kk[ok]]
        ds, dth = model.arc(u, np.diff(pts))
        c_th = _running(sums[0], dth, started)
        th_end = p0[2] + c_th
        mid = (th_end - dth) + 0.5 * dth
        c_x = _running(sums[1], ds * np.cos(mid), started)
        c_y = _running(sums[2], ds * np.sin(mid), started)
        # states at pts (index 0: the pose carried in)
        xs = np.concatenate(([state[0]], p0[0] + c_x))
        ys = np.concatenate(([state[1]], p0[1] + c_y))
        ths = np.concatenate(([state[2]], th_end))
        q = slice(qi[k], qi[k + 1])
        loc = np.searchsorted(pts, tq[q], side="left")
        poses[q, 0], poses[q, 1], poses[q, 2] = xs[loc], ys[loc], wrap_angle(ths[loc])
        if ds.shape[0]:
            interval = np.searchsorted(tq, starts, side="right") - 1
            interval = np.clip(interval, 0, max(nf - 2, 0))
            i0 = int(interval[0])  # continue its sum: the same additions as one bincount
            acc = np.bincount(
                np.concatenate(([0], interval - i0)),
                weights=np.concatenate(([dist[i0]], np.abs(ds))),
            )
            dist[i0 : i0 + acc.shape[0]] = acc
            sums = [float(c_th[-1]), float(c_x[-1]), float(c_y[-1])]
            state = [float(xs[-1]), float(ys[-1]), float(ths[-1])]
            started = True
        prev_t = float(pts[-1])
    return poses, dist


def _poses_whole(
    model: Any, controls: Controls, tq: FloatArray, p0: FloatArray
) -> tuple[FloatArray, FloatArray, tuple[Any, ...]]:
    """:func:`_poses_blocked`'s poses and distances over every segment at once (the covariance
    path needs the per-segment arrays: (u, dt, interval, ends, th_start, x_end, y_end, xs, ys))."""
    nf = tq.shape[0]
    u, dt, interval, ends = _segments(controls, tq)
    ds, dth = model.arc(u, dt)
    th_end = p0[2] + np.cumsum(dth)
    th_start = th_end - dth
    mid = th_start + 0.5 * dth
    x_end = p0[0] + np.cumsum(ds * np.cos(mid))
    y_end = p0[1] + np.cumsum(ds * np.sin(mid))
    # state after each grid point (index 0 = initial)
    xs = np.concatenate(([p0[0]], x_end))
    ys = np.concatenate(([p0[1]], y_end))
    ths = np.concatenate(([p0[2]], th_end))
    poses = np.column_stack((xs[ends], ys[ends], wrap_angle(ths[ends])))
    dist = np.bincount(interval, weights=np.abs(ds), minlength=nf - 1)[: nf - 1].astype(float)
    return poses, dist, (u, dt, interval, ends, th_start, x_end, y_end, xs, ys)


def _checked(
    model: Any, controls: Controls, times: ArrayLike, initial_pose: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Query times (F,) and initial pose (3,) as floats, after :func:`preintegrate`'s checks."""
    kind = getattr(model, "kind", None)
    if kind != controls.kind:
        raise InputError(
            f"controls are of kind {controls.kind!r} but the motion model is {kind!r}; "
            "use AckermannModel for 'ackermann' controls and UnicycleModel for 'unicycle'."
        )
    tq = np.asarray(times, dtype=np.float64).reshape(-1)
    if tq.shape[0] == 0:
        raise InputError("preintegrate needs at least one query time.")
    if np.any(np.diff(tq) < 0):
        k = int(np.argmin(np.diff(tq)))
        raise InputError(f"query times go backwards at index {k + 1}: {tq[k]} -> {tq[k + 1]}.")
    p0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    return tq, p0


def _no_covs(n: int) -> FloatArray:
    """(n, 3, 3) all NaN as a read-only broadcast view of one scalar: ``covs`` of a
    pose-only :func:`preintegrate` (an allocated NaN stack was 72 bytes per frame, ~5 MB on
    the 10x Victoria Park replay, never read)."""
    out: FloatArray = np.broadcast_to(np.float64(np.nan), (n, 3, 3))
    return out


def rollout(
    model: Any,
    controls: Controls,
    times: ArrayLike,
    initial_pose: ArrayLike = (0.0, 0.0, 0.0),
) -> FloatArray:
    """Dead-reckon ``controls`` and return the poses (F, 3) at query ``times`` (vectorised).

    Controls are held constant from their timestamp until the next one (zero-order hold); before
    the first control the vehicle stands still. ``model`` is an arc model (Ackermann, unicycle).
    """
    tq, p0 = _checked(model, controls, times, initial_pose)
    if tq.shape[0] == 1:
        return p0[None, :].copy()
    return _poses_blocked(model, controls, tq, p0)[0]  # preintegrate(..., False).poses


def preintegrate(
    model: Any,
    controls: Controls,
    times: ArrayLike,
    initial_pose: ArrayLike = (0.0, 0.0, 0.0),
    *,
    with_covariance: bool = True,
) -> Preintegrated:
    """Integrate a control stream between query times, with propagated covariance.

    Fully vectorised: the heading is a cumulative sum of ``dtheta``, positions a cumulative sum of
    mid-point chords. The covariance of the increment over one interval is
    ``Σ = Σ_k Φ_k Q_k Φ_kᵀ`` where ``Q_k`` is the world-frame noise of segment ``k`` and
    ``Φ_k = [[1, 0, -(y_end - y_k')], [0, 1, x_end - x_k'], [0, 0, 1]]`` carries an error at the
    end of segment ``k`` to the end of the interval (exact for the chord model, whose state
    Jacobian has this form and composes additively); it is then rotated into the start pose's
    body frame.

    Parameters
    ----------
    model : AckermannModel or UnicycleModel
    controls : Controls
        Its ``kind`` must match ``model.kind``.
    times : ndarray (F,), s, non-decreasing, F >= 1
    initial_pose : (3,)
    with_covariance : bool
        Skip the covariance (faster) when False; ``covs`` is then a read-only all-NaN view
        that holds no memory (:func:`_no_covs`), and the poses are
        integrated in blocks of :data:`ROLLOUT_BLOCK` grid points (:func:`_poses_blocked`: the
        same values bit for bit, working memory bounded by the block instead of linear in the
        control stream; 10x Victoria Park soak: +80 MB -> ~0 MB RSS transient).

    Raises
    ------
    InputError
        If the kinds disagree or ``times`` is empty or decreasing.
    """
    tq, p0 = _checked(model, controls, times, initial_pose)
    nf = tq.shape[0]
    if nf == 1:
        z = np.zeros(0)
        return Preintegrated(tq, p0[None, :].copy(), np.zeros((0, 3)), np.zeros((0, 3, 3)), z)
    if not with_covariance:
        poses, dist = _poses_blocked(model, controls, tq, p0)
        return Preintegrated(tq, poses, between(poses[:-1], poses[1:]), _no_covs(nf - 1), dist)
    poses, dist, seg = _poses_whole(model, controls, tq, p0)
    u, dt, interval, ends, th_start, x_end, y_end, xs, ys = seg
    deltas = between(poses[:-1], poses[1:])
    Q = model.noise_batch(u, dt, th_start)  # (S, 3, 3) world frame
    end_idx = ends[interval + 1]
    ex = xs[end_idx] - x_end
    ey = ys[end_idx] - y_end
    Phi = np.zeros((u.shape[0], 3, 3))
    Phi[:, 0, 0] = Phi[:, 1, 1] = Phi[:, 2, 2] = 1.0
    Phi[:, 0, 2] = -ey
    Phi[:, 1, 2] = ex
    contrib = Phi @ Q @ np.swapaxes(Phi, 1, 2)
    flat = contrib.reshape(-1, 9)
    acc = np.stack(
        [np.bincount(interval, weights=flat[:, j], minlength=nf - 1) for j in range(9)],
        axis=1,
    )[: nf - 1].reshape(-1, 3, 3)
    c, s = np.cos(poses[:-1, 2]), np.sin(poses[:-1, 2])
    R = np.zeros((nf - 1, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, s, -s, c
    R[:, 2, 2] = 1.0
    covs = np.asarray(R @ acc @ np.swapaxes(R, 1, 2), dtype=np.float64)  # (acc: float)
    covs = 0.5 * (covs + np.swapaxes(covs, 1, 2))
    return Preintegrated(tq, poses, deltas, covs, dist)


def preintegrate_spans(
    model: Any,
    controls: Any,
    times: FloatArray,
    initial_pose: Any,
    *,
    span_s: float = 2000.0,
    with_covariance: bool = True,
) -> Preintegrated:
    """:func:`~stemmap.slam.motion.preintegrate` over consecutive spans of at most ``span_s``
    seconds, each starting at the previous span's last pose, joined into one result.

    ``preintegrate``'s working memory grows with the control samples of one call (its (S, 3, 3)
    noise and Jacobian stacks): on the 10x Victoria Park soak one call over the whole drive
    peaked at +320 MB, the run's peak. Joined spans give the same increments and covariances
    (each interval is integrated on its own) and the same poses up to rounding; a drive
    shorter than ``span_s`` (the 1,550 s Victoria Park log) is one call, bit for bit. Every
    back-end that integrates a whole drive with covariances calls this (the soak's memory).
    """
    tq = np.asarray(times, dtype=np.float64).reshape(-1)
    if tq.size < 2 or tq[-1] - tq[0] <= span_s:
        return preintegrate(model, controls, tq, initial_pose, with_covariance=with_covariance)
    cuts = [0]
    while cuts[-1] < tq.size - 1:
        nxt = int(np.searchsorted(tq, tq[cuts[-1]] + span_s, side="right")) - 1
        cuts.append(min(max(nxt, cuts[-1] + 1), tq.size - 1))
    parts = []
    p0 = np.asarray(initial_pose, dtype=np.float64)
    for a, b in itertools.pairwise(cuts):
        parts.append(
            preintegrate(model, controls, tq[a : b + 1], p0, with_covariance=with_covariance)
        )
        p0 = parts[-1].poses[-1]
    return Preintegrated(
        tq,
        np.concatenate([parts[0].poses[:1]] + [q.poses[1:] for q in parts]),
        np.concatenate([q.deltas for q in parts]),
        np.concatenate([q.covs for q in parts]) if with_covariance else _no_covs(tq.size - 1),
        np.concatenate([q.distance for q in parts]),
    )
