"""Stereo (or RGB-D) visual odometry: Shi-Tomasi corners, pyramidal KLT, PnP RANSAC on keyframes.

The visual-lidar tree-trunk paper (visual-lidar §2.4) runs VINS-stereo as its camera odometry
and fuses its output with a LiDAR odometry in a loosely coupled EKF. We do not reimplement
VINS (a sliding-window visual-inertial optimiser); this is the classic keyframe stereo visual
odometry front end that the issue asks for, built on OpenCV:

1. **Keyframe**: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``, Shi & Tomasi 1994) in the
   left image, each triangulated in the keyframe's camera frame -- stereo: tracked into the
   (rectified) right image with pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``, Bouguet
   2000), kept when the row difference is under ``stereo_max_dy``, the disparity ``d`` over
   ``min_disparity`` and the right-to-left track returns to the corner; ``Z = fx B / d``.
   RGB-D: ``Z`` read from the depth image, rejected at depth edges.
2. **Tracking**: every frame, the surviving corners are tracked from the *keyframe's* left
   image into the new one (pyramidal KLT started at the constant-velocity prediction), with a
   forward-backward check (track back, keep if it returns within ``fb_max_error`` px; Kalal
   et al. 2010). The template is never updated between keyframes: chaining KLT from the
   previous image adds each step's small bias to the track (the "template update problem",
   Matthews, Ishikawa & Baker 2004, IEEE TPAMI 26(6) 810-815: a template re-taken every frame
   drifts; alignment against the first template does not; SVO, Forster et al. 2014, aligns
   its features against the keyframe's patches for the same reason). Each step's KLT
   displacement is short of the true one (4-5 % on the simulated drives, 10-25 % for steps
   under 0.5 px), so the chained track, and the distance, fell short by more the more frames a
   keyframe spanned: 0.4 % at 5 Hz, 3 % at 40 Hz (docs/algorithms/visual-odometry.md,
   "Distance shortfall at high frame rates").
3. **Pose**: the keyframe's 3D points and their tracked pixels give the camera pose relative to
   the keyframe by PnP in a RANSAC loop (``cv2.solvePnPRansac``, P3P hypotheses,
   ``ransac_reprojection`` px), refined by Levenberg-Marquardt on the inliers; outliers are
   dropped from the track set.
4. **Keyframe policy**: a new keyframe (re-detect and re-triangulate) when fewer than
   ``keyframe_min_tracks`` inliers, or less than ``keyframe_min_fraction`` of the keyframe's
   triangulated corners, remain, or after ``keyframe_max_translation`` metres or
   ``keyframe_max_rotation_deg`` of motion since the keyframe (wide baselines between the
   keyframe and the frame lose tracks and let depth errors grow in the reprojection).
   Tracked from the keyframe image, a corner's template deforms with the baseline (a near
   trunk's patch grows by ``t / Z``), which KLT's translation-only model does not fit; the
   forward-backward check drops the worst tracks, the survivors keep a bias that depends on
   the scene, so it differs between the legs of a drive. The fraction (0.7, 0.5 until Dec 4)
   refreshes the keyframe once 30 % of its tracks have failed: on the 12 simulated
   ``visual_lidar2023`` loops (5 Hz; no real stereo log exists in ../shared/datasets) the
   VO's loop-closure error fell from 0.45 to 0.31 m on the mean
   (docs/algorithms/visual-odometry.md, "Loop-closure error and the keyframe fraction").

**Failure handling** (documented behaviour, never an exception on a bad frame): when fewer than
``min_inliers`` points support a pose (too few tracks, PnP failure, or an implausible step of
more than ``max_step`` metres), the frame is marked :attr:`VoStatus.LOST`, its pose is
extrapolated with the last frame-to-frame motion (constant velocity), and a new keyframe is
attempted on that frame. When a keyframe cannot be made (fewer than ``min_inliers``
triangulated corners: a blank, dark or featureless image) the frame is
:attr:`VoStatus.NO_KEYFRAME`, its pose extrapolated the same way, and every following frame
retries. The result carries the status of every frame, so a consumer (e.g. the EKF fusion) can
drop extrapolated poses.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.slam.odometry import OdometrySource
from stemmap.types import FloatArray, Trajectory

__all__ = [
    "VISUAL_DRIFT_XY_PER_SQRT_M",
    "VISUAL_STEP_RATE_HZ",
    "VISUAL_STEP_SIGMA",
    "StereoCalibration",
    "VisualFrame",
    "VisualOdometry",
    "VisualOdometryConfig",
    "VisualOdometryResult",
    "VoStatus",
    "planar_from_camera",
    "run_visual_odometry",
    "visual_odometry_source",
    "visual_velocity_sigma",
]

log = logging.getLogger(__name__)

#: 1-sigma error of one visual odometry step (m along the path, rad of heading) at
#: :data:`VISUAL_STEP_RATE_HZ`; at another frame interval ``dt`` a step's error is
#: ``sqrt(dt * VISUAL_STEP_RATE_HZ)`` times it (white velocity noise: the EKF's VO noise,
#: :func:`visual_velocity_sigma`). Simulated only (no real stereo log): maximum likelihood over
#: the frame-to-frame speed and yaw-rate errors of the rendered 10 m S-curves of
#: benchmarks/visual_drift_calibration.py at 5, 10, 20 and 40 Hz, seeds 0-4, with the exponent
#: of ``dt`` fixed at 0.5 (fitted freely: 0.45 on these seeds, 0.5 on the held-out seeds 5-8);
#: docs/algorithms/visual-odometry.md "VO step noise". Re-measured after the keyframe fraction
#: went 0.5 -> 0.7 (Dec 4): S = 0.00288 m, 0.0218 deg (held-out seeds 5-8: 0.00284 m,
#: 0.0214 deg); with the fraction 0.5 it was (0.0040 m, 0.030 deg). Until Dec 4 it was
#: (0.0041 m, 0.029 deg) per step at any rate, measured at 10 Hz on one 4.9 m drive with the
#: tracking from the previous image.
VISUAL_STEP_SIGMA = (0.0029, math.radians(0.022))

#: The frame rate (Hz) whose one-step error :data:`VISUAL_STEP_SIGMA` is.
VISUAL_STEP_RATE_HZ = 10.0

#: The visual odometry's position random walk per distance travelled (m per sqrt(m): 1-sigma of
#: the x, y end error's norm after 1 m, ``sqrt(d)`` times that after ``d`` m), the drift
#: estimate of ``stemmap map --motion visual`` through
#: :func:`stemmap.odometry.drift.distance_random_walk_variance`. Each frame's pose is tracked
#: from its keyframe, so the error accrues per keyframe, whose spacing follows the motion, not
#: the frame rate. Simulated only (no real stereo log): the RMS of ``|e|² / d`` over the
#: rendered 10 m S-curves of benchmarks/visual_drift_calibration.py at 5, 10, 20 and 40 Hz,
#: seeds 0-4, was 0.0179 (seeds 5-8: 0.0193; docs/algorithms/visual-odometry.md "Drift
#: estimate"); with the keyframe fraction 0.7 (Dec 4) 0.0185 (seeds 5-8: 0.0218), kept.
VISUAL_DRIFT_XY_PER_SQRT_M = 0.018


@dataclass(frozen=True)
class StereoCalibration:
    """Rectified pinhole intrinsics shared by both images, and the stereo baseline.

    Parameters
    ----------
    fx, fy, cx, cy : float, pixels
    width, height : int, pixels
    baseline : float, metres
        Left-to-right optical centre distance; 0 for an RGB-D camera (depth images instead).
    depth_scale : float
        Metres per unit of a depth image (1.0 for float metres, 0.001 for 16-bit millimetres).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    baseline: float = 0.0
    depth_scale: float = 1.0

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ConfigError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}.")
        if not (self.width > 0 and self.height > 0):
            raise ConfigError(f"image size must be > 0, got {self.width} x {self.height}.")
        if not (self.baseline >= 0 and self.depth_scale > 0):
            raise ConfigError("baseline must be >= 0 and depth_scale > 0.")

    @property
    def K(self) -> FloatArray:  # noqa: N802 (the conventional name of the matrix)
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def is_stereo(self) -> bool:
        return self.baseline > 0


