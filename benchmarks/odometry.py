"""Benchmark: lidar odometry (KISS-ICP), IMU + wheel dead reckoning and their EKF fusion.

Prints one JSON object. Parts (``--parts``, default all):

* ``sim3d``: a Munjer-like drive -- a park-like stand (trees >= 4 m apart, branches, shrubs,
  a sloping ground), a VLP-16 (16 beams, 0.2 deg azimuth step) at 10 Hz, 4 m/s along an S
  curve, an XSens-class IMU at 100 Hz and wheels at 50 Hz (2 % scale error, slips; preset
  ``xsens`` of :mod:`stemmap.sim.imu`). Sources: ``lidar_only`` (KISS-ICP, constant-velocity
  guess), ``imu_wheel`` (gyro + wheel dead reckoning through the same EKF), ``lidar_imu``
  (KISS-ICP with the IMU + wheel motion as its guess), ``fused`` (the EKF of lidar poses, gyro
  and wheel: what ``stemmap odometry --imu`` writes). The same drive again with 2.5 s of
  empty frames in the middle (``blackout``: sensor blocked).
* ``sim2d``: 2D scans (SICK LMS preset, 80 m, 0.5 deg) at 10 Hz along an S curve at 3 m/s
  through a random stand, same IMU model; same four sources.
* ``victoria_park``: the real ACFR run (../shared/datasets). Its raw laser ranges are not in
  the redistribution, only ACFR's per-scan tree detections: the "lidar" frames are the
  detected trunk centres (a landmark scan of 0-15 points), registered by the same KISS-ICP
  scan-to-map code with ``min_points`` 3; wheel speed and the steering-derived yaw rate (no
  gyro on that car) replace the IMU. Scored by ATE against the screened GPS
  (:func:`stemmap.eval.trajectory.screen_gps`, one rigid alignment, every kept fix).

Metrics: ``drift_percent`` = end-point position error / distance driven x 100 (every source
starts at the true pose); ``rpe20_percent`` = mean translation RPE over 20 m stretches / 20 m x
100 (:func:`stemmap.eval.trajectory.rpe`). ``frames_per_s``: KISS-ICP registration speed (wall
clock, one thread); the machine is shared and loaded (the load average is reported), so read
absolute speeds as a lower bound.

Usage::

    python benchmarks/odometry.py [--parts sim3d,sim2d,victoria_park] [--frames 400]
        [--azimuth-step 0.2] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from typing import Any

import numpy as np

from stemmap.eval.trajectory import rpe
from stemmap.odometry.fusion import fuse_sources
from stemmap.odometry.inertial import fuse_front_ends, gyro_source, motion_prior, wheel_source
from stemmap.odometry.lidar import LidarOdometryConfig, lidar_odometry
from stemmap.types import Trajectory, wrap_angle


def _distance(truth: Trajectory) -> float:
    return float(np.sum(np.hypot(*np.diff(truth.poses[:, :2], axis=0).T)))


def _score(traj: Trajectory, truth: Trajectory) -> dict[str, float]:
    end = traj.interpolate(truth.times[-1:])[0]
    dist = _distance(truth)
    r = rpe(traj, truth, delta=20.0)
    return {
        "drift_percent": round(100.0 * float(np.hypot(*(end[:2] - truth.poses[-1, :2]))) / dist, 3),
        "rpe20_percent": round(100.0 * r.trans_mean / 20.0, 3) if r else math.nan,
        "end_error_m": round(float(np.hypot(*(end[:2] - truth.poses[-1, :2]))), 3),
    }


def _four_sources(
    frames: list[tuple[float, Any]], log: Any, truth: Trajectory, cfg: LidarOdometryConfig
) -> dict[str, Any]:
    p0 = truth.poses[0]
    t0 = time.perf_counter()
    lidar = lidar_odometry(frames, cfg, initial_pose=p0)
    dt = time.perf_counter() - t0
    aided = lidar_odometry(
        frames, cfg, initial_pose=p0, motion_prior=motion_prior(log, initial_pose=p0)
    )
    fused = fuse_front_ends(lidar=aided, inertial=log)
    dr = fuse_sources([gyro_source(log), wheel_source(log)], initial_pose=p0)
    out: dict[str, Any] = {
        "lidar_only": _score(lidar.trajectory(), truth),
        "imu_wheel": _score(dr.trajectory, truth),
        "lidar_imu": _score(aided.trajectory(), truth),
        "fused": _score(fused.trajectory, truth),
        "held_frames": int(lidar.held.sum()),
        "frames_per_s": round(len(frames) / dt, 1),
        "calibration": dict(
            zip(fused.calibration_names, np.round(fused.calibration, 5).tolist(), strict=True)
        ),
        "rejected": fused.n_rejected.tolist(),
    }
    single = min(out["lidar_only"]["drift_percent"], out["imu_wheel"]["drift_percent"])
    out["fused_beats_every_single_source"] = out["fused"]["drift_percent"] < single
    return out


def part_sim3d(n_frames: int, az_step: float, seed: int) -> dict[str, Any]:
    from stemmap.sim import s_curve_path
    from stemmap.sim.drive import simulate_lidar_drive
    from stemmap.sim.lidar import lidar_preset, random_stand3d

    size = (220.0, 70.0)
    stand = random_stand3d(150, size, min_spacing=4.0, rng=seed + 1)
    t0 = time.perf_counter()
    d = simulate_lidar_drive(
        stand,
        s_curve_path(size, amplitude=12.0, length_scale=20.0, n_points=20),
        speed=4.0,
        lidar=lidar_preset("vlp16", azimuth_step_deg=az_step),
        max_frames=n_frames,
        rng=seed + 3,
    )
    t_sim = time.perf_counter() - t0
    cfg = LidarOdometryConfig()
    frames = [(float(t), f.xyz) for t, f in zip(d.times, d.frames, strict=True)]
    res = _four_sources(frames, d.imu.log, d.true_poses, cfg)
    k0 = len(frames) // 2
    blk = [(t, np.zeros((0, 3)) if k0 <= k < k0 + 25 else f) for k, (t, f) in enumerate(frames)]
    res_blackout = _four_sources(blk, d.imu.log, d.true_poses, cfg)
    return {
        "scenario": {
            "frames": len(frames),
            "distance_m": round(_distance(d.true_poses), 1),
            "speed_m_s": 4.0,
            "lidar": f"vlp16, 16 beams, {az_step} deg azimuth, 10 Hz",
            "trees_left_after_corridor": d.stand.n_trees,
            "points_per_frame_median": int(np.median([f.xyz.shape[0] for f in d.frames])),
            "imu": "xsens preset: gyro bias 0.2 deg/s + walk, noise 0.1 deg/s @100 Hz; "
            "wheel 2 % fast, slips 0.05/s",
            "simulation_s": round(t_sim, 1),
        },
        "nominal": res,
        "blackout_2p5s": res_blackout,
    }


def part_sim2d(seed: int) -> dict[str, Any]:
    from stemmap.sim.drive import simulate_s_curve_drive

    run, imu = simulate_s_curve_drive(
        300, (200.0, 70.0), amplitude=12.0, length_scale=20.0, n_waypoints=16, seed=seed + 3
    )
    cfg = LidarOdometryConfig(max_range=run.scanner.range_max, min_range=0.1)
    frames = list(zip(run.true_poses.times, run.scans, strict=True))
    res = _four_sources(frames, imu.log, run.true_poses, cfg)
    return {
        "scenario": {
            "scans": len(frames),
            "distance_m": round(_distance(run.true_poses), 1),
            "speed_m_s": 3.0,
            "scanner": "sick_lms preset (0.5 deg, 80 m) at 10 Hz",
        },
        "nominal": res,
    }


def part_victoria_park() -> dict[str, Any]:
    from stemmap.datasets import find_datasets_dir
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate
    from stemmap.io.imu import InertialLog
    from stemmap.slam.base import sensor_poses
    from stemmap.slam.motion import preintegrate

    root = find_datasets_dir()
    if root is None or not (root / "victoria_park").is_dir():
        return {"skipped": "../shared/datasets/victoria_park not found"}
    vp = load_victoria_park(root / "victoria_park")
    m = vp.model
    fr = vp.frames
    keep_gps = vp.screened_gps()
    # trunk centres of each scan, sensor frame (range to the surface + radius)
    r = fr.ranges + np.where(np.isfinite(fr.diameters), fr.diameters / 2.0, 0.0)
    pts = np.column_stack((r * np.cos(fr.bearings), r * np.sin(fr.bearings)))
    frames = []
    last = -math.inf
    for f in range(len(fr.times)):
        t = float(fr.times[f])
        if not t > last:
            continue
        last = t
        frames.append((t, pts[fr.ptr[f] : fr.ptr[f + 1]]))
    times = np.array([t for t, _ in frames])
    # wheel odometry carried to the laser (Ackermann model, rear encoder + steering; no gyro
    # on that car): the laser's forward speed and yaw rate at the odometry rate
    c = vp.controls
    ct = np.unique(c.times)
    sp = sensor_poses(preintegrate(m, c, ct, with_covariance=False).poses, m.sensor_offset)
    dtc = np.diff(ct)
    d = np.diff(sp, axis=0)
    fwd = (np.cos(sp[:-1, 2]) * d[:, 0] + np.sin(sp[:-1, 2]) * d[:, 1]) / dtc
    yaw_rate = wrap_angle(d[:, 2]) / dtc
    log = InertialLog(
        ct[1:],
        np.column_stack((np.zeros(dtc.size), np.zeros(dtc.size), yaw_rate)),
        np.full((dtc.size, 3), np.nan),
        fwd,
    )
    dr_poses = sensor_poses(preintegrate(m, c, times, with_covariance=False).poses, m.sensor_offset)
    truth0 = dr_poses[0]
    cfg = LidarOdometryConfig(max_range=80.0, min_range=0.5, min_points=3, voxel_size=1.0)
    t0 = time.perf_counter()
    lidar = lidar_odometry(frames, cfg, initial_pose=truth0)
    t_lidar = time.perf_counter() - t0
    aided = lidar_odometry(frames, cfg, initial_pose=truth0, motion_prior=motion_prior(log))
    fused = fuse_front_ends(lidar=aided, inertial=log)
    dr = Trajectory(times, dr_poses, frame="odom")

    def score(tr: Trajectory) -> dict[str, float]:
        a = ate(tr, vp.gps_times, vp.gps_xy, keep=keep_gps)
        return {"ate_rmse_m": round(a.rmse, 2), "ate_max_m": round(a.max, 2), "n_fixes": a.n}

    return {
        "data": "ACFR Victoria Park (tree detections as landmark scans), wheel + steering",
        "frames": len(frames),
        "held_frames": int(lidar.held.sum()),
        "ackermann_dead_reckoning": score(dr),
        "lidar_only": score(lidar.trajectory()),
        "lidar_wheel": score(aided.trajectory()),
        "fused": score(fused.trajectory),
        "frames_per_s": round(len(frames) / t_lidar, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="sim3d,sim2d,victoria_park")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--azimuth-step", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    out: dict[str, Any] = {
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
    }
    if "sim3d" in parts:
        out["sim3d"] = part_sim3d(args.frames, args.azimuth_step, args.seed)
    if "sim2d" in parts:
        out["sim2d"] = part_sim2d(args.seed)
    if "victoria_park" in parts:
        out["victoria_park"] = part_victoria_park()
    out["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    json.dump(out, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
