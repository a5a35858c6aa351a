"""Controls from a pose-output odometry, ``lateral="drop"`` against ``"keep"``
(:func:`stemmap.slam.munjer.controls_from_trajectory`), through every back-end on a simulated
2D scan log.

Usage: python benchmarks/pose_controls.py [--seed 3] [--rate-hz 5] [--backends treedb ekf
       fastslam isam2] [--sigma-lateral 0.05 0.0] [--out result.json]

The log is ``stemmap sim scans --seed SEED --rate-hz RATE`` (the one tests/cli/
test_map_motion.py maps); the motion source is ``stemmap map --motion lidar``'s: KISS-ICP
scan-to-map odometry on the log's own scans (:func:`stemmap.cli._map_motion.motion_trajectory`),
made into controls three ways: ``drop`` (speed and yaw rate per interval, the default),
``keep`` with each ``--sigma-lateral`` (m/s; controls through every pose,
:meth:`stemmap.slam.base.Controls.from_trajectory`). The motion noise is the CLI's default
(``UnicycleModel()``: 0.05 m/s, 0.01 rad/s). Each back-end runs with its defaults on the
log's scan detections (:func:`stemmap.cli._map_inputs.file_problem`).

Prints one JSON object: ``odometry`` (the lidar path's RMSE against the truth, its per-step
error std along / across the heading, the lateral increments' sum) and ``rows``: per
``{controls}.{backend}`` the path RMSE (m) against the simulator's poses, the map frame put
on the true first pose.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.cli import app
from stemmap.cli._map_inputs import file_problem
from stemmap.cli._map_motion import Motion, motion_trajectory
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.slam.base import make_backend
from stemmap.slam.motion import UnicycleModel, between, compose
from stemmap.slam.munjer import controls_from_trajectory


def _rmse(truth: Any, times: Any, poses: Any) -> float:
    world = compose(truth.poses[0], poses)
    err = np.hypot(*(world[:, :2] - truth.interpolate(times)[:, :2]).T)
    return float(np.sqrt(np.mean(err**2)))


def main() -> None:
    from typer.testing import CliRunner

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--rate-hz", type=float, default=5.0)
    ap.add_argument("--backends", nargs="+", default=["treedb", "ekf", "fastslam", "isam2"])
    ap.add_argument("--sigma-lateral", type=float, nargs="+", default=[0.05, 0.0])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "run.npz"
        args = ["sim", "scans", "--out", str(log), "--seed", str(a.seed), "--rate-hz"]
        res = CliRunner().invoke(app, [*args, str(a.rate_hz), "-q"])
        if res.exit_code != 0:
            raise SystemExit(res.output)
        truth = read_trajectory_csv(Path(tmp) / "run_poses.csv")
        traj, _ = motion_trajectory(log, Motion.lidar, camera=None, imu=None)
        problem, _ = file_problem(log, None, (0.0, 0.0), motion=traj)
    d = between(traj.poses[:-1], traj.poses[1:])
    e = d - between(truth.poses[:-1], truth.poses[1:])
    out: dict[str, Any] = {
        "odometry": {
            "path_rmse_m": _rmse(truth, traj.times, traj.poses),
            "step_error_std_along_m": float(np.std(e[:, 0])),
            "step_error_std_lateral_m": float(np.std(e[:, 1])),
            "lateral_increments_sum_m": float(np.abs(d[:, 1]).sum()),
            "distance_m": float(np.hypot(d[:, 0], d[:, 1]).sum()),
        },
        "rows": {},
    }
    base = UnicycleModel()
    variants: dict[str, Any] = {"drop": (problem.controls, problem.motion)}
    for s in a.sigma_lateral:
        variants[f"keep_lateral_{s:g}"] = controls_from_trajectory(
            traj,
            sigma_speed=base.sigma_speed,
            sigma_yaw_rate=base.sigma_steer,
            lateral="keep",
            sigma_lateral=s,
        )
    for name, (controls, model) in variants.items():
        p = replace(problem, controls=controls, motion=model)
        for be in a.backends:
            r = make_backend(be).run(p)
            out["rows"][f"{name}.{be}"] = _rmse(truth, r.trajectory.times, r.trajectory.poses)
    out["scenario"] = {"seed": a.seed, "rate_hz": a.rate_hz, "motion": "lidar"}
    text = json.dumps(out, indent=1)
    if a.out is not None:
        a.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