@dataclass(frozen=True)
class VisualOdometryConfig:
    """Tuning of :class:`VisualOdometry` (pixels refer to the input images).

    Defaults were chosen on the simulated orchard drive (``StereoCamera()`` of
    :mod:`stemmap.sim.render`, 320 x 200 px, 90° field of view); no real stereo data was
    available (see docs/algorithms/slam-frontends.md).
    """

    max_corners: int = 400
    quality_level: float = 0.005
    min_distance: int = 6
    block_size: int = 5
    klt_window: int = 21
    klt_levels: int = 3
    fb_max_error: float = 0.5
    stereo_max_dy: float = 1.0
    min_disparity: float = 1.0
    max_depth: float = 30.0
    ransac_reprojection: float = 1.5
    ransac_iterations: int = 200
    min_inliers: int = 12
    keyframe_min_tracks: int = 40
    keyframe_min_fraction: float = 0.7
    keyframe_max_translation: float = 1.0
    keyframe_max_rotation_deg: float = 15.0
    max_step: float = 2.0
    rng_seed: int = 0

    def __post_init__(self) -> None:
        if self.max_corners < 4 or self.min_inliers < 4:
            raise ConfigError("max_corners and min_inliers must be >= 4 (PnP needs 4 points).")
        if not (self.fb_max_error > 0 and self.ransac_reprojection > 0 and self.min_disparity > 0):
            raise ConfigError("fb_max_error, ransac_reprojection and min_disparity must be > 0.")
        if self.klt_window < 5 or self.klt_window % 2 == 0:
            raise ConfigError(f"klt_window must be odd and >= 5, got {self.klt_window}.")


