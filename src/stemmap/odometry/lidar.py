"""Lidar odometry: scan-to-map registration of 3D frames or 2D scans with KISS-ICP.

Munjer et al. (2025, §3.5, Fig. 6) compute the robot's odometry with "a LiDAR-based scan
matcher using the Iterative Closest Point algorithm" fused with the IMU in an EKF; the paper
names neither the ICP variant nor its parameters. We use KISS-ICP (Vizzo et al., "KISS-ICP: In
Defense of Point-to-Point ICP", IEEE RA-L 2023; ``pip install kiss-icp``), a maintained
point-to-point ICP odometry: each frame is voxel-downsampled and registered to a local voxel
map of the previous frames, starting from a constant-velocity prediction, with an adaptive
correspondence threshold (their eqs. 1-6). It works unchanged for 2D scans lifted to ``z = 0``:
point-to-point residuals keep the out-of-plane motion observable, so the planar case needs no
special solver (small_gicp's GICP, the alternative, fits a covariance to each point's
neighbours, which is singular for a planar scan).

Decisions where the paper is silent (docs/algorithms/odometry.md):

* **Ground removal (3D).** A level lidar over a planar ground sees the same range rings
  wherever it is: those rings pin point-to-point ICP to zero forward motion (on a simulated
  16-beam drive at 4 m/s the raw frames gave 57 % drift, the ground-free ones 0.4 %). Points
  less than ``ground_clearance`` above a per-frame ground raster (:func:`stemmap.cloud.ground
  .fit_ground`, cell ``ground_cell``) are dropped before registration. A frame thinner than
  ``ground_clearance`` (a 2D scan stored as x, y, 0 points) has no ground and keeps all.
* **Degenerate frames.** A frame with fewer than ``min_points`` usable points (empty, all
  returns out of range, a blocked sensor) is not registered: the pose is extrapolated with the
  last velocity (KISS-ICP's own constant-velocity model), the frame is marked ``held`` and its
  increment gets no covariance, so a fusing EKF ignores it and bridges with IMU and wheels.
* **Increment covariance.** KISS-ICP returns no uncertainty. After registration we pair the
  frame's points with the previous frame's (nearest neighbour within the ICP threshold) and use
  the Gauss-Newton form ``Σ = σ² (Σ_i J_iᵀ J_i)⁻¹`` over the planar increment (x, y, yaw),
  ``σ²`` the residual variance (Censi 2007, the paper's reference [11], §III: the Hessian
  approximation; it ignores correlated errors and is optimistic, hence the floors
  ``sigma_xy_floor`` / ``sigma_yaw_floor``). Few or badly spread correspondences (a frame that
  sees one trunk) give a large covariance instead of a confident wrong increment.

The odometry is planar (x, y, yaw), as the paper's 2D map: the 3D pose is projected (yaw from
the rotation's first column); the sensor is assumed level with x forward.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from stemmap.errors import ConfigError, InputError
from stemmap.odometry.drift import distance_random_walk_variance
from stemmap.odometry.fusion import PoseSource
from stemmap.types import FloatArray, LaserScan, PointCloud, Trajectory, wrap_angle

log = logging.getLogger(__name__)

__all__ = [
    "LidarOdometry",
    "LidarOdometryConfig",
    "LidarOdometryResult",
    "LidarStep",
    "lidar_odometry",
]

STATUS_FIRST = "first"
STATUS_OK = "ok"
STATUS_HELD = "held"


@dataclass(frozen=True)
class LidarOdometryConfig:
    """Parameters of :class:`LidarOdometry`.

    Parameters
    ----------
    max_range, min_range : float, metres
        Points outside this range from the sensor are dropped (KISS-ICP's ``data`` settings).
    voxel_size : float or None, metres
        Local-map voxel; None = KISS-ICP's own rule ``max_range / 100``.
    max_points_per_voxel : int
        KISS-ICP's map density.
    remove_ground : bool
        3D frames only: drop ground points before registration (see the module docstring).
    ground_cell, ground_clearance : float, metres
        Ground raster cell and the height above it below which points are ground.
    min_points : int, >= 3
        Frames with fewer usable points are held (constant velocity), not registered.
    sigma_xy_floor : float, metres
        Smallest 1-sigma of an increment's x / y (the Hessian covariance is optimistic).
    sigma_yaw_floor : float, radians
    drift_xy_per_sqrt_m : float, metres per sqrt(metre)
        The scan-to-map odometry's position random walk per distance travelled (1-sigma of
        the x, y error's norm after 1 m; ``sqrt(d)`` times that after ``d`` m), the floor of
        :meth:`LidarOdometryResult.drift_xy_variance`. Measured on simulated 2D scan logs and
        16-beam drives at 10-75 Hz (docs/algorithms/odometry.md "Drift estimate").
    max_iterations : int
        ICP iterations per frame.
    level : bool
        Keep the sensor level: zero roll and pitch after every registration (a ground
        vehicle with a level lidar, as in the paper's 2D map). Ground-free frames of vertical
        trunks leave roll and pitch nearly unobservable: unconstrained, the pitch drifted to
        -2.5 deg in 32 m on flat simulated ground and tilted the x, y motion. 3D frames
        only: 2D scans keep KISS-ICP's unmodified step (on Victoria Park's landmark scans,
        levelling them raised the ATE from 6.06 to 10.0 m).
    """

    max_range: float = 100.0
    min_range: float = 0.5
    voxel_size: float | None = None
    max_points_per_voxel: int = 20
    remove_ground: bool = True
    ground_cell: float = 2.0
    ground_clearance: float = 0.3
    min_points: int = 20
    sigma_xy_floor: float = 0.02
    sigma_yaw_floor: float = math.radians(0.1)
    drift_xy_per_sqrt_m: float = 0.01
    max_iterations: int = 500
    level: bool = True

    def __post_init__(self) -> None:
        if not self.max_range > self.min_range >= 0:
            raise ConfigError(
                f"lidar odometry needs 0 <= min_range < max_range, got {self.min_range}, "
                f"{self.max_range}."
            )
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ConfigError(f"voxel_size must be > 0 m or None, got {self.voxel_size}.")
        if self.min_points < 3:
            raise ConfigError(f"min_points must be >= 3, got {self.min_points}.")
        for name in ("ground_cell", "sigma_xy_floor", "sigma_yaw_floor", "drift_xy_per_sqrt_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}.")
        if self.max_points_per_voxel < 1 or self.max_iterations < 1:
            raise ConfigError("max_points_per_voxel and max_iterations must be >= 1.")

    @property
    def voxel(self) -> float:
        """The voxel size in use (metres)."""
        return float(self.voxel_size) if self.voxel_size is not None else self.max_range / 100.0


@dataclass(frozen=True, eq=False)
class LidarStep:
    """One registered frame.

    Attributes
    ----------
    time : float, s
    pose : ndarray (4, 4)
        Sensor pose in the odometry frame (the first frame's sensor pose is the identity).
    increment : ndarray (3,)
        Planar motion (dx, dy, dyaw) since the previous frame, in the previous sensor frame.
    cov : ndarray (3, 3)
        Its covariance; NaN when the frame was not registered (first or held).
    n_points : int
        Points used for registration (after range filter and ground removal).
    status : str
        ``"first"``, ``"ok"`` or ``"held"`` (degenerate frame, pose extrapolated).
    reason : str
        Why a frame was held.
    """

    time: float
    pose: FloatArray
    increment: FloatArray
    cov: FloatArray
    n_points: int
    status: str
    reason: str = ""


def _planar(T: FloatArray) -> FloatArray:
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])


def _levelled(T: FloatArray) -> FloatArray:
    """``T`` with its rotation replaced by the pure yaw of its x axis (roll = pitch = 0)."""
    yaw = math.atan2(T[1, 0], T[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    out = T.copy()
    out[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return out


def _with_planar(delta: FloatArray, planar: ArrayLike) -> FloatArray:
    """``delta`` (4, 4) with its x, y and yaw replaced by ``planar`` (z, roll, pitch kept)."""
    dx, dy, dyaw = np.asarray(planar, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite((dx, dy, dyaw))):
        return delta
    yaw = math.atan2(delta[1, 0], delta[0, 0])
    c, s = math.cos(dyaw - yaw), math.sin(dyaw - yaw)
    out = delta.copy()
    out[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ delta[:3, :3]
    out[0, 3], out[1, 3] = dx, dy
    return out


def _as_points(frame: ArrayLike | PointCloud | LaserScan) -> tuple[FloatArray, bool]:
    """(N, 3) float64 points and whether the frame was planar (2D scan or (N, 2) array)."""
    if isinstance(frame, LaserScan):
        p = frame.points()
        return np.column_stack((p, np.zeros(p.shape[0]))), True
    a = frame.xyz if isinstance(frame, PointCloud) else np.asarray(frame, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] not in (2, 3):
        raise InputError(
            f"a lidar frame must be an (N, 3) or (N, 2) array of points, got shape {a.shape}."
        )
    a = np.asarray(a, dtype=np.float64)
    if a.shape[1] == 2:
        return np.column_stack((a, np.zeros(a.shape[0]))), True
    return a, False


class LidarOdometry:
    """Incremental lidar odometry (KISS-ICP scan-to-map) over a stream of frames.

    Examples
    --------
    >>> import numpy as np
    >>> lo = LidarOdometry(LidarOdometryConfig(max_range=30.0))
    >>> step = lo.register(np.zeros((0, 3)), time=0.0)  # an empty frame does not crash
    >>> step.status, step.reason
    ('held', 'only 0 usable points (need 20)')
    """

    def __init__(self, config: LidarOdometryConfig | None = None) -> None:
        try:
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError as exc:  # pragma: no cover - a main dependency
            raise ConfigError(
                "lidar odometry needs KISS-ICP: pip install kiss-icp (a stemmap dependency)."
            ) from exc
        self.config = cfg = config or LidarOdometryConfig()
        kc = KISSConfig()
        kc.data.max_range = cfg.max_range
        kc.data.min_range = cfg.min_range
        kc.data.deskew = False
        kc.mapping.voxel_size = cfg.voxel
        kc.mapping.max_points_per_voxel = cfg.max_points_per_voxel
        kc.registration.max_num_iterations = cfg.max_iterations
        kc.registration.max_num_threads = 1
        self._icp: Any = KissICP(kc)
        self._prev: FloatArray | None = None  # previous frame's points, odometry frame
        self._prev_time: float | None = None
        self._n = 0
        self._planar: bool | None = None

    def _preprocess(self, pts: FloatArray, planar: bool) -> FloatArray:
        cfg = self.config
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        r = np.linalg.norm(pts, axis=1)
        pts = pts[(r > cfg.min_range) & (r < cfg.max_range)]
        flat = pts.shape[0] == 0 or float(np.ptp(pts[:, 2])) < cfg.ground_clearance
        if not (planar or flat) and cfg.remove_ground and pts.shape[0] >= cfg.min_points:
            from stemmap.cloud.ground import fit_ground

            ground = fit_ground(pts, cfg.ground_cell)
            pts = pts[ground.height_of(pts) > cfg.ground_clearance]
        return pts

    def register(
        self,
        frame: ArrayLike | PointCloud | LaserScan,
        time: float,
        *,
        prior: ArrayLike | None = None,
    ) -> LidarStep:
        """Register one frame (sensor frame, x forward, z up) taken at ``time`` (s).

        ``prior`` is the planar motion ``(dx, dy, dyaw)`` since the previous frame from
        another sensor (IMU + wheels, :func:`stemmap.odometry.inertial.motion_prior`): it
        replaces KISS-ICP's constant-velocity guess as the ICP starting point, and the
        extrapolation of a held frame -- the "ICP + IMU" coupling of Munjer 2025 §3.5.

        Raises
        ------
        InputError
            Wrong array shape, a time not after the previous frame's, or a 2D frame after 3D
            ones (or the reverse).
        """
        pts, planar = _as_points(frame)
        t = float(time)
        if not math.isfinite(t):
            raise InputError(f"lidar frame {self._n}: time must be finite, got {time}.")
        if self._prev_time is not None and not t > self._prev_time:
            raise InputError(
                f"lidar frame {self._n}: time {t} s is not after the previous frame's "
                f"{self._prev_time} s; frames must be in time order."
            )
        if self._planar is not None and planar != self._planar:
            raise InputError(
                f"lidar frame {self._n} is {'2D' if planar else '3D'} but the earlier frames "
                f"were {'2D' if self._planar else '3D'}; one run needs one sensor."
            )
        self._planar = planar
        self._n += 1
        self._prev_time = t
        src = self._preprocess(pts, planar)
        icp = self._icp
        prev_pose = np.array(icp.last_pose, dtype=np.float64)
        nan3 = np.full((3, 3), np.nan)
        if prior is not None:
            icp.last_delta = _with_planar(np.asarray(icp.last_delta, dtype=np.float64), prior)
        if src.shape[0] < self.config.min_points:
            reason = f"only {src.shape[0]} usable points (need {self.config.min_points})"
            log.info("lidar frame at t=%.3f s held: %s", t, reason)
            new = prev_pose @ icp.last_delta if self._prev is not None else prev_pose
            icp.last_pose = new
            inc = _planar(np.linalg.inv(prev_pose) @ new)
            return LidarStep(t, new.copy(), inc, nan3, int(src.shape[0]), STATUS_HELD, reason)
        first = self._prev is None
        new = self._register(src)
        inc = _planar(np.linalg.inv(prev_pose) @ new)
        moved = src @ new[:3, :3].T + new[:3, 3]
        cov = nan3 if first else self._increment_cov(moved, new, prev_pose)
        self._prev = moved
        return LidarStep(t, new, inc, cov, int(src.shape[0]), STATUS_FIRST if first else STATUS_OK)

    def _register(self, src: FloatArray) -> FloatArray:
        """One KISS-ICP step (``KissICP.register_frame`` without deskew, from the library's own
        voxelizer, registration, threshold and map), with a 3D frame's pose levelled (roll =
        pitch = 0) before it updates the map when ``config.level``."""
        icp = self._icp
        source, frame_down = icp.voxelize(src)
        sigma = float(icp.adaptive_threshold.get_threshold())
        guess = icp.last_pose @ icp.last_delta
        new = np.array(
            icp.registration.align_points_to_map(
                points=source,
                voxel_map=icp.local_map,
                initial_guess=guess,
                max_correspondance_distance=3.0 * sigma,
                kernel=sigma,
            ),
            dtype=np.float64,
        )
        if self.config.level and not self._planar:
            new = _levelled(new)
        icp.adaptive_threshold.update_model_deviation(np.linalg.inv(guess) @ new)
        icp.local_map.update(frame_down, new)
        icp.last_delta = np.linalg.inv(icp.last_pose) @ new
        icp.last_pose = new
        return new

    def _increment_cov(self, moved: FloatArray, new: FloatArray, prev: FloatArray) -> FloatArray:
        """Planar Gauss-Newton covariance of the increment (module docstring), in the previous
        sensor frame."""
        cfg = self.config
        assert self._prev is not None
        thr = 3.0 * float(self._icp.adaptive_threshold.get_threshold())
        d, j = cKDTree(self._prev).query(moved, distance_upper_bound=max(thr, cfg.voxel))
        ok = np.isfinite(d)
        big = np.diag([1.0, 1.0, math.radians(30.0) ** 2])
        if ok.sum() < 3:
            return big
        q = moved[ok]
        r = (q - self._prev[j[ok]])[:, :2]
        c = q[:, :2] - new[:2, 3]
        n = q.shape[0]
        J = np.zeros((2 * n, 3))
        J[0::2, 0] = 1.0
        J[1::2, 1] = 1.0
        J[0::2, 2] = -c[:, 1]
        J[1::2, 2] = c[:, 0]
        H = J.T @ J
        dof = max(2 * n - 3, 1)
        s2 = float(np.sum(r**2)) / dof
        try:
            cov_w = s2 * np.linalg.inv(H)
        except np.linalg.LinAlgError:
            return big
        if not np.all(np.isfinite(cov_w)):
            return big
        # odometry-frame (x, y, yaw) -> previous sensor frame
        th = math.atan2(prev[1, 0], prev[0, 0])
        R = np.array([[math.cos(th), math.sin(th), 0.0], [-math.sin(th), math.cos(th), 0.0]])
        R = np.vstack((R, [0.0, 0.0, 1.0]))
        cov = R @ cov_w @ R.T
        floor = np.array([cfg.sigma_xy_floor, cfg.sigma_xy_floor, cfg.sigma_yaw_floor]) ** 2
        cov[np.diag_indices(3)] = np.maximum(np.diag(cov), floor)
        return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


@dataclass(frozen=True, eq=False)
class LidarOdometryResult:
    """Output of :func:`lidar_odometry`.

    Attributes
    ----------
    times : ndarray (F,), s
    poses : ndarray (F, 4, 4)
        Sensor poses in the odometry frame (first = identity, or ``initial_pose``).
    planar : ndarray (F, 3)
        x, y, yaw of ``poses``.
    increment_cov : ndarray (F, 3, 3)
        Covariance of the increment that ends at each frame (NaN for the first and held
        frames).
    n_points : ndarray (F,), int
    status : ndarray (F,), str
    config : LidarOdometryConfig
    """

    times: FloatArray
    poses: FloatArray
    planar: FloatArray
    increment_cov: FloatArray
    n_points: NDArray[np.int64]
    status: NDArray[np.str_]
    config: LidarOdometryConfig = field(default_factory=LidarOdometryConfig)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def held(self) -> NDArray[np.bool_]:
        """Frames whose pose was extrapolated (degenerate input)."""
        return np.asarray(self.status == STATUS_HELD)

    def drift_xy_variance(self, distance: float) -> float:
        """Variance (m², x + y) of the end position after ``distance`` metres of this run.

        The scan-to-map poses drift per distance, not per frame: each frame is registered to
        the local map, so consecutive frames' errors are nearly the same error, and summing the
        floored increment covariances as independent steps grew with the frame rate (9-12x
        the measured end error at 10 Hz, 17-28x at 75 Hz). The variance is a random walk in
        distance, ``drift_xy_per_sqrt_m² * distance``, with each frame's share of the distance (its
        step) weighted by how far its Gauss-Newton x + y variance exceeds the floor's
        ``2 sigma_xy_floor²`` (1 for a well-constrained frame; large where the geometry is
        degenerate: few or badly spread correspondences). Held frames (no covariance) weigh 1.
        Blind to scale errors, like any covariance. The random walk is
        :func:`stemmap.odometry.drift.distance_random_walk_variance`, shared with the visual
        odometry's estimate. Measurements: docs/algorithms/odometry.md
        "Drift estimate".
        """
        cfg = self.config
        if len(self) < 2:
            return distance_random_walk_variance(cfg.drift_xy_per_sqrt_m, distance)
        step = np.hypot(*np.diff(self.planar[:, :2], axis=0).T)
        c = self.increment_cov[1:]
        infl = np.maximum((c[:, 0, 0] + c[:, 1, 1]) / (2.0 * cfg.sigma_xy_floor**2), 1.0)
        return distance_random_walk_variance(cfg.drift_xy_per_sqrt_m, distance, step, infl)

    def trajectory(self) -> Trajectory:
        """The planar sensor trajectory (frame ``"odom"``)."""
        p = self.planar.copy()
        p[:, 2] = wrap_angle(p[:, 2])
        return Trajectory(self.times, p, frame="odom")

    def pose_source(self, name: str = "lidar") -> PoseSource:
        """The poses as absolute measurements for :func:`~stemmap.odometry.fusion
        .fuse_sources`, each with its registration covariance (rotated to the odometry frame);
        first and held frames carry NaN (no measurement)."""
        th = self.planar[:-1, 2] if len(self) > 1 else np.zeros(0)
        c, s = np.cos(th), np.sin(th)
        R = np.zeros((th.shape[0], 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, -s, s, c
        R[:, 2, 2] = 1.0
        covs = self.increment_cov.copy()
        covs[1:] = R @ covs[1:] @ np.transpose(R, (0, 2, 1))
        return PoseSource(self.times, self.planar, covs, name=name)


def lidar_odometry(
    frames: Iterable[tuple[float, ArrayLike | PointCloud | LaserScan]],
    config: LidarOdometryConfig | None = None,
    *,
    initial_pose: ArrayLike = (0.0, 0.0, 0.0),
    motion_prior: Callable[[float, float], FloatArray] | None = None,
) -> LidarOdometryResult:
    """Run :class:`LidarOdometry` over ``(time, frame)`` pairs (Munjer 2025 §3.5 scan matcher).

    Parameters
    ----------
    frames : iterable of (float, frame)
        Time (s) and the frame: an (N, 3) / (N, 2) array or :class:`~stemmap.types.PointCloud`
        in the sensor frame, or a :class:`~stemmap.types.LaserScan` (lifted to ``z = 0``).
    config : LidarOdometryConfig, optional
    initial_pose : (3,)
        Planar pose of the first frame in the output frame.
    motion_prior : callable ``(t0, t1) -> (dx, dy, dyaw)``, optional
        Planar motion between two times from IMU + wheels
        (:func:`stemmap.odometry.inertial.motion_prior`): the ICP starting guess and the
        bridge over held frames. None = KISS-ICP's constant-velocity model (lidar only).

    Returns
    -------
    LidarOdometryResult

    Raises
    ------
    InputError
        No frames, bad shapes, times not increasing.
    """
    lo = LidarOdometry(config)
    steps: list[LidarStep] = []
    for t, f in frames:
        prior = None
        if motion_prior is not None and steps:
            prior = motion_prior(steps[-1].time, float(t))
        steps.append(lo.register(f, t, prior=prior))
    if not steps:
        raise InputError("lidar odometry: no frames were given.")
    p0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    c, s = math.cos(p0[2]), math.sin(p0[2])
    T0 = np.eye(4)
    T0[:2, :2] = [[c, -s], [s, c]]
    T0[:2, 3] = p0[:2]
    poses = np.stack([T0 @ st.pose for st in steps])
    planar = np.array([_planar(T) for T in poses])
    planar[:, 2] = np.unwrap(planar[:, 2])
    return LidarOdometryResult(
        times=np.array([st.time for st in steps]),
        poses=poses,
        planar=planar,
        increment_cov=np.stack([st.cov for st in steps]),
        n_points=np.array([st.n_points for st in steps], dtype=np.int64),
        status=np.array([st.status for st in steps]),
        config=lo.config,
    )
