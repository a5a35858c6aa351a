"""Munjer et al. (2025) end to end: per-frame trunk detections (EB-LiDAR or DAIM) -> FastSLAM
(100 particles) -> Kalman refinement of the trees -> stem map (§3.1, Fig. 2; §3.6).

The motion source is pluggable: anything that yields :class:`~stemmap.slam.base.Controls`.
Wheel odometry CSVs give them directly; a pose-output odometry (the paper's ICP + IMU EKF, or
any SLAM front end writing ``time_s,x,y,theta``) is turned into controls by
:func:`controls_from_trajectory`: speed and yaw rate per interval, or (``lateral="keep"``)
controls that dead-reckon through every pose, sideways steps included
(:meth:`~stemmap.slam.base.Controls.from_trajectory`).

* :func:`eb_lidar_observations` -- EB-LiDAR (:func:`~stemmap.cloud.munjer.detect_stems_munjer`)
  on every lidar frame, as sensor-frame :class:`~stemmap.types.StemObservations`;
* :func:`ours_lidar_observations` -- stemmap's own cloud detector on every frame, for comparison;
* :func:`daim_observations` -- a trunk detector's boxes (never truth) + aligned depth ->
  :func:`~stemmap.vision.depth.daim_trunks` on every RGB-D frame;
* :func:`munjer_problem` -- a :class:`~stemmap.slam.base.SlamProblem` from either;
* :func:`map_munjer` -- FastSLAM (``preset="munjer2025"``) then
  :func:`~stemmap.slam.refine.refine_stem_map`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.cloud.filters import pass_through
from stemmap.cloud.munjer import MunjerConfig, detect_stems_munjer, level_to_ground
from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import Controls, SlamProblem, SlamResult, TreeFrames
from stemmap.slam.motion import UnicycleModel, between
from stemmap.types import FloatArray, PointCloud, StemObservations, Trajectory

if TYPE_CHECKING:
    from stemmap.cloud.config import StemConfig
    from stemmap.cloud.result import CloudStems

__all__ = [
    "MunjerMapConfig",
    "accumulate_frames",
    "controls_from_trajectory",
    "daim_observations",
    "eb_lidar_observations",
    "lidar_observations",
    "map_munjer",
    "munjer_problem",
    "ours_lidar_observations",
]

log = logging.getLogger(__name__)


_COLUMNS = (
    "centers",
    "radii",
    "covs",
    "n_points",
    "arc_deg",
    "widths",
    "quality",
    "index",
    "times",
)


def _stack(parts: list[StemObservations], source: str, frame: str) -> StemObservations:
    parts = [p for p in parts if len(p)]
    if not parts:
        return StemObservations.empty(source=source, frame=frame)
    cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in _COLUMNS}
    return StemObservations(**cat, source=source, frame=frame)


def lidar_observations(
    frames: Sequence[PointCloud | FloatArray],
    times: ArrayLike,
    detect: Callable[[FloatArray], CloudStems],
    source: str,
) -> StemObservations:
    """Run a per-frame cloud stem detector on every lidar frame.

    Parameters
    ----------
    frames : F lidar frames, sensor frame (x forward, z up), metres
    times : (F,) s
    detect : ``xyz (N, 3) -> CloudStems`` in the same frame
    source : the observations' ``source`` tag

    Returns
    -------
    StemObservations in the sensor frame, ``index`` = frame index.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.shape[0] != len(frames):
        raise InputError(f"{len(frames)} lidar frames but {t.shape[0]} times.")
    dets = (
        detect(fr.xyz if isinstance(fr, PointCloud) else np.asarray(fr, dtype=np.float64))
        for fr in frames
    )
    return _observations(dets, t, source)


def _observations(dets: Iterable[CloudStems], t: FloatArray, source: str) -> StemObservations:
    """Per-frame detections (frame ``f`` = the ``f``-th item, lidar frame) as observations."""
    parts = []
    for f, det in enumerate(dets):
        k = len(det)
        if k == 0:
            continue
        parts.append(
            StemObservations(
                centers=det.xy,
                radii=det.diameter / 2,
                covs=np.full((k, 3, 3), np.nan),
                n_points=det.n_points,
                arc_deg=np.full(k, np.nan),
                widths=np.full(k, np.nan),
                quality=np.ones(k),
                index=np.full(k, f, dtype=np.int64),
                times=np.full(k, t[f]),
                source=source,
                frame="lidar",
            )
        )
    return _stack(parts, source, "lidar")