class VoStatus(enum.IntEnum):
    """What happened on a frame."""

    #: A new keyframe was made on this frame (its pose comes from tracking or extrapolation).
    KEYFRAME = 0
    #: Pose from PnP against the current keyframe.
    TRACKED = 1
    #: Too few inliers: pose extrapolated with the last motion; a keyframe is re-made here.
    LOST = 2
    #: No keyframe could be made (too few triangulated corners): pose extrapolated.
    NO_KEYFRAME = 3


@dataclass(frozen=True, eq=False)
class VisualFrame:
    """One input frame: a rectified stereo pair, or an image with a depth image."""

    time: float
    left: NDArray[np.generic]
    right: NDArray[np.generic] | None = None
    depth: NDArray[np.generic] | None = None


@dataclass(frozen=True, eq=False)
class VisualOdometryResult:
    """Camera trajectory of a visual odometry run.

    Attributes
    ----------
    times : ndarray (N,), s
    poses : ndarray (N, 4, 4)
        ``world_from_camera`` of the left camera; world = the first camera frame unless an
        initial pose was given.
    status : ndarray (N,) of :class:`VoStatus` values
    n_tracks : ndarray (N,) int
        Corners tracked into the frame (after the forward-backward check).
    n_inliers : ndarray (N,) int
        PnP RANSAC inliers (0 where no PnP was solved).
    """

    times: FloatArray
    poses: FloatArray
    status: NDArray[np.int64]
    n_tracks: NDArray[np.int64]
    n_inliers: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def ok(self) -> NDArray[np.bool_]:
        """Frames whose pose was measured (not extrapolated)."""
        return np.isin(self.status, (VoStatus.KEYFRAME, VoStatus.TRACKED))


