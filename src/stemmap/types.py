"""Core value types shared by every part of stemmap.

Conventions (see docs/architecture.md):

* SI units everywhere: metres, radians, seconds.
* Angles counter-clockwise from the sensor's x axis (forward), wrapped to (-pi, pi].
* Every type that holds coordinates names its ``frame``.
* Point batches are ``(N, 2)`` or ``(N, 3)`` float64 arrays (GTSAM uses ``(2, N)``: convert at
  that boundary only).
* Arrays handed to a constructor are copied to float64 and made read-only, so a value can never
  be changed behind the back of whoever holds it.

Nothing here imports from the rest of the package.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError

__all__ = [
    "FloatArray",
    "LaserScan",
    "PointCloud",
    "Pose2",
    "ScanBatch",
    "StemMap",
    "StemObservation",
    "StemObservations",
    "Trajectory",
    "Tree",
    "wrap_angle",
]

FloatArray = NDArray[np.float64]


def wrap_angle(angle: ArrayLike) -> Any:
    """Wrap angles (radians) to (-pi, pi]. Works on scalars and arrays."""
    a = np.asarray(angle, dtype=np.float64)
    wrapped = np.pi - np.mod(np.pi - a, 2.0 * np.pi)
    return float(wrapped) if wrapped.ndim == 0 else wrapped


def _frozen_array(
    value: ArrayLike, name: str, *, ndim: int | None = None, dtype: Any = np.float64
) -> NDArray[Any]:
    """Copy ``value`` to a read-only array of ``dtype``; raise InputError on a bad shape/dtype."""
    try:
        arr = np.array(value, dtype=dtype, copy=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric, got {type(value).__name__}: {exc}") from exc
    if ndim is not None and arr.ndim != ndim:
        raise InputError(f"{name} must be {ndim}-dimensional, got shape {arr.shape}.")
    arr.setflags(write=False)
    return arr


def _finite_scalar(value: Any, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number, got {value!r}.") from exc
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {v}.")
    return v


# --------------------------------------------------------------------------------------------
# 2D laser
# --------------------------------------------------------------------------------------------


def _check_increment(value: Any, n_beams: int) -> float:
    """The angle increment as a float; InputError if zero or if the beams span > 360 deg.

    A scanner's beams cover at most one turn: ``|increment| * (n_beams - 1) <= 2 pi`` (a
    1-rad increment over 181 beams, or a 0, is a damaged header, never a real scan).
    """
    inc = _finite_scalar(value, "angle_increment")
    if inc == 0.0:
        raise InputError("angle_increment must be non-zero (radians between beams).")
    span = abs(inc) * max(n_beams - 1, 0)
    if span > 2.0 * math.pi + 1e-9:
        raise InputError(
            f"angle_increment {inc!r} rad over {n_beams} beams spans {math.degrees(span):.0f} "
            "degrees; a scan covers at most 360 (is the increment in degrees, or damaged?)."
        )
    return inc


@dataclass(frozen=True, eq=False)
class LaserScan:
    """One 2D laser scan; mirrors ROS ``sensor_msgs/LaserScan``.

    Parameters
    ----------
    ranges : ndarray of shape (N,), metres
        Beam ranges. NaN, inf, values ``<= range_min`` and ``>= range_max`` are "no return",
        never an error.
    angle_min : float, radians
        Angle of beam 0, counter-clockwise from the sensor's x axis.
    angle_increment : float, radians, non-zero
        Angle between consecutive beams (negative for clockwise scanners).
    time : float, seconds
        Acquisition time of the scan.
    range_min, range_max : float, metres
        Valid range window of the sensor.
    intensities : ndarray of shape (N,), optional
    frame : str
        Name of the sensor frame the ranges are measured in.

    Raises
    ------
    InputError
        If ``ranges`` is not 1-D numeric, ``intensities`` has a different length, the angle
        increment is zero or not finite, or the range window is empty.
    """

    ranges: FloatArray
    angle_min: float
    angle_increment: float
    time: float = 0.0
    range_min: float = 0.0
    range_max: float = math.inf
    intensities: FloatArray | None = None
    frame: str = "laser"

    def __post_init__(self) -> None:
        ranges = _frozen_array(self.ranges, "LaserScan.ranges", ndim=1)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "angle_min", _finite_scalar(self.angle_min, "angle_min"))
        inc = _check_increment(self.angle_increment, ranges.shape[-1])
        object.__setattr__(self, "angle_increment", inc)
        object.__setattr__(self, "time", _finite_scalar(self.time, "time"))
        rmin = float(self.range_min)
        rmax = float(self.range_max)
        if not (rmin >= 0.0 and rmax > rmin):
            raise InputError(
                f"range window must satisfy 0 <= range_min < range_max, got [{rmin}, {rmax}]."
            )
        object.__setattr__(self, "range_min", rmin)
        object.__setattr__(self, "range_max", rmax)
        if self.intensities is not None:
            inten = _frozen_array(self.intensities, "LaserScan.intensities", ndim=1)
            if inten.shape != ranges.shape:
                raise InputError(
                    f"intensities has {inten.shape[0]} values but ranges has {ranges.shape[0]}."
                )
            object.__setattr__(self, "intensities", inten)

    def __len__(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def angles(self) -> FloatArray:
        """Beam angles, shape (N,), radians (not wrapped: beam order is preserved)."""
        return self.angle_min + self.angle_increment * np.arange(len(self), dtype=np.float64)

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Mask of beams with a return inside (range_min, range_max)."""
        r = self.ranges
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r > self.range_min) & (r < self.range_max)

    def points(self) -> FloatArray:
        """Cartesian points of the valid returns, shape (M, 2), in ``frame``."""
        m = self.valid
        a = self.angles[m]
        r = self.ranges[m]
        return np.column_stack((r * np.cos(a), r * np.sin(a)))


