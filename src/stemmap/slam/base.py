"""The SLAM interface every back-end builds to: inputs, problem, result, registry.

Inputs are columnar (numpy arrays, not lists of objects): :class:`Controls` (odometry) and
:class:`TreeFrames` (per-scan tree detections, polar in the sensor frame). A
:class:`SlamProblem` ties them to a motion model and the sensor's mounting; a back-end
(:class:`SlamBackend`) turns it into a :class:`SlamResult` (trajectory + stem map + stats).

Observation model shared by all back-ends (sensor at ``sensor_offset = (a, b)`` in the vehicle
frame, pose ``(x, y, theta)`` of the vehicle reference point)::

    s = (x + a cos(theta) - b sin(theta),  y + a sin(theta) + b cos(theta))
    range   = |m - s|
    bearing = atan2(m_y - s_y, m_x - s_x) - theta        (CCW from the vehicle's forward axis)
"""

from __future__ import annotations

import contextlib
import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.slam.motion import MotionModel, rollout
from stemmap.types import FloatArray, StemMap, StemObservations, Trajectory, wrap_angle

if TYPE_CHECKING:
    from stemmap.slam.gnss import GnssFixes

__all__ = [
    "BACKENDS",
    "Controls",
    "IntArray",
    "SlamBackend",
    "SlamProblem",
    "SlamResult",
    "TreeFrames",
    "dead_reckoning",
    "duplicate_pairs",
    "make_backend",
    "observation_to_world",
    "observe",
    "sensor_poses",
    "single_threaded_blas",
]

IntArray = NDArray[np.int64]


def _ro(value: ArrayLike, name: str, dtype: Any = np.float64) -> NDArray[Any]:
    try:
        arr = np.array(value, dtype=dtype, copy=True).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric, got {type(value).__name__}: {exc}") from exc
    arr.setflags(write=False)
    return arr


def _check_nondecreasing(t: FloatArray, name: str) -> None:
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"{name} must be finite; value {t[k]} at index {k}.")
    if t.shape[0] > 1:
        d = np.diff(t)
        if np.any(d < 0):
            k = int(np.flatnonzero(d < 0)[0])
            raise InputError(
                f"{name} must be non-decreasing; time goes backwards from {t[k]} s to "
                f"{t[k + 1]} s at index {k + 1}."
            )