def _to_gray(img: NDArray[np.generic], name: str) -> NDArray[np.uint8]:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY)
    if a.ndim != 2:
        raise InputError(f"{name}: expected an (H, W) or (H, W, 3) image, got shape {a.shape}.")
    if a.dtype != np.uint8:
        a = (
            np.clip(
                a.astype(np.float64) / max(float(np.max(a, initial=1)) / 255.0, 1e-12), 0, 255
            ).astype(np.uint8)
            if a.dtype.kind == "f"
            else (a >> 8).astype(np.uint8)
        )
    return np.ascontiguousarray(a)


def _depth_at(depth: FloatArray, uv: NDArray[np.float32]) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Bilinear depth at sub-pixel corners; invalid where the 5 x 5 neighbourhood has no depth or
    straddles a depth edge (depths differing by more than 30 % of the corner's depth; the ground
    seen at a grazing angle changes by ~15 % per pixel row at 20 m). Corners on occlusion
    boundaries do not belong to one surface: they slide along the silhouette as the camera moves.
    """
    h, w = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    kernel = np.ones((5, 5), np.uint8)
    dmax = cv2.dilate(np.where(valid, depth, 0.0).astype(np.float32), kernel)
    dmin = cv2.erode(np.where(valid, depth, np.inf).astype(np.float32), kernel)
    all_valid = cv2.erode(valid.astype(np.uint8), kernel).astype(bool)
    u = np.clip(uv[:, 0].astype(np.float64), 0, w - 1.001)
    v = np.clip(uv[:, 1].astype(np.float64), 0, h - 1.001)
    iu, iv = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - iu, v - iv
    d = np.where(valid, depth, 0.0)
    z = (
        d[iv, iu] * (1 - fu) * (1 - fv)
        + d[iv, iu + 1] * fu * (1 - fv)
        + d[iv + 1, iu] * (1 - fu) * fv
        + d[iv + 1, iu + 1] * fu * fv
    )
    ju, jv = np.rint(u).astype(int), np.rint(v).astype(int)
    ok = all_valid[jv, ju] & (dmax[jv, ju] - dmin[jv, ju] < 0.3 * z)
    return np.where(ok, z, 1.0), ok


def _klt(
    img0: NDArray[np.uint8],
    img1: NDArray[np.uint8],
    pts: NDArray[np.float32],
    guess: NDArray[np.float32],
    cfg: VisualOdometryConfig,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Pyramidal Lucas-Kanade (Bouguet 2000) of (N, 2) points from ``img0`` into ``img1``."""
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        img0,
        img1,
        pts.reshape(-1, 1, 2),
        guess.reshape(-1, 1, 2).copy(),
        winSize=(cfg.klt_window, cfg.klt_window),
        maxLevel=cfg.klt_levels,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    return np.asarray(p1, np.float32).reshape(-1, 2), np.asarray(st).reshape(-1) == 1