@dataclass(frozen=True, eq=False)
class ScanBatch:
    """Many scans of one sensor, stored as one (S, N) array for vectorised processing.

    Same semantics as :class:`LaserScan` per row; ``times`` has shape (S,).
    """

    ranges: FloatArray
    times: FloatArray
    angle_min: float
    angle_increment: float
    range_min: float = 0.0
    range_max: float = math.inf
    frame: str = "laser"

    def __post_init__(self) -> None:
        ranges = _frozen_array(self.ranges, "ScanBatch.ranges", ndim=2)
        times = _frozen_array(self.times, "ScanBatch.times", ndim=1)
        if times.shape[0] != ranges.shape[0]:
            raise InputError(
                f"ScanBatch has {ranges.shape[0]} scans but {times.shape[0]} timestamps."
            )
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "angle_min", _finite_scalar(self.angle_min, "angle_min"))
        inc = _check_increment(self.angle_increment, ranges.shape[-1])
        object.__setattr__(self, "angle_increment", inc)
        rmin, rmax = float(self.range_min), float(self.range_max)
        if not (rmin >= 0.0 and rmax > rmin):
            raise InputError(
                f"range window must satisfy 0 <= range_min < range_max, got [{rmin}, {rmax}]."
            )
        object.__setattr__(self, "range_min", rmin)
        object.__setattr__(self, "range_max", rmax)

    def __len__(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def n_beams(self) -> int:
        return int(self.ranges.shape[1])

    @property
    def angles(self) -> FloatArray:
        return self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)

    def __getitem__(self, i: int) -> LaserScan:
        return LaserScan(
            self.ranges[i],
            self.angle_min,
            self.angle_increment,
            time=float(self.times[i]),
            range_min=self.range_min,
            range_max=self.range_max,
            frame=self.frame,
        )

    def __iter__(self) -> Iterator[LaserScan]:
        for i in range(len(self)):
            yield self[i]

    @classmethod
    def from_scans(cls, scans: Sequence[LaserScan]) -> ScanBatch:
        """Stack scans of one sensor; raise InputError if their geometry differs."""
        if not scans:
            raise InputError("cannot build a ScanBatch from zero scans.")
        s0 = scans[0]
        for k, s in enumerate(scans):
            if (
                len(s) != len(s0)
                or s.angle_min != s0.angle_min
                or s.angle_increment != s0.angle_increment
            ):
                raise InputError(
                    f"scan {k} has a different beam geometry than scan 0 "
                    f"({len(s)} beams from {s.angle_min} rad vs {len(s0)} from {s0.angle_min})."
                )
        return cls(
            np.stack([s.ranges for s in scans]),
            np.array([s.time for s in scans]),
            s0.angle_min,
            s0.angle_increment,
            s0.range_min,
            s0.range_max,
            s0.frame,
        )