@dataclass(frozen=True, eq=False)
class Controls:
    """Odometry inputs, time-ordered.

    Parameters
    ----------
    times : ndarray (M,), s, non-decreasing
    speed : ndarray (M,), m/s
        Victoria Park: speed of the left rear wheel (encoder).
    steer : ndarray (M,)
        Front steering angle, rad (``kind="ackermann"``), or yaw rate, rad/s (``"unicycle"``).
    kind : {"ackermann", "unicycle"}

    Raises
    ------
    InputError
        On length mismatch, non-finite values, time going backwards or an unknown kind.
    """

    times: FloatArray
    speed: FloatArray
    steer: FloatArray
    kind: Literal["ackermann", "unicycle"]

    def __post_init__(self) -> None:
        if self.kind not in ("ackermann", "unicycle"):
            raise InputError(f"Controls.kind must be 'ackermann' or 'unicycle', got {self.kind!r}.")
        t = _ro(self.times, "Controls.times")
        _check_nondecreasing(t, "Controls.times")
        object.__setattr__(self, "times", t)
        for name in ("speed", "steer"):
            arr = _ro(getattr(self, name), f"Controls.{name}")
            if arr.shape != t.shape:
                raise InputError(
                    f"Controls.{name} has {arr.shape[0]} values but times has {t.shape[0]}."
                )
            if not np.all(np.isfinite(arr)):
                k = int(np.flatnonzero(~np.isfinite(arr))[0])
                raise InputError(f"Controls.{name} must be finite; value {arr[k]} at index {k}.")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @classmethod
    def from_trajectory(cls, trajectory: Trajectory, *, turn_fraction: float = 0.1) -> Controls:
        """Unicycle controls that dead-reckon exactly through every pose of a pose-output
        odometry (lidar + IMU, visual, fused, a SLAM front end), its lateral steps included.

        Each interval ``[t_k, t_k+1]`` carries the body-frame increment
        ``(dx, dy, dθ) = between(p_k, p_k+1)`` (:func:`~stemmap.slam.motion.between`). The
        unicycle's chord model (:mod:`stemmap.slam.motion`: ``x' = x + ds cos(θ + γ / 2)``) has
        two controls per step, so an increment is an arc only when its chord points along the
        mid heading, ``atan2(dy, dx) = dθ / 2``; an EKF path after a pose update (the fused
        visual + lidar odometry, the lidar + IMU odometry of Munjer et al. 2025 §3.5) also
        steps sideways. The interval is then split in two: an arc over the first
        ``1 - turn_fraction`` of it, whose chord lands on ``(dx, dy)`` (``ds = ±|(dx, dy)|``,
        ``γ = 2 atan2(dy, dx)``, driven backwards when the chord points behind), and a turn on
        the spot by the rest, ``dθ - γ``, over the last ``turn_fraction``. An arc increment
        (wheel odometry, the speed-and-yaw-rate path) stays one control, the same as its
        velocity; a pure rotation is one turn. After the last pose the last interval's mean
        velocity ``(ds, dθ) / dt`` is held, as a velocity source is.

        The poses at ``trajectory.times`` are exact for any ``turn_fraction`` in (0, 1); it
        shapes only the poses between them (a frame inside an interval) and how the interval's
        control noise is split: the unicycle noise is per second of driving, independent of
        the control values (``UnicycleModel.arc_jacobian = diag(dt, dt)``), so the interval's
        speed and yaw-rate variance stays ``σ² dt`` and the turn takes ``turn_fraction`` of it
        (docs/algorithms/slam.md, "Controls from a pose trajectory").

        Parameters
        ----------
        trajectory : Trajectory
            At least 2 poses, strictly increasing times.
        turn_fraction : float, in (0, 1)
            Share of a split interval given to the turn on the spot.

        Raises
        ------
        InputError
            If the trajectory has fewer than 2 poses.
        ConfigError
            If ``turn_fraction`` is outside (0, 1).
        """
        from stemmap.slam.motion import between

        if not (0.0 < turn_fraction < 1.0):
            raise ConfigError(f"turn_fraction must lie in (0, 1), got {turn_fraction}.")
        t = np.asarray(trajectory.times, dtype=np.float64)
        p = np.asarray(trajectory.poses, dtype=np.float64)
        if t.shape[0] < 2:
            raise InputError(f"Controls.from_trajectory needs at least 2 poses, got {t.shape[0]}.")
        d = between(p[:-1], p[1:])
        dist = np.hypot(d[:, 0], d[:, 1])
        chord = np.arctan2(d[:, 1], d[:, 0])
        back = np.abs(chord) > 0.5 * math.pi  # drive backwards rather than turn round
        chord = np.where(back, chord - np.copysign(math.pi, chord), chord)
        chord = np.where(dist > 0.0, chord, 0.5 * d[:, 2])  # standing still: one turn
        ds = np.where(back, -dist, dist)
        arc = 2.0 * chord
        turn = wrap_angle(d[:, 2] - arc)
        t_mid = t[:-1] + (1.0 - turn_fraction) * np.diff(t)
        split = (np.abs(turn) > 1e-12) & (t_mid > t[:-1]) & (t_mid < t[1:])
        t_mid = np.where(split, t_mid, t[1:])
        h_arc = t_mid - t[:-1]  # the same float differences preintegrate() takes
        h_turn = np.where(split, t[1:] - t_mid, 1.0)
        arc = np.where(split, arc, d[:, 2])
        rows = np.stack(
            (
                np.column_stack((t[:-1], ds / h_arc, arc / h_arc)),
                np.column_stack((t_mid, np.zeros_like(ds), turn / h_turn)),
            ),
            axis=1,
        )[np.column_stack((np.ones_like(split), split))]
        dt = t[-1] - t[-2]
        last = np.array([[t[-1], ds[-1] / dt, d[-1, 2] / dt]])
        u = np.concatenate((rows, last))
        return cls(u[:, 0], u[:, 1], u[:, 2], "unicycle")

    def slice(self, t0: float, t1: float) -> Controls:
        """Controls with ``t0 <= time <= t1`` plus the last one before ``t0`` (the hold value)."""
        i0 = max(int(np.searchsorted(self.times, t0, side="right")) - 1, 0)
        i1 = int(np.searchsorted(self.times, t1, side="right"))
        s = slice(i0, i1)
        return Controls(self.times[s], self.speed[s], self.steer[s], self.kind)