def _inv(T: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _pose_from_rt(rvec: FloatArray, tvec: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    return T


class VisualOdometry:
    """Incremental stereo / RGB-D visual odometry (see the module docstring for the method).

    Examples
    --------
    >>> import numpy as np
    >>> cal = StereoCalibration(100.0, 100.0, 63.5, 47.5, 128, 96, baseline=0.1)
    >>> vo = VisualOdometry(cal)
    >>> blank = np.zeros((96, 128), np.uint8)
    >>> vo.process(VisualFrame(0.0, blank, blank)).name   # featureless: no keyframe, no crash
    'NO_KEYFRAME'
    """

    def __init__(
        self,
        calibration: StereoCalibration,
        config: VisualOdometryConfig | None = None,
        *,
        initial_pose: FloatArray | None = None,
    ) -> None:
        self.cal = calibration
        self.cfg = config or VisualOdometryConfig()
        # PnP RANSAC draws from OpenCV's global RNG: seed it so a run is reproducible
        # (two runs in one process otherwise differ by ~1e-5 m)
        cv2.setRNGSeed(self.cfg.rng_seed)
        self.pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, float)
        self._velocity = np.eye(4)  # last frame-to-frame motion, prev_from_cur
        self._kf_pose: FloatArray | None = None
        self._kf_pts = np.zeros((0, 3))
        self._kf_uv = np.zeros((0, 2), np.float32)  # the points' corners in the keyframe image
        self._kf_img: NDArray[np.uint8] | None = None
        self._uv = np.zeros((0, 2), np.float32)  # their last tracked pixels
        self._started = False  # a frame was processed (the velocity and pose have a past)
        self._rvec = np.zeros(3)
        self._tvec = np.zeros(3)
        self.n_tracks = 0
        self.n_inliers = 0
        self._kf_n = 0

    # -- keyframes -------------------------------------------------------------------------

    def _triangulate(
        self, left: NDArray[np.uint8], frame: VisualFrame
    ) -> tuple[FloatArray, NDArray[np.float32]]:
        cfg, cal = self.cfg, self.cal
        corners = cv2.goodFeaturesToTrack(
            left, cfg.max_corners, cfg.quality_level, cfg.min_distance, blockSize=cfg.block_size
        )
        if corners is None or len(corners) < cfg.min_inliers:
            return np.zeros((0, 3)), np.zeros((0, 2), np.float32)
        uv = corners.reshape(-1, 2).astype(np.float32)
        if cal.is_stereo:
            if frame.right is None:
                raise InputError(f"frame at t={frame.time}: stereo calibration but no right image.")
            right = _to_gray(frame.right, "right image")
            ur, st = _klt(left, right, uv, uv, cfg)
            back, st2 = _klt(right, left, ur, uv, cfg)
            disp = uv[:, 0] - ur[:, 0]
            ok = (
                st
                & st2
                & (np.abs(ur[:, 1] - uv[:, 1]) < cfg.stereo_max_dy)
                & (np.linalg.norm(back - uv, axis=1) < cfg.fb_max_error)
                & (disp > cfg.min_disparity)
            )
            z = cal.fx * cal.baseline / np.where(ok, disp, 1.0)
        else:
            if frame.depth is None:
                raise InputError(f"frame at t={frame.time}: RGB-D calibration but no depth image.")
            dimg = np.asarray(frame.depth, dtype=np.float64) * cal.depth_scale
            z, ok = _depth_at(dimg, uv)
            z = np.where(ok, z, 1.0)
        ok &= z < cfg.max_depth
        z = z[ok]
        uv = uv[ok]
        pts = np.column_stack(
            ((uv[:, 0] - cal.cx) * z / cal.fx, (uv[:, 1] - cal.cy) * z / cal.fy, z)
        )
        return pts, uv

    def _make_keyframe(self, left: NDArray[np.uint8], frame: VisualFrame) -> bool:
        pts, uv = self._triangulate(left, frame)
        if pts.shape[0] < self.cfg.min_inliers:
            self._kf_pose = self._kf_img = None
            self._kf_pts, self._uv = np.zeros((0, 3)), np.zeros((0, 2), np.float32)
            self._kf_uv = self._uv
            return False
        self._kf_pose = self.pose.copy()
        self._kf_img = left
        self._kf_pts, self._uv, self._kf_uv = pts, uv, uv.copy()
        self._kf_n = pts.shape[0]
        self._rvec, self._tvec = np.zeros(3), np.zeros(3)
        return True

    # -- tracking ----------------------------------------------------------------------------

    def _predict(self, p0: NDArray[np.float32]) -> NDArray[np.float32]:
        """Initial KLT guesses: the keyframe points projected with the constant-velocity pose
        prediction (as ORB-SLAM's motion model guides its search), for large image motion in
        turns (~25 px per frame at 9° per frame and a 160 px focal length). Measured on a
        simulated 180° headland turn (50 frames, 5 Hz): stereo 0.12 m / 0.33° end error with
        the guess against 0.06 m / 0.41° without (no clear difference), RGB-D 0.27 m / 1.8°
        against 0.44 m / 3.3°."""
        assert self._kf_pose is not None
        T = _inv(self.pose @ self._velocity) @ self._kf_pose  # predicted camera_from_keyframe
        q = self._kf_pts @ T[:3, :3].T + T[:3, 3]
        guess = p0.copy()
        front = q[:, 2] > 0.1
        uv = self.cal.K[:2, :2] @ (q[front, :2] / q[front, 2:]).T + self.cal.K[:2, 2:3]
        guess[front] = uv.T.astype(np.float32)
        h, w = self.cal.height, self.cal.width
        bad = (guess[:, 0] < 0) | (guess[:, 1] < 0) | (guess[:, 0] > w - 1) | (guess[:, 1] > h - 1)
        guess[bad] = p0[bad]
        return guess

    def _track(self, left: NDArray[np.uint8]) -> None:
        """KLT of the keyframe's corners from the keyframe image (not the previous image: see
        the module docstring), started at the predicted pixels (the last tracked ones where a
        point does not project)."""
        assert self._kf_img is not None
        if self._uv.shape[0] == 0:
            return
        p0 = self._kf_uv
        q, st = _klt(self._kf_img, left, p0, self._predict(self._uv), self.cfg)
        pb, stb = _klt(left, self._kf_img, q, p0, self.cfg)
        fb = np.linalg.norm(pb - p0, axis=1)
        h, w = left.shape
        ok = (
            st
            & stb
            & (fb < self.cfg.fb_max_error)
            & (q[:, 0] >= 0)
            & (q[:, 1] >= 0)
            & (q[:, 0] <= w - 1)
            & (q[:, 1] <= h - 1)
        )
        self._kf_pts = self._kf_pts[ok]
        self._kf_uv = self._kf_uv[ok]
        self._uv = q[ok].astype(np.float32)

    def _solve(self) -> FloatArray | None:
        """``camera_from_keyframe`` by PnP RANSAC + LM refinement, or None."""
        cfg = self.cfg
        n = self._uv.shape[0]
        self.n_tracks = n
        self.n_inliers = 0
        if n < cfg.min_inliers:
            return None
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            self._kf_pts,
            self._uv.astype(np.float64),
            self.cal.K,
            None,
            rvec=self._rvec.copy().reshape(3, 1),
            tvec=self._tvec.copy().reshape(3, 1),
            useExtrinsicGuess=True,
            iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.ransac_reprojection,
            confidence=0.999,
            flags=cv2.SOLVEPNP_P3P,
        )
        if not ok or inl is None or len(inl) < cfg.min_inliers:
            return None
        idx = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(
            self._kf_pts[idx], self._uv[idx].astype(np.float64), self.cal.K, None, rvec, tvec
        )
        T = _pose_from_rt(np.asarray(rvec, np.float64), np.asarray(tvec, np.float64))
        if not np.all(np.isfinite(T)) or np.linalg.norm(T[:3, 3]) > cfg.max_step + np.linalg.norm(
            self._tvec
        ):
            return None
        self._rvec = np.asarray(rvec, np.float64).ravel()
        self._tvec = np.asarray(tvec, np.float64).ravel()
        self._kf_pts = self._kf_pts[idx]
        self._kf_uv = self._kf_uv[idx]
        self._uv = self._uv[idx]
        self.n_inliers = int(idx.shape[0])
        return T

    def _need_keyframe(self, T_ck: FloatArray) -> bool:
        cfg = self.cfg
        ang = math.degrees(math.acos(np.clip((np.trace(T_ck[:3, :3]) - 1) / 2, -1.0, 1.0)))
        return bool(
            self.n_inliers < max(cfg.keyframe_min_tracks, cfg.keyframe_min_fraction * self._kf_n)
            or np.linalg.norm(T_ck[:3, 3]) > cfg.keyframe_max_translation
            or ang > cfg.keyframe_max_rotation_deg
        )

    def process(self, frame: VisualFrame) -> VoStatus:
        """Consume one frame; updates :attr:`pose` (``world_from_camera``), returns the status."""
        left = _to_gray(frame.left, "left image")
        if left.shape != (self.cal.height, self.cal.width):
            raise InputError(
                f"frame at t={frame.time}: image is {left.shape[1]} x {left.shape[0]}, the "
                f"calibration says {self.cal.width} x {self.cal.height}."
            )
        prev_pose = self.pose.copy()
        status: VoStatus
        if not self._started or self._kf_pose is None:
            if self._started:
                self.pose = self.pose @ self._velocity
            self.n_tracks = self.n_inliers = 0
            made = self._make_keyframe(left, frame)
            if not made:
                status = VoStatus.NO_KEYFRAME
            else:  # the first frame, or a recovery whose pose was extrapolated
                status = VoStatus.LOST if self._started else VoStatus.KEYFRAME
        else:
            self._track(left)
            T_ck = self._solve()
            if T_ck is None:
                log.info(
                    "frame t=%.3f: %d tracks, too few inliers: lost", frame.time, self.n_tracks
                )
                self.pose = self.pose @ self._velocity
                self._make_keyframe(left, frame)
                status = VoStatus.LOST
            else:
                self.pose = self._kf_pose @ _inv(T_ck)
                status = VoStatus.TRACKED
                if self._need_keyframe(T_ck):
                    status = (
                        VoStatus.KEYFRAME if self._make_keyframe(left, frame) else VoStatus.TRACKED
                    )
                    if self._kf_pose is None:  # could not re-triangulate: keep extrapolating
                        status = VoStatus.NO_KEYFRAME
        if self._started and status in (VoStatus.TRACKED, VoStatus.KEYFRAME):
            self._velocity = _inv(prev_pose) @ self.pose
        self._started = True
        return status