# --------------------------------------------------------------------------------------------
# 3D
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PointCloud:
    """A 3D point cloud.

    Parameters
    ----------
    xyz : ndarray of shape (N, 3), metres
    time : float, seconds
    frame : str
    fields : dict of str to ndarray of shape (N,)
        Extra per-point fields (intensity, ring, return number, ...).
    """

    xyz: FloatArray
    time: float = 0.0
    frame: str = "lidar"
    fields: dict[str, NDArray[Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        xyz = _frozen_array(self.xyz, "PointCloud.xyz", ndim=2)
        if xyz.shape[1] != 3:
            raise InputError(f"PointCloud.xyz must have shape (N, 3), got {xyz.shape}.")
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "time", _finite_scalar(self.time, "time"))
        fields = {}
        for k, v in self.fields.items():
            arr = np.array(v, copy=True)
            if arr.shape[:1] != (xyz.shape[0],):
                raise InputError(
                    f"PointCloud field {k!r} has {arr.shape[:1]} values for {xyz.shape[0]} points."
                )
            arr.setflags(write=False)
            fields[k] = arr
        object.__setattr__(self, "fields", fields)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


# --------------------------------------------------------------------------------------------
# Stem observations (one frame) -- single record and columnar batch
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class StemObservation:
    """One trunk seen in one frame.

    Parameters
    ----------
    center : ndarray of shape (2,), metres, in ``frame``
    radius : float, metres
    cov : ndarray of shape (3, 3)
        Covariance over (x, y, r), m^2. NaN where the method cannot estimate it.
    n_points : int
        Returns (pixels, points) supporting the observation.
    arc_deg : float
        Angular extent of the visible arc around the fitted centre, degrees.
    width : float, metres
        Chord width of the visible part (Xue eq. 12), NaN if not measured.
    quality : float in [0, 1]
    source : str
        Producer, e.g. ``"scan:ours"``, ``"cloud:munjer2025"``.
    frame : str
    time : float, seconds
    """

    center: FloatArray
    radius: float
    cov: FloatArray
    n_points: int = 0
    arc_deg: float = math.nan
    width: float = math.nan
    quality: float = 1.0
    source: str = ""
    frame: str = "laser"
    time: float = 0.0

    def __post_init__(self) -> None:
        c = _frozen_array(self.center, "StemObservation.center", ndim=1)
        if c.shape != (2,):
            raise InputError(f"center must have shape (2,), got {c.shape}.")
        object.__setattr__(self, "center", c)
        cov = _frozen_array(self.cov, "StemObservation.cov", ndim=2)
        if cov.shape != (3, 3):
            raise InputError(f"cov must have shape (3, 3), got {cov.shape}.")
        object.__setattr__(self, "cov", cov)

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius


_OBS_COLUMNS = ("centers", "radii", "covs", "n_points", "arc_deg", "widths", "quality", "index")


@dataclass(frozen=True, eq=False)
class StemObservations:
    """A columnar batch of stem observations (hot paths use this, not lists of objects).

    Parameters
    ----------
    centers : ndarray of shape (K, 2), metres
    radii : ndarray of shape (K,), metres
    covs : ndarray of shape (K, 3, 3) over (x, y, r)
    n_points : ndarray of shape (K,), int
    arc_deg, widths, quality : ndarray of shape (K,)
    index : ndarray of shape (K,), int
        Frame (scan / image / cloud) index each observation came from.
    times : ndarray of shape (K,), seconds
    source, frame : str
    """

    centers: FloatArray
    radii: FloatArray
    covs: FloatArray
    n_points: NDArray[np.int64]
    arc_deg: FloatArray
    widths: FloatArray
    quality: FloatArray
    index: NDArray[np.int64]
    times: FloatArray
    source: str = ""
    frame: str = "laser"

    def __post_init__(self) -> None:
        centers = _frozen_array(self.centers, "centers").reshape(-1, 2)
        k = centers.shape[0]
        object.__setattr__(self, "centers", centers)
        covs = _frozen_array(self.covs, "covs").reshape(k, 3, 3)
        object.__setattr__(self, "covs", covs)
        for name in ("radii", "arc_deg", "widths", "quality", "times"):
            arr = _frozen_array(getattr(self, name), name).reshape(-1)
            if arr.shape[0] != k:
                raise InputError(f"StemObservations.{name} has {arr.shape[0]} values, need {k}.")
            object.__setattr__(self, name, arr)
        for name in ("n_points", "index"):
            arr = _frozen_array(getattr(self, name), name, dtype=np.int64).reshape(-1)
            if arr.shape[0] != k:
                raise InputError(f"StemObservations.{name} has {arr.shape[0]} values, need {k}.")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    @property
    def diameters(self) -> FloatArray:
        return 2.0 * self.radii

    def __getitem__(self, i: int) -> StemObservation:
        return StemObservation(
            center=self.centers[i],
            radius=float(self.radii[i]),
            cov=self.covs[i],
            n_points=int(self.n_points[i]),
            arc_deg=float(self.arc_deg[i]),
            width=float(self.widths[i]),
            quality=float(self.quality[i]),
            source=self.source,
            frame=self.frame,
            time=float(self.times[i]),
        )

    def __iter__(self) -> Iterator[StemObservation]:
        for i in range(len(self)):
            yield self[i]

    def select(self, mask_or_index: ArrayLike) -> StemObservations:
        """Subset by boolean mask or integer index array."""
        sel = np.asarray(mask_or_index)
        return StemObservations(
            centers=self.centers[sel],
            radii=self.radii[sel],
            covs=self.covs[sel],
            n_points=self.n_points[sel],
            arc_deg=self.arc_deg[sel],
            widths=self.widths[sel],
            quality=self.quality[sel],
            index=self.index[sel],
            times=self.times[sel],
            source=self.source,
            frame=self.frame,
        )

    @classmethod
    def empty(cls, source: str = "", frame: str = "laser") -> StemObservations:
        z = np.zeros(0)
        zi = np.zeros(0, dtype=np.int64)
        return cls(
            np.zeros((0, 2)), z, np.zeros((0, 3, 3)), zi, z, z, z, zi, z, source=source, frame=frame
        )

    @classmethod
    def from_records(
        cls, records: Sequence[StemObservation], index: ArrayLike | None = None
    ) -> StemObservations:
        """Build a batch from single observations (not for hot paths)."""
        if not records:
            return cls.empty()
        idx = np.zeros(len(records), dtype=np.int64) if index is None else np.asarray(index)
        return cls(
            centers=np.array([r.center for r in records]),
            radii=np.array([r.radius for r in records]),
            covs=np.array([r.cov for r in records]),
            n_points=np.array([r.n_points for r in records]),
            arc_deg=np.array([r.arc_deg for r in records]),
            widths=np.array([r.width for r in records]),
            quality=np.array([r.quality for r in records]),
            index=idx,
            times=np.array([r.time for r in records]),
            source=records[0].source,
            frame=records[0].frame,
        )

    @classmethod
    def concatenate(cls, parts: Sequence[StemObservations]) -> StemObservations:
        """Join batches of the same source and frame."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(
            **{c: np.concatenate([getattr(p, c) for p in parts]) for c in _OBS_COLUMNS},
            times=np.concatenate([p.times for p in parts]),
            source=parts[0].source,
            frame=parts[0].frame,
        )


# --------------------------------------------------------------------------------------------
# Poses, trajectories, maps
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pose2:
    """A planar pose: position (m) and heading (rad, wrapped to (-pi, pi])."""

    x: float
    y: float
    theta: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "x", _finite_scalar(self.x, "Pose2.x"))
        object.__setattr__(self, "y", _finite_scalar(self.y, "Pose2.y"))
        object.__setattr__(self, "theta", wrap_angle(_finite_scalar(self.theta, "Pose2.theta")))

    def as_array(self) -> FloatArray:
        return np.array([self.x, self.y, self.theta])

    def compose(self, other: Pose2) -> Pose2:
        """``self * other``: ``other`` expressed in this pose's frame, mapped to the world."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            self.theta + other.theta,
        )

    def inverse(self) -> Pose2:
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2(-c * self.x - s * self.y, s * self.x - c * self.y, -self.theta)

    def transform_points(self, points: ArrayLike) -> FloatArray:
        """Map (N, 2) points from this pose's local frame to the parent frame."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.theta), math.sin(self.theta)
        return p @ np.array([[c, s], [-s, c]]) + np.array([self.x, self.y])


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timed planar poses.

    ``times`` (N,) seconds, strictly increasing; ``poses`` (N, 3) as x, y (m), theta (rad).
    """

    times: FloatArray
    poses: FloatArray
    frame: str = "map"

    def __post_init__(self) -> None:
        t = _frozen_array(self.times, "Trajectory.times", ndim=1)
        p = _frozen_array(self.poses, "Trajectory.poses", ndim=2)
        if p.shape != (t.shape[0], 3):
            raise InputError(f"Trajectory.poses must have shape ({t.shape[0]}, 3), got {p.shape}.")
        if t.shape[0] > 1 and not np.all(np.diff(t) > 0):
            k = int(np.argmin(np.diff(t)))
            raise InputError(
                f"Trajectory.times must be strictly increasing; time goes from {t[k]} to "
                f"{t[k + 1]} at index {k + 1}."
            )
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "poses", p)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def xy(self) -> FloatArray:
        return self.poses[:, :2]

    def interpolate(self, times: ArrayLike) -> FloatArray:
        """Poses at ``times`` (linear in x, y; shortest-arc in theta), shape (M, 3)."""
        tq = np.asarray(times, dtype=np.float64)
        x = np.interp(tq, self.times, self.poses[:, 0])
        y = np.interp(tq, self.times, self.poses[:, 1])
        th = np.unwrap(self.poses[:, 2])
        return np.column_stack((x, y, wrap_angle(np.interp(tq, self.times, th))))


