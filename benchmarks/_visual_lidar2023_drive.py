"""The drives of benchmarks/visual_lidar2023.py and their two odometry sources: each loop
simulated on orchard rows inside a forest edge, its visual odometry on rendered stereo frames
(cached per loop: rendering and VO are 95 % of the benchmark's time) and its lidar odometry
(KISS-ICP on the simulated 2D scans), both as vehicle trajectories in the world frame."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np


def _lidar_odometry(run: Any) -> tuple[Any, Any]:
    """KISS-ICP on the run's 2D scans, as the vehicle trajectory in the world frame and the
    result (for its covariances)."""
    from stemmap.odometry.lidar import LidarOdometryConfig, lidar_odometry
    from stemmap.sim.unicycle import compose_poses
    from stemmap.types import Trajectory

    sensor = run.true_poses
    cfg = LidarOdometryConfig(max_range=run.scanner.range_max, min_range=0.1)
    res = lidar_odometry(
        zip(sensor.times, run.scans, strict=True), cfg, initial_pose=sensor.poses[0]
    )
    o = run.sensor_offset.as_array()  # sensor = vehicle * offset
    c, s = math.cos(o[2]), math.sin(o[2])
    inv = np.array([-(c * o[0] + s * o[1]), s * o[0] - c * o[1], -o[2]])
    vehicle = Trajectory(res.times, compose_poses(res.trajectory().poses, inv), frame="world")
    return vehicle, res


def _world(traj: Any, pose0: np.ndarray) -> Any:
    """A trajectory given in the frame of its first pose, placed at ``pose0`` in the world."""
    from stemmap.sim.unicycle import compose_poses
    from stemmap.types import Trajectory

    return Trajectory(traj.times, compose_poses(pose0, traj.poses), frame="world")


def prepare_loop(
    name: str, waypoints: list[tuple[float, float]], seed: int, cache: Path | None = None
) -> dict[str, Any]:
    """Simulate the drive, run (or load) the visual odometry and run the lidar odometry."""
    from stemmap.odometry.visual import (
        StereoCalibration,
        VisualFrame,
        VisualOdometryResult,
        planar_from_camera,
        run_visual_odometry,
    )
    from stemmap.sim.forest import row_stand
    from stemmap.sim.render import (
        StereoCamera,
        iter_stereo,
        stand3d_from_stand,
        with_forest_edge,
    )
    from stemmap.sim.scanner import scanner_preset
    from stemmap.sim.trajectory import simulate_run

    rng = np.random.default_rng(seed)
    rows = row_stand(3, 7, row_spacing=4.0, tree_spacing=3.0, jitter=0.1, rng=rng)
    stand = with_forest_edge(rows, rng=rng)
    cam = StereoCamera(rate_hz=5.0)
    run = simulate_run(
        stand,
        np.array(waypoints, dtype=np.float64),
        scanner=scanner_preset("rplidar", angle_increment=math.radians(0.25)),
        speed=1.0,
        rate_hz=cam.rate_hz,
        odometry_noise="wheel",
        rng=seed,
    )
    truth = run.vehicle_poses
    pose0 = truth.poses[0]
    t0 = time.perf_counter()
    cached = None if cache is None else cache / f"vo_{name}_{seed}.npz"
    if cached is not None and cached.is_file():
        z = np.load(cached)
        vo = VisualOdometryResult(
            z["times"], z["poses"], z["status"], z["n_tracks"], z["n_inliers"]
        )
    else:
        frames = iter_stereo(stand3d_from_stand(run.stand, rng=seed), truth, cam, rng=seed)
        cal = StereoCalibration(
            cam.fx, cam.fx, cam.K[0, 2], cam.K[1, 2], cam.width, cam.height, cam.baseline
        )
        # rendering and odometry interleave (frames are rendered on demand)
        vo = run_visual_odometry((VisualFrame(f.time, f.left, f.right) for f in frames), cal)
        if cache is not None and cached is not None:
            cache.mkdir(parents=True, exist_ok=True)
            np.savez(
                cached,
                times=vo.times,
                poses=vo.poses,
                status=vo.status,
                n_tracks=vo.n_tracks,
                n_inliers=vo.n_inliers,
            )
    t_render_vo = time.perf_counter() - t0
    visual = _world(planar_from_camera(vo, cam.vehicle_from_camera()), pose0)
    t0 = time.perf_counter()
    lidar, lres = _lidar_odometry(run)
    t_lidar = time.perf_counter() - t0
    return {
        "name": name,
        "seed": seed,
        "run": run,
        "truth": truth,
        "cam": cam,
        "vo": vo,
        "visual": visual,
        "lidar": lidar,
        "lres": lres,
        "t_render_vo": t_render_vo,
        "t_lidar": t_lidar,
    }