def run_visual_odometry(
    frames: Iterable[VisualFrame],
    calibration: StereoCalibration,
    config: VisualOdometryConfig | None = None,
    *,
    initial_pose: FloatArray | None = None,
) -> VisualOdometryResult:
    """Run :class:`VisualOdometry` over a sequence of frames (stereo pairs or RGB + depth).

    Raises
    ------
    InputError
        When the sequence is empty or frame times do not increase.
    """
    vo = VisualOdometry(calibration, config, initial_pose=initial_pose)
    times: list[float] = []
    poses: list[FloatArray] = []
    status: list[int] = []
    nt: list[int] = []
    ni: list[int] = []
    for fr in frames:
        if times and not fr.time > times[-1]:
            raise InputError(f"frame times must increase: {fr.time} after {times[-1]}.")
        st = vo.process(fr)
        times.append(float(fr.time))
        poses.append(vo.pose.copy())
        status.append(int(st))
        nt.append(vo.n_tracks)
        ni.append(vo.n_inliers)
    if not times:
        raise InputError("visual odometry: no frames.")
    lost = sum(s in (VoStatus.LOST, VoStatus.NO_KEYFRAME) for s in status)
    if lost:
        log.warning("visual odometry: %d of %d frames lost (poses extrapolated)", lost, len(times))
    return VisualOdometryResult(
        np.array(times),
        np.array(poses),
        np.array(status, np.int64),
        np.array(nt, np.int64),
        np.array(ni, np.int64),
    )


