"""Benchmark: the lidar odometry's drift estimate (``drift_estimate_percent`` of ``stemmap map
--motion lidar|fused``) against the measured drift, over simulated runs at several frame
rates, speeds and stands.

Runs (each registered lidar-only, ``lidar``, and with ``--imu``, ``lidar_imu``):

* ``scans_*``: ``stemmap sim scans`` 2D logs (SICK LMS preset, 30 m of the loop), stands
  ``random`` and ``rows`` at 10, 25 and 75 Hz and 1 m/s, and the random stand at 0.5 and 2 m/s;
  the IMU is the log's noisy wheel odometry written as ``gyro_z = yaw_rate``,
  ``wheel_speed = speed`` (as benchmarks/odometry_distance.py);
* ``munjer_*``: ``stemmap sim munjer`` drives (VLP-16 at 10 Hz, lidar frames only): the park
  and orchard stadium lap at 4 m/s (59 m), the park at 1 m/s for 20 s, the orchard at 0.5 m/s
  for 20 s; the IMU is the drive's simulated XSens gyro + wheel speed.

Per run group (seeds pooled) it prints: ``end_rms`` (RMS over seeds of the end-point error,
% of the true length; the map frame put on the true first pose), ``rpe10_rms`` (RMS of the
translational RPE over 10 m stretches, % of 10 m), ``old`` (median of the estimate before Dec 4:
every frame's floored increment covariance as an independent step) and ``new`` (median of the
reported estimate, :meth:`~stemmap.odometry.lidar.LidarOdometryResult.drift_xy_variance`),
and the ratios ``old / end_rms``, ``new / end_rms`` and ``new10 / rpe10_rms`` (the estimate
scaled to 10 m as a random walk, ``new * sqrt(D / 10)``). A stadium lap ends where it started,
inside the local map of its first metres, so its end error is not a drift: read the RPE there.

Usage::

    python benchmarks/drift_calibration.py [--seeds 0 1 2 3 4 5] [--munjer-seeds 0 1 2]
        [--only scans|munjer] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from odometry_distance import _invoke, _wheel_as_imu
from stemmap.cli._map_motion import LIDAR_DEFAULTS, _random_walk_percent
from stemmap.cli._odometry import lidar_front_end
from stemmap.eval.trajectory import path_length, rpe
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.slam.motion import compose

_SCANS = {
    f"scans_{lay}_{hz}hz_1ms": [
        "--layout",
        lay,
        "--rate-hz",
        str(hz),
        "--speed",
        "1",
        "--n-scans",
        str(30 * hz),
    ]
    for lay in ("random", "rows")
    for hz in (10, 25, 75)
} | {
    "scans_random_25hz_0.5ms": ["--rate-hz", "25", "--speed", "0.5", "--n-scans", "1500"],
    "scans_random_25hz_2ms": ["--rate-hz", "25", "--speed", "2", "--n-scans", "375"],
    "scans_random_10hz_2ms": ["--rate-hz", "10", "--speed", "2", "--n-scans", "150"],
}
_MUNJER = {
    "munjer_park_4ms_lap": ["--layout", "park", "--speed", "4"],
    "munjer_orchard_4ms_lap": ["--layout", "orchard", "--speed", "4"],
    "munjer_park_1ms_20s": ["--layout", "park", "--speed", "1", "--duration", "20"],
    "munjer_orchard_0.5ms_20s": ["--layout", "orchard", "--speed", "0.5", "--duration", "20"],
}


def _measure(log: Path, imu: Path | None) -> dict[str, float]:
    """One registration: the estimates (old and new) and the measured drift."""
    truth = read_trajectory_csv(log.with_name(f"{log.stem}_poses.csv"))
    traj, lidar, _, _ = lidar_front_end(log, imu=imu, quiet=True, **LIDAR_DEFAULTS)
    dist = path_length(traj)  # the reported distance_m, as motion_trajectory
    c = lidar.increment_cov
    old = _random_walk_percent(c[:, 0, 0] + c[:, 1, 1], dist)
    new = _random_walk_percent([lidar.drift_xy_variance(dist)], dist)
    true_m = path_length(truth, min_step=0.0)
    end = compose(truth.poses[0], traj.poses[-1])[:2] - truth.interpolate(traj.times[-1:])[0][:2]
    world = type(traj)(traj.times, compose(truth.poses[0], traj.poses))
    r = rpe(world, truth, delta=10.0)
    return {
        "distance_m": dist,
        "old": float("nan") if old is None else old,
        "new": float("nan") if new is None else new,
        "end": 100.0 * float(np.hypot(*end)) / true_m,
        "rpe10": 100.0 * r.trans_rmse / 10.0 if r else float("nan"),
    }


def _summary(runs: list[dict[str, float]]) -> dict[str, Any]:
    g = {k: np.array([r[k] for r in runs]) for k in runs[0]}
    end_rms = float(np.sqrt(np.mean(g["end"] ** 2)))
    rpe_rms = float(np.sqrt(np.nanmean(g["rpe10"] ** 2)))
    old, new = float(np.median(g["old"])), float(np.median(g["new"]))
    new10 = new * math.sqrt(float(np.mean(g["distance_m"])) / 10.0)
    return {
        "n": len(runs),
        "distance_m": round(float(np.mean(g["distance_m"])), 1),
        "end_rms": round(end_rms, 3),
        "rpe10_rms": round(rpe_rms, 3),
        "old": round(old, 3),
        "new": round(new, 3),
        "old_over_end": round(old / end_rms, 2),
        "new_over_end": round(new / end_rms, 2),
        "new10_over_rpe10": round(new10 / rpe_rms, 2),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--munjer-seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--only", choices=["scans", "munjer"], default=None)
    ap.add_argument("--work", type=Path, default=None, help="Keep the simulated logs here.")
    args = ap.parse_args(argv)
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        plan = []
        if args.only != "munjer":
            plan += [("scans", n, o, args.seeds) for n, o in _SCANS.items()]
        if args.only != "scans":
            plan += [("munjer", n, o, args.munjer_seeds) for n, o in _MUNJER.items()]
        for kind, name, opts, seeds in plan:
            res: dict[str, list[dict[str, float]]] = {"lidar": [], "lidar_imu": []}
            for seed in seeds:
                log = work / f"{name}_s{seed}.npz"
                sim = ["sim", kind, "--out", str(log), "--seed", str(seed), "-q", *opts]
                if kind == "munjer":
                    _invoke([*sim, "--camera-every", "0"])
                    imu = log.with_name(f"{log.stem}_imu.csv")
                else:
                    _invoke(sim)
                    odo = log.with_name(f"{log.stem}_odometry.csv")
                    imu = _wheel_as_imu(odo, work / f"{log.stem}_wheel.csv")
                res["lidar"].append(_measure(log, None))
                res["lidar_imu"].append(_measure(log, imu))
            out[name] = {k: _summary(v) for k, v in res.items()}
            print(json.dumps({name: out[name]}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