@dataclass(frozen=True, eq=False)
class Tree:
    """One mapped tree: position (m, in the map frame), diameter (m), covariance over (x, y)."""

    id: int
    x: float
    y: float
    diameter: float
    cov: FloatArray = field(default_factory=lambda: np.full((2, 2), np.nan))
    n_obs: int = 0
    first_time: float = math.nan
    last_time: float = math.nan
    confidence: float = 1.0
    diameter_std: float = math.nan

    def __post_init__(self) -> None:
        cov = _frozen_array(self.cov, "Tree.cov", ndim=2)
        if cov.shape != (2, 2):
            raise InputError(f"Tree.cov must have shape (2, 2), got {cov.shape}.")
        object.__setattr__(self, "cov", cov)

    @property
    def std_xy(self) -> tuple[float, float]:
        return float(np.sqrt(self.cov[0, 0])), float(np.sqrt(self.cov[1, 1]))


@dataclass(frozen=True, eq=False)
class StemMap:
    """A stem map: trees in ``frame``; ``crs`` is an EPSG code or WKT when georeferenced.

    ``information`` (optional, from :class:`stemmap.slam.graph.Isam2Slam` with
    ``joint_information=True``): the (2N, 2N) joint information matrix of the trees' positions
    in tree order ``(x_0, y_0, x_1, ...)``, 1/m², every pose marginalised out. It keeps the
    correlations the per-tree ``cov`` blocks drop; a later session continues from it
    (:func:`stemmap.slam.relocalise.joint_prior_factor`).
    """

    trees: tuple[Tree, ...]
    frame: str = "map"
    crs: str | None = None
    information: FloatArray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "trees", tuple(self.trees))
        if self.information is not None:
            info = _frozen_array(self.information, "StemMap.information", ndim=2)
            n2 = 2 * len(self.trees)
            if info.shape != (n2, n2):
                raise InputError(
                    f"StemMap.information must have shape ({n2}, {n2}) for {len(self.trees)} "
                    f"trees, got {info.shape}."
                )
            object.__setattr__(self, "information", info)

    def __len__(self) -> int:
        return len(self.trees)

    def __iter__(self) -> Iterator[Tree]:
        return iter(self.trees)

    @property
    def xy(self) -> FloatArray:
        if not self.trees:
            return np.zeros((0, 2))
        return np.array([[t.x, t.y] for t in self.trees])

    @property
    def diameters(self) -> FloatArray:
        return np.array([t.diameter for t in self.trees], dtype=np.float64)