def planar_from_camera(
    result: VisualOdometryResult, vehicle_from_camera: FloatArray, *, frame: str = "odom"
) -> Trajectory:
    """Planar vehicle trajectory (x, y, yaw) from the camera poses of a visual odometry run.

    The odometry frame is the vehicle frame at the first image:
    ``T_odom_vehicle(k) = T_vc T_c0_ck T_vc^-1`` with ``T_vc`` the camera mount; x, y are its
    translation, yaw the heading of its x axis (the paper assumes planar ground, §2.4).
    """
    T_vc = np.asarray(vehicle_from_camera, dtype=np.float64).reshape(4, 4)
    T0 = _inv(result.poses[0])
    rel = np.einsum("ij,njk->nik", T0, result.poses)
    T = np.einsum("ij,njk,kl->nil", T_vc, rel, _inv(T_vc))
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    return Trajectory(result.times, np.column_stack((T[:, 0, 3], T[:, 1, 3], yaw)), frame=frame)


def visual_velocity_sigma(dt: float) -> tuple[float, float]:
    """The EKF noise (m/s, rad/s) of a visual odometry velocity over an interval of ``dt``
    seconds: white velocity noise, a step's error ``VISUAL_STEP_SIGMA * sqrt(dt *
    VISUAL_STEP_RATE_HZ)`` divided by ``dt``.

    On the rendered drives a step's error falls with the frame interval as ``sqrt(dt)``; it
    does not stay the same (speed error 0.029 m/s at 5 Hz, 0.039 at 10, 0.052 at 20, 0.082 at
    40 Hz; docs/algorithms/visual-odometry.md "VO step noise"), so the position variance the
    filter adds per second is the same at every camera rate, as the VO's measured drift is
    (:data:`VISUAL_DRIFT_XY_PER_SQRT_M`). Until Dec 4 the noise was ``VISUAL_STEP_SIGMA / dt``
    (one 10 Hz step's error at every rate: 1.4x too small in sigma at 5 Hz, 2x too large at
    40 Hz).
    """
    if not (dt > 0 and math.isfinite(dt)):
        raise ConfigError(f"the frame interval must be finite and > 0, got {dt}.")
    f = math.sqrt(dt * VISUAL_STEP_RATE_HZ) / dt
    return VISUAL_STEP_SIGMA[0] * f, VISUAL_STEP_SIGMA[1] * f