def accumulate_frames(
    frames: Sequence[PointCloud | FloatArray],
    poses: ArrayLike,
    config: MunjerConfig | None = None,
) -> list[FloatArray]:
    """Per frame, the pass-through points of it and the ``config.window - 1`` frames before it,
    in its own lidar frame (our decision where Munjer et al. 2025 are silent; see
    docs/algorithms/cloud.md, "Accumulated frames").

    Parameters
    ----------
    frames : F lidar frames, sensor frame (x forward, z up), metres, each taken at one instant
        (de-skewed: the simulator's frames are; a real sensor's need the odometry's de-skew)
    poses : (F, 3) -- the motion source's planar pose (x, y, theta) of the lidar at each frame,
        in any fixed odometry frame (only poses relative to each other are used)
    config : MunjerConfig -- its box (applied to each frame in its own lidar frame, as §3.2
        prescribes), ``ground_relative`` and ``window``

    Returns
    -------
    list of F arrays (N_f, 3): frame f's box points joined with the earlier frames' box points
    moved by :func:`~stemmap.slam.motion.between` (planar: z is kept, the lidar is assumed level).
    """
    return [xyz for xyz, _ in _accumulate(frames, poses, config or MunjerConfig())]


def _accumulate(
    frames: Sequence[PointCloud | FloatArray], poses: ArrayLike, cfg: MunjerConfig
) -> list[tuple[FloatArray, NDArray[np.int64]]]:
    """:func:`accumulate_frames` with, per joined cloud, the frame index of every point."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] != len(frames):
        raise InputError(f"{len(frames)} lidar frames but {p.shape[0]} poses.")
    boxed = []
    for fr in frames:
        xyz = fr.xyz if isinstance(fr, PointCloud) else np.asarray(fr, dtype=np.float64)
        zb = level_to_ground(xyz) if cfg.ground_relative else xyz
        boxed.append(xyz[pass_through(zb, x=cfg.box_x, y=cfg.box_y, z=cfg.box_z)])
    out = []
    for f in range(len(boxed)):
        lo = max(0, f - cfg.window + 1)
        rel = between(p[f], p[lo : f + 1])
        parts = []
        for (dx, dy, dth), q in zip(rel, boxed[lo : f + 1], strict=True):
            c, s = math.cos(dth), math.sin(dth)
            parts.append(
                np.column_stack(
                    (c * q[:, 0] - s * q[:, 1] + dx, s * q[:, 0] + c * q[:, 1] + dy, q[:, 2])
                )
            )
        ids = np.repeat(np.arange(lo, f + 1), [len(q) for q in parts])
        out.append((np.vstack(parts), ids))
    return out


def eb_lidar_observations(
    frames: Sequence[PointCloud | FloatArray],
    times: ArrayLike,
    config: MunjerConfig | None = None,
    *,
    poses: ArrayLike | None = None,
) -> StemObservations:
    """EB-LiDAR (:func:`~stemmap.cloud.munjer.detect_stems_munjer`, Munjer et al. 2025,
    §3.2-3.3, Table 1 by default) on every lidar frame; see :func:`lidar_observations`.

    With ``config.window > 1`` each frame keeps its own detections and adds those of
    :func:`accumulate_frames` (its box points and those of the ``window - 1`` frames before it,
    moved with ``poses``, the motion source's (F, 3) lidar poses) that lie farther than
    ``config.association_distance`` from all of them. On the joined cloud a cluster needs
    ``min_points`` points from one frame (``detect_stems_munjer(..., frame_ids=...)``): the
    window can sharpen the shape of a trunk already dense in one frame, not create density.
    All detections stay in that frame's lidar frame (docs/algorithms/cloud.md,
    "Accumulated frames").
    """
    from dataclasses import replace

    cfg = config or MunjerConfig()
    if cfg.window > 1 and poses is None:
        raise ConfigError(
            f"EB-LiDAR with window={cfg.window} joins frames and needs the motion source's poses "
            "(poses=...); use window=1 for strictly per-frame detection."
        )
    single = lidar_observations(
        frames, times, lambda xyz: detect_stems_munjer(xyz, cfg), "cloud:munjer2025"
    )
    if cfg.window == 1 or poses is None:
        return single
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    opened = replace(cfg, box_x=None, box_y=None, box_z=None, ground_relative=False)
    joined = _observations(
        (
            detect_stems_munjer(xyz, opened, frame_ids=ids)
            for xyz, ids in _accumulate(frames, poses, cfg)
        ),
        t,
        "cloud:munjer2025",
    )
    new_obs = np.ones(len(joined), dtype=bool)
    for f in np.intersect1d(joined.index, single.index):
        j, k = joined.index == f, single.index == f
        d = np.hypot(
            *(joined.centers[j][:, None, :] - single.centers[k][None, :, :]).transpose(2, 0, 1)
        )
        new_obs[np.flatnonzero(j)[d.min(axis=1) <= cfg.association_distance]] = False
    both = _stack([single, _select(joined, new_obs)], "cloud:munjer2025", "lidar")
    return _select(both, np.argsort(both.index, kind="stable"))


def _select(obs: StemObservations, idx: NDArray[np.bool_] | NDArray[np.int64]) -> StemObservations:
    """Rows ``idx`` of an observation batch."""
    from dataclasses import replace

    return replace(obs, **{k: getattr(obs, k)[idx] for k in _COLUMNS})


def ours_lidar_observations(
    frames: Sequence[PointCloud | FloatArray],
    times: ArrayLike,
    config: StemConfig | None = None,
) -> StemObservations:
    """stemmap's own cloud detector (:func:`~stemmap.cloud.stems.detect_stems`, ground fit,
    breast-height slices, fits refined along the rays from the sensor at the frame origin) on
    every lidar frame; see :func:`lidar_observations`."""
    from stemmap.cloud.stems import detect_stems

    origin = np.zeros(3)
    return lidar_observations(
        frames, times, lambda xyz: detect_stems(xyz, config, origins=origin), "cloud:ours"
    )


def daim_observations(
    images: Sequence[NDArray[np.uint8]],
    depths: Sequence[ArrayLike],
    frame_index: ArrayLike,
    times: ArrayLike,
    rig: object,
    detector: object,
    *,
    params: object | None = None,
) -> StemObservations:
    """DAIM on every RGB-D frame (Munjer et al. 2025, §3.4), boxes from ``detector``.

    Parameters
    ----------
    images, depths : C colour images (H, W, 3) uint8 and aligned z-depth images (H, W), metres
    frame_index : (C,) int -- the lidar/odometry frame each image belongs to
    times : (F,) s -- frame times (indexed by ``frame_index``)
    rig : :class:`~stemmap.sim.camera.CameraRig` -- camera model and lidar -> camera transform
    detector : a :class:`~stemmap.vision.detector.TrunkDetector` (``SegmentationDetector`` or an
        ``OnnxDetector``); boxes never come from ground truth here
    params : :class:`~stemmap.vision.depth.DaimParams` (default: the Munjer three-point fit)

    Returns
    -------
    StemObservations in the lidar (vehicle) frame, ``index`` = frame index.
    """
    from stemmap.vision.depth import MUNJER2025, daim_trunks

    idx = np.asarray(frame_index, dtype=np.int64).reshape(-1)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if not (len(images) == len(depths) == idx.shape[0]):
        raise InputError(
            f"{len(images)} images, {len(depths)} depth images and {idx.shape[0]} frame indices "
            "must agree."
        )
    if idx.size and (idx.min() < 0 or idx.max() >= t.shape[0]):
        raise InputError(f"image frame indices must lie in [0, {t.shape[0]}).")
    to_body = rig.laser_to_camera.inverse()  # type: ignore[attr-defined]
    parts = []
    for img, dep, f in zip(images, depths, idx, strict=True):
        boxes = detector.detect(img).boxes  # type: ignore[attr-defined]
        if len(boxes) == 0:
            continue
        obs = daim_trunks(
            dep,
            rig.camera,  # type: ignore[attr-defined]
            boxes,
            camera_to_body=to_body,
            params=params or MUNJER2025,  # type: ignore[arg-type]
            time=float(t[f]),
        )
        if len(obs):
            from dataclasses import replace

            parts.append(replace(obs, index=np.full(len(obs), int(f), dtype=np.int64)))
    return _stack(parts, "vision:munjer2025", "laser")


def controls_from_trajectory(
    trajectory: Trajectory,
    *,
    sigma_speed: float = 0.05,
    sigma_yaw_rate: float = 0.01,
    lateral: Literal["drop", "keep"] = "drop",
    sigma_lateral: float | None = None,
) -> tuple[Controls, UnicycleModel]:
    """Unicycle controls and motion noise from any pose-output odometry (the pluggable motion
    source: the lidar + IMU odometry that stands in for the paper's ICP + IMU EKF, §3.5 -- the
    paper's odometry is ICP scan matching fused with an IMU in an EKF, a pose output; visual
    odometry; the fused visual + lidar EKF; a SLAM front end).

    ``sigma_speed`` / ``sigma_yaw_rate`` (one-second averages) become the motion model's noise.
    ``lateral`` says what happens to the sideways part of each pose increment, which a
    unicycle's speed and yaw rate cannot carry:

    * ``"drop"`` (default): speed and yaw rate of each interval
      (:func:`~stemmap.slam.odometry.velocities_from_poses`), the odometry projected on the
      vehicle's non-holonomic motion. The back-ends then start from another path than the
      odometry's: on a scan matcher's jittery path a smoother one (``stemmap sim scans``
      log, 2D KISS-ICP: path RMSE 0.076 m for the odometry, 0.052 m for these controls).
    * ``"keep"``: controls that dead-reckon exactly through every pose
      (:meth:`~stemmap.slam.base.Controls.from_trajectory`), so every back-end with no
      landmark returns the odometry's own path; the model gets a sideways noise
      ``sigma_lateral`` (m/s, one-second average; default ``sigma_speed``:
      ``UnicycleModel.sigma_lateral``; the steps' lateral error is as large as their
      along-track one, 2.7 against 2.3 cm per 0.2 m step on that log, and without it FastSLAM
      took the jitter as certain, path RMSE 1.55 m).

    Which is better depends on the odometry (docs/algorithms/slam.md, "Controls from a pose
    trajectory": measured on simulated drives only; the default is the earlier behaviour).
    """
    if lateral == "keep":
        model = UnicycleModel(
            sigma_speed=sigma_speed,
            sigma_steer=sigma_yaw_rate,
            sigma_lateral=sigma_speed if sigma_lateral is None else sigma_lateral,
        )
        return Controls.from_trajectory(trajectory), model
    if lateral != "drop":
        raise ConfigError(f"lateral must be 'drop' or 'keep', got {lateral!r}.")
    from stemmap.slam.odometry import velocities_from_poses

    src = velocities_from_poses(trajectory, sigma_speed=sigma_speed, sigma_yaw_rate=sigma_yaw_rate)
    assert src.interval_start is not None  # set by velocities_from_poses: the intervals' starts
    controls = Controls(src.interval_start, src.speed, src.yaw_rate, "unicycle")
    return controls, UnicycleModel(sigma_speed=sigma_speed, sigma_steer=sigma_yaw_rate)


def munjer_problem(
    observations: StemObservations,
    times: ArrayLike,
    controls: Controls,
    motion: UnicycleModel,
    *,
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    max_range: float = math.inf,
    name: str = "munjer2025",
) -> SlamProblem:
    """A SLAM problem from per-frame detections (sensor = vehicle frame) and a motion source.

    ``max_range`` is the sensor's declared range (``SlamProblem.max_range``): it bounds where
    the post-steps expect a tree to be seen; it drops no detection.
    """
    frames = TreeFrames.from_observations(observations, times)
    return SlamProblem(
        controls,
        frames,
        motion,
        initial_pose=initial_pose,
        name=name,
        max_range=max_range,
    )


@dataclass(frozen=True)
class MunjerMapConfig:
    """Back end of the Munjer pipeline (§3.6, Table 1).

    n_particles : FastSLAM particles (Table 1: 100)
    sigma_range, sigma_bearing : detection noise (m, rad) of FastSLAM and of the refinement
        (the paper gives none; FastSLAM's defaults)
    min_observations : detections a landmark needs to enter the map. 3, not FastSLAM's 5 (set
        on Victoria Park, where a tree is in 50-100 scans): EB-LiDAR reaches ~6 m (beyond, a
        trunk has < 20 points in the 0.5 m band), so at 4 m/s and 10 Hz a tree is inside its
        range for ~10-15 frames and detected in 4-10 of them
    refine : run the Kalman refinement of the trees (§3.6) after FastSLAM
    refine_gate : m -- detection-to-tree association distance of the refinement (Table 1's
        proximity threshold, 1.0 m)
    detection_noise : bool -- ours: each detection's own noise (``TreeFrames.noise``, from
        ``StemObservations.covs``: DAIM's depth-noise model,
        :func:`~stemmap.vision.depth.daim_trunks`) added to ``sigma_range`` / ``sigma_bearing``
        in FastSLAM (:class:`~stemmap.slam.fastslam.FastSlam` ``detection_noise``) and in the
        refinement, so a far, noisy detection weighs less. Default on: detections without a
        covariance (EB-LiDAR, ours) are unchanged by it; DAIM's are weighed by the simulator's
        D435 model (docs/algorithms/cloud.md, "DAIM: per-detection noise"). The paper gives
        every detection the same noise (False).
    path : "mean" or "best" -- the FastSLAM path the refinement maps every detection with
        and the result's trajectory: the posterior mean over the particles' lineages (ours,
        default; :class:`~stemmap.slam.fastslam.FastSlam` ``path``) or the best particle's
        (Montemerlo's usual output; the paper does not say which). On the Munjer-like DAIM
        drives the weights stay flat (no resampling in a lap), so the best particle is one draw
        of the motion noise around the odometry, its path error about 1.6 x the odometry's,
        and it set the worst draws' map error (docs/algorithms/cloud.md, "DAIM: the worst
        draws")
    seed : FastSLAM seed
    """

    n_particles: int = 100
    sigma_range: float = 0.5
    sigma_bearing: float = math.radians(2.0)
    min_observations: int = 3
    refine: bool = True
    refine_gate: float = 1.0
    detection_noise: bool = True
    path: Literal["best", "mean"] = "mean"
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_particles < 1 or self.min_observations < 1 or not self.refine_gate > 0:
            raise ConfigError("n_particles, min_observations >= 1 and refine_gate > 0 needed.")


def map_munjer(problem: SlamProblem, config: MunjerMapConfig | None = None) -> SlamResult:
    """FastSLAM then the per-tree Kalman refinement (Munjer et al. 2025, §3.6).

    Returns the FastSLAM result with its stem map replaced by the refined one (same trees; each
    position re-estimated from every detection within ``refine_gate``, the pose uncertainty of
    the particle cloud ignored: FastSLAM's path, ``config.path``, is taken as exact).
    """
    from stemmap.slam.fastslam import FastSlam
    from stemmap.slam.refine import refine_stem_map

    cfg = config or MunjerMapConfig()
    fs = FastSlam(
        n_particles=cfg.n_particles,
        sigma_range=cfg.sigma_range,
        sigma_bearing=cfg.sigma_bearing,
        min_observations=cfg.min_observations,
        seed=cfg.seed,
        smooth=False,  # the paper's FastSLAM: no joint smoothing afterwards (ours)
        detection_noise=cfg.detection_noise,
        path=cfg.path,
    )
    result = fs.run(problem)
    if cfg.refine and len(result.stem_map):
        fr = problem.frames
        refined = refine_stem_map(
            result.stem_map,
            result.trajectory.poses,
            fr.ptr,
            fr.ranges,
            fr.bearings,
            sigma_range=cfg.sigma_range,
            sigma_bearing=cfg.sigma_bearing,
            sensor_offset=problem.sensor_offset,
            gate=cfg.refine_gate,
            noise=fr.noise if cfg.detection_noise else None,
        )
        result.stem_map = refined
        result.stats["refined"] = "kalman"
    return result
