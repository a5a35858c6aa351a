"""Odometry, IMU and GNSS logs from bags (``nav_msgs/Odometry``, ``sensor_msgs/Imu``,
``sensor_msgs/NavSatFix``); re-exported by :mod:`stemmap.io.rosbag`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError
from stemmap.io._bag import (
    IMU,
    NAVSATFIX,
    ODOMETRY,
    _checked,
    _iter_messages,
    _skip,
    _stamp,
)
from stemmap.io._util import PathLike, SkippedFrame
from stemmap.io.maps import lonlat_to_local
from stemmap.io.trajectory import yaw_from_quaternion
from stemmap.types import FloatArray, Trajectory

# --------------------------------------------------------------------------------------------
# Odometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class OdometryLog:
    """``nav_msgs/Odometry`` messages as arrays, sorted by time.

    Attributes
    ----------
    times : ndarray (N,), seconds
    poses : ndarray (N, 3)
        x, y (m) and yaw (rad, in (-pi, pi]) of ``child_frame`` in ``frame``.
    z : ndarray (N,), metres
    quaternions : ndarray (N, 4)
        Full orientation ``(qx, qy, qz, qw)``.
    twists : ndarray (N, 3)
        Forward and lateral speed (m/s) and yaw rate (rad/s), in ``child_frame``.
    pose_cov : ndarray (N, 3, 3)
        Covariance over (x, y, yaw) taken from the 6x6 ROS covariance (rows/cols 0, 1, 5).
    frame, child_frame : str
    """

    times: FloatArray
    poses: FloatArray
    z: FloatArray
    quaternions: FloatArray
    twists: FloatArray
    pose_cov: FloatArray
    frame: str
    child_frame: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def trajectory(self) -> Trajectory:
        """The poses as a :class:`Trajectory` (later duplicates of a time stamp dropped)."""
        keep = np.concatenate(([True], np.diff(self.times) > 0))
        return Trajectory(self.times[keep], self.poses[keep], frame=self.frame)


def _sorted(times: FloatArray, *arrays: NDArray[Any]) -> list[NDArray[Any]]:
    order = np.argsort(times, kind="stable")
    return [times[order], *(a[order] for a in arrays)]


def read_odometry(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> OdometryLog:
    """Read every ``nav_msgs/Odometry`` message of a topic into an :class:`OdometryLog`.

    Messages with a NaN/inf or zero-quaternion pose are skipped and recorded.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Returns
    -------
    OdometryLog
        Sorted by ``header.stamp``; yaw by the z-y-x (ROS tf) convention.

    Raises
    ------
    InputError
        Bag unreadable, topic missing or ambiguous, or no usable message.
    """
    rows: list[list[float]] = []
    covs: list[NDArray[np.float64]] = []
    frame = child = ""
    for m in _checked(_iter_messages(path, ODOMETRY, topic), path, skipped):
        msg = m.msg
        try:
            pos, q = msg.pose.pose.position, msg.pose.pose.orientation
            lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
            row = [
                _stamp(msg.header, m.bag_time),
                pos.x,
                pos.y,
                pos.z,
                q.x,
                q.y,
                q.z,
                q.w,
                lin.x,
                lin.y,
                ang.z,
            ]
            cov6 = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
        except (AttributeError, TypeError, ValueError) as exc:
            _skip(skipped, path, m, f"Odometry message {m.seq} is malformed: {exc}")
            continue
        vals = np.asarray(row, dtype=np.float64)
        if not np.all(np.isfinite(vals[:8])) or not np.linalg.norm(vals[4:8]) > 0:
            _skip(skipped, path, m, f"Odometry message {m.seq} has a NaN/inf or zero pose")
            continue
        rows.append(row)
        covs.append(cov6[np.ix_([0, 1, 5], [0, 1, 5])])
        frame = frame or str(msg.header.frame_id)
        child = child or str(msg.child_frame_id)
    if not rows:
        raise InputError(f"ROS bag {str(path)!r} holds no usable nav_msgs/Odometry message.")
    a = np.asarray(rows)
    t, a, cov = _sorted(a[:, 0], a, np.asarray(covs))
    yaw = yaw_from_quaternion(a[:, 4:8])
    return OdometryLog(
        times=t,
        poses=np.column_stack((a[:, 1], a[:, 2], yaw)),
        z=a[:, 3],
        quaternions=a[:, 4:8],
        twists=a[:, 8:11],
        pose_cov=cov,
        frame=frame or "odom",
        child_frame=child or "base_link",
    )


# --------------------------------------------------------------------------------------------
# IMU
# --------------------------------------------------------------------------------------------


def roll_pitch_from_quaternion(q: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Roll and pitch (rad) of quaternions ``(qx, qy, qz, qw)`` (N, 4), z-y-x Euler (ROS tf).

    roll = atan2(2 (w x + y z), 1 - 2 (x^2 + y^2)); pitch = asin(2 (w y - z x)).
    """
    qa = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    qa = qa / np.linalg.norm(qa, axis=1, keepdims=True)
    x, y, z, w = qa.T
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    return roll, pitch