def visual_odometry_source(
    result: VisualOdometryResult,
    vehicle_from_camera: FloatArray,
    *,
    sigma_speed: float,
    sigma_yaw_rate: float,
    inlier_exponent: float = 0.0,
    reference_inliers: float = 100.0,
) -> OdometrySource:
    """The visual odometry as a velocity source for the loosely coupled EKF (visual-lidar §2.4).

    The planar vehicle path (:func:`planar_from_camera`) is differenced into body-frame
    velocities (:func:`stemmap.slam.odometry.velocities_from_poses`); intervals that end on a
    frame whose pose was extrapolated (lost tracking) are dropped, so the filter coasts on the
    other source there instead of fusing a guess.

    ``sigma_speed`` / ``sigma_yaw_rate`` are the noise of an interval whose two poses were
    solved with ``reference_inliers`` PnP inliers. With ``inlier_exponent`` ``p > 0`` each
    interval's noise is scaled by ``(n / reference_inliers) ** -p``, ``n`` the fewer inliers
    of its two frames: the VO's own measure of how well a step is constrained (ours, no paper
    gives a VO covariance; on the simulated orchard drives the step error falls ~2x faster
    than ``1 / sqrt(n)``, docs/algorithms/visual-odometry.md). ``p = 0``: constant noise.
    """
    from stemmap.slam.odometry import velocities_from_poses

    if inlier_exponent < 0 or not reference_inliers > 0:
        raise ConfigError("inlier_exponent must be >= 0 and reference_inliers > 0.")
    traj = planar_from_camera(result, vehicle_from_camera)
    # a frame without a PnP (the first keyframe: the origin) does not limit its intervals
    ni = np.where(result.n_inliers > 0, result.n_inliers.astype(float), np.inf)
    n = np.minimum(ni[1:], ni[:-1])
    n = np.where(np.isfinite(n), n, reference_inliers)
    scale = (n / reference_inliers) ** -inlier_exponent
    src = velocities_from_poses(
        traj,
        sigma_speed=sigma_speed * scale,
        sigma_yaw_rate=sigma_yaw_rate * scale,
        name="visual odometry",
    )
    keep = result.ok[1:] & result.ok[:-1]
    if not keep.any():
        raise InputError("visual odometry lost every frame: nothing to fuse.")
    return src.take(keep)
