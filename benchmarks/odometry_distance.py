"""Benchmark: the distance travelled that ``stemmap odometry`` / ``stemmap map --motion lidar``
report, summed step by step (before) and by :func:`stemmap.eval.trajectory.path_length`
(after), against the simulator's true path length.

Prints one JSON object, one entry per drive and motion source:

* ``munjer_*``: ``stemmap sim munjer`` drives (VLP-16 at 10 Hz, park or orchard, one stadium lap
  at 4 m/s, or 20 s at 1 and 0.5 m/s), lidar frames only (``--camera-every 0``);
* ``scans_*``: ``stemmap sim scans`` 2D logs (SICK LMS preset: 75 Hz, 1 m/s, ``--n-scans``
  scans, the ``random`` stand or orchard ``rows``).

Each drive is run ``lidar`` (no IMU) and ``lidar_imu``: with the drive's IMU CSV (Munjer: the
simulated XSens gyro + wheel speed) or, for the 2D logs, the log's own noisy wheel odometry
written as ``gyro_z = yaw_rate``, ``wheel_speed = speed``. The motion record is
:func:`stemmap.cli._map_motion.motion_trajectory`'s (what ``stemmap map --motion lidar
[--imu]`` writes to metrics.json; its ``lidar.distance_m`` is ``stemmap odometry``'s summary).

Per entry: ``true_m`` (the true poses' polyline, every pose), ``before_m`` (sum of the estimated
steps, the code before the fix), ``after_m`` (the reported ``distance_m``), their errors in % of
the true length, ``drift_estimate_before`` / ``_after`` (``drift_estimate_percent``, which is
inversely proportional to the square root of the distance since the Dec 4 drift estimate fix,
docs/algorithms/odometry.md "Drift estimate"; to the distance before it, the table there)
and ``end_drift_percent`` (the measured end-point
error, % of the true length; the map frame put on the true first pose).

Usage::

    python benchmarks/odometry_distance.py [--seed 0] [--n-scans 3000] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._map_motion import Motion, motion_trajectory
from stemmap.eval.trajectory import path_length
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.slam.motion import compose

_MUNJER = {
    "munjer_park_4ms_lap": ["--layout", "park", "--speed", "4"],
    "munjer_orchard_4ms_lap": ["--layout", "orchard", "--speed", "4"],
    "munjer_park_1ms_20s": ["--layout", "park", "--speed", "1", "--duration", "20"],
    "munjer_orchard_0.5ms_20s": ["--layout", "orchard", "--speed", "0.5", "--duration", "20"],
}
_SCANS = {
    "scans_random_75hz_1ms": ["--layout", "random"],
    "scans_rows_75hz_1ms": ["--layout", "rows"],
}


def _invoke(args: list[str]) -> None:
    res = CliRunner().invoke(app, args)
    if res.exit_code != 0:
        raise RuntimeError(f"stemmap {' '.join(args)} failed: {res.output}")


def _wheel_as_imu(odometry_csv: Path, out: Path) -> Path:
    odo = np.loadtxt(odometry_csv, delimiter=",", skiprows=1).reshape(-1, 3)
    np.savetxt(out, odo[:, [0, 2, 1]], delimiter=",", header="time_s,gyro_z,wheel_speed",
               comments="")  # fmt: skip
    return out


def _measure(bundle: Path, imu: Path | None) -> dict[str, Any]:
    truth = read_trajectory_csv(bundle.with_name(f"{bundle.stem}_poses.csv"))
    traj, info = motion_trajectory(bundle, Motion.lidar, camera=None, imu=imu)
    true_m = path_length(truth, min_step=0.0)
    before = path_length(traj, min_step=0.0)
    after = float(info["distance_m"])
    est = info["drift_estimate_percent"]
    end = compose(truth.poses[0], traj.poses[-1])[:2] - truth.poses[-1, :2]
    return {
        "frames": len(traj),
        "true_m": round(true_m, 3),
        "before_m": round(before, 3),
        "before_error_percent": round(100.0 * (before / true_m - 1.0), 2),
        "after_m": round(after, 3),
        "after_error_percent": round(100.0 * (after / true_m - 1.0), 2),
        "drift_estimate_before": None if est is None else round(est * (after / before) ** 0.5, 3),
        "drift_estimate_after": None if est is None else round(est, 3),
        "end_drift_percent": round(100.0 * float(np.hypot(*end)) / true_m, 3),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-scans", type=int, default=3000)
    ap.add_argument("--work", type=Path, default=None, help="Keep the simulated logs here.")
    args = ap.parse_args(argv)
    out: dict[str, Any] = {"seed": args.seed, "load_average_1min": round(os.getloadavg()[0], 2)}
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        seed = ["--seed", str(args.seed), "-q"]
        for name, opts in _MUNJER.items():
            bundle = work / f"{name}.npz"
            _invoke(["sim", "munjer", "--out", str(bundle), "--camera-every", "0", *opts, *seed])
            imu = bundle.with_name(f"{name}_imu.csv")
            out[name] = {"lidar": _measure(bundle, None), "lidar_imu": _measure(bundle, imu)}
        for name, opts in _SCANS.items():
            log = work / f"{name}.npz"
            n = ["--n-scans", str(args.n_scans)]
            _invoke(["sim", "scans", "--out", str(log), "--speed", "1", *n, *opts, *seed])
            imu = _wheel_as_imu(log.with_name(f"{name}_odometry.csv"), work / f"{name}_wheel.csv")
            out[name] = {"lidar": _measure(log, None), "lidar_imu": _measure(log, imu)}
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