def roll_pitch_from_acceleration(acc: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Roll and pitch (rad) from accelerometer specific force (N, 3), valid when the sensor
    is not accelerating (gravity dominates).

    A level sensor reads (0, 0, +g). With the z-y-x convention the body-frame gravity reading
    is g (-sin p, sin r cos p, cos r cos p), hence roll = atan2(a_y, a_z) and
    pitch = atan2(-a_x, hypot(a_y, a_z)).
    """
    a = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    roll = np.arctan2(a[:, 1], a[:, 2])
    pitch = np.arctan2(-a[:, 0], np.hypot(a[:, 1], a[:, 2]))
    return roll, pitch


@dataclass(frozen=True, eq=False)
class ImuLog:
    """``sensor_msgs/Imu`` messages as arrays, sorted by time.

    Attributes
    ----------
    times : ndarray (N,), seconds
    roll, pitch : ndarray (N,), radians
        From the orientation quaternion when the message has one, else from the
        accelerometer (see :func:`roll_pitch_from_acceleration`); ``from_orientation`` says which.
    yaw : ndarray (N,), radians; NaN where the message had no orientation
    angular_velocity : ndarray (N, 3), rad/s
    linear_acceleration : ndarray (N, 3), m/s^2
    from_orientation : ndarray (N,) of bool
    frame : str
    """

    times: FloatArray
    roll: FloatArray
    pitch: FloatArray
    yaw: FloatArray
    angular_velocity: FloatArray
    linear_acceleration: FloatArray
    from_orientation: NDArray[np.bool_]
    frame: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def tilt_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Roll and pitch (rad) linearly interpolated at ``times`` (held at the ends)."""
        tq = np.asarray(times, dtype=np.float64)
        return np.interp(tq, self.times, self.roll), np.interp(tq, self.times, self.pitch)


def read_imu(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> ImuLog:
    """Read every ``sensor_msgs/Imu`` message of a topic into an :class:`ImuLog`.

    ROS marks "no orientation" with ``orientation_covariance[0] == -1``; those messages (and
    any with a zero/NaN quaternion) take roll and pitch from the accelerometer instead.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Returns
    -------
    ImuLog
        Sorted by time; ``from_orientation`` tells which source gave roll and pitch.

    Raises
    ------
    InputError
        Bag unreadable, topic missing or ambiguous, or no usable message.
    """
    rows: list[list[float]] = []
    has_q: list[bool] = []
    frame = ""
    for m in _checked(_iter_messages(path, IMU, topic), path, skipped):
        msg = m.msg
        try:
            q, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
            row = [_stamp(msg.header, m.bag_time), q.x, q.y, q.z, q.w, w.x, w.y, w.z, a.x, a.y]
            row.append(a.z)
            ocov0 = float(np.asarray(msg.orientation_covariance, dtype=np.float64)[0])
        except (AttributeError, TypeError, ValueError, IndexError) as exc:
            _skip(skipped, path, m, f"Imu message {m.seq} is malformed: {exc}")
            continue
        vals = np.asarray(row)
        qok = (
            ocov0 != -1.0
            and bool(np.all(np.isfinite(vals[1:5])))
            and (float(np.linalg.norm(vals[1:5])) > 0)
        )
        if not qok and not np.all(np.isfinite(vals[8:11])):
            _skip(skipped, path, m, f"Imu message {m.seq} has neither orientation nor gravity")
            continue
        rows.append(row)
        has_q.append(qok)
        frame = frame or str(msg.header.frame_id)
    if not rows:
        raise InputError(f"ROS bag {str(path)!r} holds no usable sensor_msgs/Imu message.")
    t, a, hq = _sorted(np.asarray(rows)[:, 0], np.asarray(rows), np.asarray(has_q))
    quat = np.where(hq[:, None], a[:, 1:5], np.array([0.0, 0.0, 0.0, 1.0]))
    r_q, p_q = roll_pitch_from_quaternion(quat)
    r_a, p_a = roll_pitch_from_acceleration(a[:, 8:11])
    yaw = np.where(hq, yaw_from_quaternion(quat), np.nan)
    return ImuLog(
        times=t,
        roll=np.where(hq, r_q, r_a),
        pitch=np.where(hq, p_q, p_a),
        yaw=yaw,
        angular_velocity=a[:, 5:8],
        linear_acceleration=a[:, 8:11],
        from_orientation=hq.astype(bool),
        frame=frame or "imu",
    )


# --------------------------------------------------------------------------------------------
# NavSatFix
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class GnssLog:
    """``sensor_msgs/NavSatFix`` messages as arrays, sorted by time.

    Attributes
    ----------
    times : ndarray (N,), seconds
    lat, lon : ndarray (N,), degrees (WGS84); alt : ndarray (N,), metres
    status : ndarray (N,) of int
        ROS NavSatStatus: -1 no fix, 0 fix, 1 SBAS-augmented, 2 ground-based augmentation (RTK).
    cov : ndarray (N, 3, 3), m^2, east-north-up
    cov_type : ndarray (N,) of int (0 unknown, 1 approximated, 2 diagonal known, 3 known)
    frame : str
    """

    times: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt: FloatArray
    status: NDArray[np.int64]
    cov: FloatArray
    cov_type: NDArray[np.int64]
    frame: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Fixes with status >= 0 and finite latitude/longitude."""
        return (self.status >= 0) & np.isfinite(self.lat) & np.isfinite(self.lon)

    def to_local(self, origin_lonlat: tuple[float, float] | None = None) -> FloatArray:
        """East-north metres (N, 2) around ``origin_lonlat`` (default: the first valid fix),
        by the tangent-plane approximation of :func:`stemmap.io.maps.lonlat_to_local`."""
        if origin_lonlat is None:
            v = np.flatnonzero(self.valid)
            if v.size == 0:
                raise InputError("the GNSS log has no valid fix to use as the local origin.")
            origin_lonlat = (float(self.lon[v[0]]), float(self.lat[v[0]]))
        return lonlat_to_local(self.lon, self.lat, origin_lonlat)


def read_navsatfix(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> GnssLog:
    """Read every ``sensor_msgs/NavSatFix`` message of a topic into a :class:`GnssLog`.

    Messages without a fix (status -1, or NaN position as some drivers send) are kept with
    their status so that gaps stay visible; use :attr:`GnssLog.valid` to filter.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Returns
    -------
    GnssLog
        Sorted by time; degrees, metres, ENU covariance in m^2.

    Raises
    ------
    InputError
        Bag unreadable, topic missing or ambiguous, or no message at all.
    """
    rows: list[list[float]] = []
    covs: list[NDArray[np.float64]] = []
    frame = ""
    for m in _checked(_iter_messages(path, NAVSATFIX, topic), path, skipped):
        msg = m.msg
        try:
            row = [
                _stamp(msg.header, m.bag_time),
                float(msg.latitude),
                float(msg.longitude),
                float(msg.altitude),
                int(msg.status.status),
                int(msg.position_covariance_type),
            ]
            cov = np.asarray(msg.position_covariance, dtype=np.float64).reshape(3, 3)
        except (AttributeError, TypeError, ValueError) as exc:
            _skip(skipped, path, m, f"NavSatFix message {m.seq} is malformed: {exc}")
            continue
        rows.append(row)
        covs.append(cov)
        frame = frame or str(msg.header.frame_id)
    if not rows:
        raise InputError(f"ROS bag {str(path)!r} holds no usable sensor_msgs/NavSatFix message.")
    a = np.asarray(rows)
    t, a, cov = _sorted(a[:, 0], a, np.asarray(covs))
    return GnssLog(
        times=t,
        lat=a[:, 1],
        lon=a[:, 2],
        alt=a[:, 3],
        status=a[:, 4].astype(np.int64),
        cov=cov,
        cov_type=a[:, 5].astype(np.int64),
        frame=frame or "gps",
    )