@dataclass(frozen=True, eq=False)
class TreeFrames:
    """Tree detections, columnar, one frame per scan; polar coordinates in the SENSOR frame.

    Parameters
    ----------
    times : ndarray (F,), s, non-decreasing
    ptr : ndarray (F+1,), int
        Detections of frame ``f`` are ``[ptr[f], ptr[f+1])``; ``ptr[0] == 0``, ``ptr[-1] == K``.
    ranges : ndarray (K,), m, > 0
    bearings : ndarray (K,), rad, CCW from the sensor's forward axis, wrapped to (-pi, pi]
    diameters : ndarray (K,), m (NaN if unknown)
    noise : ndarray (K, 2) or None
        Each detection's own measurement noise (sigma_range m, sigma_bearing rad), NaN where
        the detector gives none (e.g. DAIM's depth-noise model,
        :func:`stemmap.vision.depth.daim_trunks`). Only back ends asked to use it do
        (:class:`stemmap.slam.fastslam.FastSlam` ``detection_noise``, the Kalman refinement);
        the others use their constant R.
    diameter_std : ndarray (K,) or None
        Each detection's own diameter standard deviation, m (the fit's, ``2 sqrt(cov_rr)``;
        NaN where unknown). :func:`stemmap.slam.uncertainty.annotate_uncertainty` weights a
        tree's diameters by it (:func:`~stemmap.slam.uncertainty.fused_diameters`); None: every
        detection counts the same.
    noise_cov : ndarray (K, 2, 2) or None
        Each detection's full (range, bearing) covariance (m^2, m rad, rad^2), NaN where the
        detector gives none: ``noise`` is the square root of its diagonal, this keeps the
        range-bearing correlation ``noise`` drops. Read only by the covariance the tree DB and
        Forestrix report for their trees (:mod:`stemmap.slam.tree_covariance`,
        ``detection_covs``); no estimate reads it.
    """

    times: FloatArray
    ptr: IntArray
    ranges: FloatArray
    bearings: FloatArray
    diameters: FloatArray
    noise: FloatArray | None = None
    diameter_std: FloatArray | None = None
    noise_cov: FloatArray | None = None

    def __post_init__(self) -> None:
        t = _ro(self.times, "TreeFrames.times")
        _check_nondecreasing(t, "TreeFrames.times")
        ptr = _ro(self.ptr, "TreeFrames.ptr", dtype=np.int64)
        r = _ro(self.ranges, "TreeFrames.ranges")
        k = r.shape[0]
        if ptr.shape[0] != t.shape[0] + 1:
            raise InputError(
                f"TreeFrames.ptr must have {t.shape[0] + 1} entries (frames + 1), "
                f"got {ptr.shape[0]}."
            )
        if ptr[0] != 0 or ptr[-1] != k or np.any(np.diff(ptr) < 0):
            raise InputError(
                f"TreeFrames.ptr must rise from 0 to the number of detections ({k}); "
                f"got {ptr[0]} .. {ptr[-1]}."
            )
        b = _ro(self.bearings, "TreeFrames.bearings")
        d = _ro(self.diameters, "TreeFrames.diameters")
        for name, arr in (("bearings", b), ("diameters", d)):
            if arr.shape[0] != k:
                raise InputError(f"TreeFrames.{name} has {arr.shape[0]} values but ranges has {k}.")
        if not np.all(np.isfinite(r) & (r > 0)):
            i = int(np.flatnonzero(~(np.isfinite(r) & (r > 0)))[0])
            raise InputError(f"TreeFrames.ranges must be finite and > 0; value {r[i]} at {i}.")
        if not np.all(np.isfinite(b)):
            i = int(np.flatnonzero(~np.isfinite(b))[0])
            raise InputError(f"TreeFrames.bearings must be finite; value {b[i]} at {i}.")
        bw = wrap_angle(b)
        bw = np.asarray(bw, dtype=np.float64).reshape(-1)
        bw.setflags(write=False)
        if self.noise is not None:
            nz = np.array(self.noise, dtype=np.float64, copy=True)
            if nz.shape != (k, 2) or np.any(nz[np.isfinite(nz)] < 0):
                raise InputError(
                    f"TreeFrames.noise must be ({k}, 2) sigmas >= 0 or NaN, got shape {nz.shape}."
                )
            nz.setflags(write=False)
            object.__setattr__(self, "noise", nz)
        if self.diameter_std is not None:
            ds = np.array(self.diameter_std, dtype=np.float64, copy=True).reshape(-1)
            if ds.shape != (k,) or np.any(ds[np.isfinite(ds)] < 0):
                raise InputError(
                    f"TreeFrames.diameter_std must be ({k},) sigmas >= 0 or NaN, got shape "
                    f"{ds.shape}."
                )
            ds.setflags(write=False)
            object.__setattr__(self, "diameter_std", ds)
        if self.noise_cov is not None:
            nc = np.array(self.noise_cov, dtype=np.float64, copy=True)
            fin = np.all(np.isfinite(nc), axis=(1, 2)) if nc.ndim == 3 else np.zeros(0, bool)
            if nc.shape != (k, 2, 2) or np.any((nc[fin][:, 0, 0] < 0) | (nc[fin][:, 1, 1] < 0)):
                raise InputError(
                    f"TreeFrames.noise_cov must be ({k}, 2, 2) covariances or NaN, got shape "
                    f"{nc.shape}."
                )
            nc.setflags(write=False)
            object.__setattr__(self, "noise_cov", nc)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "ptr", ptr)
        object.__setattr__(self, "ranges", r)
        object.__setattr__(self, "bearings", bw)
        object.__setattr__(self, "diameters", d)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def n_detections(self) -> int:
        return int(self.ranges.shape[0])

    def frame(self, f: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(ranges, bearings, diameters)`` of frame ``f`` (views)."""
        s = slice(int(self.ptr[f]), int(self.ptr[f + 1]))
        return self.ranges[s], self.bearings[s], self.diameters[s]

    @property
    def frame_index(self) -> IntArray:
        """Frame index of every detection, shape (K,)."""
        return np.repeat(np.arange(len(self), dtype=np.int64), np.diff(self.ptr))

    def select_frames(self, start: int, stop: int) -> TreeFrames:
        """Frames ``start:stop`` (detections re-based)."""
        p0, p1 = int(self.ptr[start]), int(self.ptr[stop])
        s = slice(p0, p1)
        return TreeFrames(
            self.times[start:stop],
            self.ptr[start : stop + 1] - p0,
            self.ranges[s],
            self.bearings[s],
            self.diameters[s],
            None if self.noise is None else self.noise[s],
            None if self.diameter_std is None else self.diameter_std[s],
            None if self.noise_cov is None else self.noise_cov[s],
        )

    def slice(self, t0: float, t1: float) -> TreeFrames:
        """Frames with ``t0 <= time <= t1``."""
        a = int(np.searchsorted(self.times, t0, side="left"))
        b = int(np.searchsorted(self.times, t1, side="right"))
        return self.select_frames(a, b)

    @classmethod
    def from_observations(cls, obs: StemObservations, times: ArrayLike) -> TreeFrames:
        """Build frames from a detector's batch; ``obs.index`` gives each one's frame in ``times``.

        Observation centres must be in the sensor frame; range and bearing are computed from
        them, the diameter is ``2 * radius``. Where ``obs.covs`` has a finite (x, y) block, its
        polar form ``J C J^T`` (``J = d(range, bearing) / d(x, y)``) gives ``noise`` (the
        square roots of its diagonal) and ``noise_cov`` (the whole of it); both are None when no
        detection has one. A finite
        radius variance ``obs.covs[:, 2, 2]`` gives ``diameter_std`` (``2 sqrt(cov_rr)``; None
        when no detection has one).
        """
        t = _ro(times, "times")
        idx = np.asarray(obs.index, dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= t.shape[0]):
            raise InputError(
                f"StemObservations.index must lie in [0, {t.shape[0]}) (one per frame time); "
                f"got values in [{idx.min()}, {idx.max()}]."
            )
        order = np.argsort(idx, kind="stable")
        c = obs.centers[order]
        counts = np.bincount(idx, minlength=t.shape[0])
        ptr = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
        rng = np.hypot(c[:, 0], c[:, 1])
        noise = polar = None
        cxy = np.asarray(obs.covs, dtype=np.float64)[order][:, :2, :2]
        if cxy.size and np.any(np.all(np.isfinite(cxy), axis=(1, 2))):
            rs = np.where(rng > 0, rng, 1.0)
            J = np.zeros((rng.shape[0], 2, 2))
            J[:, 0, 0], J[:, 0, 1] = c[:, 0] / rs, c[:, 1] / rs
            J[:, 1, 0], J[:, 1, 1] = -c[:, 1] / rs**2, c[:, 0] / rs**2
            polar = J @ cxy @ np.swapaxes(J, 1, 2)
            noise = np.sqrt(np.clip(np.diagonal(polar, axis1=1, axis2=2), 0.0, None))
            polar = 0.5 * (polar + np.swapaxes(polar, 1, 2))
        dstd = None
        crr = np.asarray(obs.covs, dtype=np.float64)[order][:, 2, 2] if rng.size else np.zeros(0)
        if np.any(np.isfinite(crr)):
            dstd = 2.0 * np.sqrt(np.clip(crr, 0.0, None))
        return cls(
            t,
            ptr,
            rng,
            np.arctan2(c[:, 1], c[:, 0]),
            2.0 * np.asarray(obs.radii)[order],
            noise,
            dstd,
            polar,
        )

    @classmethod
    def empty_frames(cls, times: ArrayLike) -> TreeFrames:
        t = _ro(times, "times")
        z = np.zeros(0)
        return cls(t, np.zeros(t.shape[0] + 1, dtype=np.int64), z, z, z)


@dataclass(frozen=True, eq=False)
class SlamProblem:
    """Everything a back-end needs.

    Parameters
    ----------
    controls : Controls
    frames : TreeFrames
    motion : MotionModel
        Must accept ``controls`` (e.g. :class:`~stemmap.slam.motion.AckermannModel` for
        ``kind="ackermann"``).
    sensor_offset : (a, b), m
        Sensor position in the vehicle frame (forward, left).
    initial_pose : (x, y, theta)
        Vehicle pose at ``frames.times[0]``.
    name : str
    max_range : float, m
        The sensor's declared range: how far the detector can report a tree (a scan file's
        ``range_max``, Victoria Park's 80 m; default inf = not declared). A declaration, not
        a filter of the detections: no back-end's ``run`` reads it. Which detections a
        back-end uses is its own setting (iSAM2, Forestrix and the tree DB: their config's
        ``max_range``, 50 m by default; the EKF: ``max_new_range`` for new trees; FastSLAM:
        no range limit). It bounds where a tree is *expected* to be seen, and caps one
        local map:

        * :func:`~stemmap.slam.uncertainty.annotate_uncertainty` (every ``map`` / ``demo``
          run): far end of the range window in which a mapped tree should have been detected
          (its ``confidence``), ``min(max_range, 90th percentile of the detection ranges)``;
        * :func:`~stemmap.slam.negative.remove_false_trees_after` (Forestrix with
          ``false_trees="detections"``): far end of the window in which an undetected tree
          counts against it, ``min(max_range, 30 m)``. Forestrix's default ray casting
          (``"rays"``) does not read it;
        * :func:`~stemmap.slam.relocalise.relocalise` (``--prior-map``): the local map it
          matches to the prior map is built from the detections within
          ``min(max_range, 40 m)`` only -- the one use that leaves detections out, of that
          local map, never of the run's map.
    fov : (min, max), rad
        Bearing window of the detector in the sensor frame.
    gnss : GnssFixes or None
        GNSS fixes (:class:`stemmap.slam.gnss.GnssFixes`, antenna lever arm included); the
        ``isam2`` back-end fuses them as robust priors and returns the map in their frame.
    prior_map : StemMap or None
        A map of an earlier session, in whose frame ``initial_pose`` is given (e.g. from
        :func:`stemmap.slam.relocalise.relocalise`); ``isam2`` starts from its trees (with
        their covariances as priors) and returns the merged map.
    prior_graph : SavedGraph or None
        With ``prior_map``: that session's factor graph
        (:class:`stemmap.slam._graph_continue.SavedGraph`, its trees the map's); ``isam2``
        then continues it (the earlier poses and trees stay variables) instead of holding the
        trees by marginal priors. Other back-ends ignore it.
    """

    controls: Controls
    frames: TreeFrames
    motion: MotionModel
    sensor_offset: tuple[float, float] = (0.0, 0.0)
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = ""
    max_range: float = math.inf
    fov: tuple[float, float] = (-math.pi, math.pi)
    gnss: GnssFixes | None = None
    prior_map: StemMap | None = None
    prior_graph: Any = None

    def __post_init__(self) -> None:
        if len(self.frames) == 0:
            raise InputError(f"SLAM problem {self.name!r} has no frames.")


@dataclass
class SlamResult:
    """A back-end's output: vehicle pose at every frame time, the stem map, and run statistics."""

    trajectory: Trajectory
    stem_map: StemMap
    stats: dict[str, float | int | str] = field(default_factory=dict)
    #: (N, 3, 3) covariance of every trajectory pose (x, y, theta; map frame) where the back-end
    #: gives one, NaN rows where it has none for that frame, else None (FastSLAM: the particle
    #: spread, calibrated; EKF: the smoothed path's; iSAM2: keyframe marginals; docs/outputs.md
    #: "trajectory.csv")
    pose_covs: FloatArray | None = None
    #: the session's factor graph (:class:`stemmap.slam._graph_continue.SavedGraph`; iSAM2 with
    #: ``export_graph``), for ``graph.npz`` beside the map; else None
    graph: Any = None


@runtime_checkable
class SlamBackend(Protocol):
    name: str

    def run(
        self, problem: SlamProblem, *, progress: Callable[[int, int], None] | None = None
    ) -> SlamResult: ...


#: name -> "module:Class"; instantiated with keyword config (each class has sensible defaults).
BACKENDS: dict[str, str] = {
    "treedb": "stemmap.slam._treedb_slam:TreeDbSlam",
    "ekf": "stemmap.slam.ekf:EkfSlam",
    "fastslam": "stemmap.slam.fastslam:FastSlam",
    "forestrix": "stemmap.slam.forestrix:ForestrixSlam",
    "isam2": "stemmap.slam.graph:Isam2Slam",
}


def make_backend(name: str, **config: Any) -> SlamBackend:
    """Instantiate a back-end by name with keyword config.

    Raises
    ------
    ConfigError
        If ``name`` is unknown or its module cannot be imported.
    """
    if name not in BACKENDS:
        raise ConfigError(
            f"unknown SLAM back-end {name!r}; choose one of {', '.join(sorted(BACKENDS))}."
        )
    mod_name, cls_name = BACKENDS[name].split(":")
    try:
        cls = getattr(importlib.import_module(mod_name), cls_name)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"SLAM back-end {name!r} is not available: {exc}.") from exc
    backend: SlamBackend = cls(**config)
    return backend


def single_threaded_blas() -> contextlib.AbstractContextManager[Any]:
    """Context manager limiting BLAS/OpenMP to one thread (filters doing many small matrix
    products run faster that way); a no-op if ``threadpoolctl`` is missing."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - scikit-learn depends on it
        return contextlib.nullcontext()
    return threadpool_limits(limits=1)


def duplicate_pairs(stem_map: StemMap, min_separation: float = 1.0) -> int:
    """Number of mapped-tree pairs closer than ``min_separation`` (m).

    Without ground truth (Victoria Park) a duplicate is a tree mapped twice: two landmarks
    closer than 1 m, where two real trunks of 0.1-0.6 m diameter are rare. Each pair counts
    once (one tree too many).
    """
    from scipy.spatial import cKDTree

    xy = stem_map.xy
    if xy.shape[0] < 2:
        return 0
    return len(cKDTree(xy).query_pairs(min_separation))


def _unique_times(times: FloatArray) -> FloatArray:
    """Strictly increasing copy of non-decreasing ``times`` (duplicates nudged by 1 µs)."""
    t = np.array(times, dtype=np.float64)
    for k in range(1, t.shape[0]):  # rare; only runs past duplicates
        if t[k] <= t[k - 1]:
            t[k] = t[k - 1] + 1e-6
    return t


def frame_trajectory(times: FloatArray, poses: FloatArray, frame: str = "map") -> Trajectory:
    """A :class:`Trajectory` at frame times (duplicated frame times nudged to keep order)."""
    t = times if np.all(np.diff(times) > 0) else _unique_times(times)
    return Trajectory(t, poses, frame=frame)


def dead_reckoning(problem: SlamProblem) -> Trajectory:
    """Integrate the controls only (no landmarks): vehicle pose at every frame time."""
    poses = rollout(
        problem.motion, problem.controls, problem.frames.times, np.asarray(problem.initial_pose)
    )
    return frame_trajectory(problem.frames.times, poses)


# --------------------------------------------------------------------------------------------
# Observation model helpers (shared by back-ends)
# --------------------------------------------------------------------------------------------


def sensor_poses(poses: ArrayLike, sensor_offset: tuple[float, float]) -> FloatArray:
    """Sensor poses (..., 3) for vehicle poses (..., 3) and a mounting offset (a, b)."""
    p = np.asarray(poses, dtype=np.float64)
    a, b = sensor_offset
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    out = np.array(p, copy=True)
    out[..., 0] = p[..., 0] + a * c - b * s
    out[..., 1] = p[..., 1] + a * s + b * c
    return out


def observation_to_world(
    pose: ArrayLike,
    ranges: ArrayLike,
    bearings: ArrayLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
) -> FloatArray:
    """World positions (K, 2) of range-bearing detections taken from vehicle ``pose`` (3,)
    or per-detection poses (K, 3)."""
    s = sensor_poses(pose, sensor_offset)
    r = np.asarray(ranges, dtype=np.float64)
    ang = s[..., 2] + np.asarray(bearings, dtype=np.float64)
    return np.column_stack((s[..., 0] + r * np.cos(ang), s[..., 1] + r * np.sin(ang)))


def observe(
    pose: ArrayLike,
    landmarks: ArrayLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
) -> tuple[FloatArray, FloatArray]:
    """Predicted ``(ranges, bearings)`` (N,) of world ``landmarks`` (N, 2) from vehicle ``pose``."""
    s = sensor_poses(pose, sensor_offset)
    m = np.asarray(landmarks, dtype=np.float64).reshape(-1, 2)
    dx = m[:, 0] - s[..., 0]
    dy = m[:, 1] - s[..., 1]
    return np.hypot(dx, dy), np.asarray(wrap_angle(np.arctan2(dy, dx) - s[..., 2]))
