"""The lidar odometry's drift estimate (``drift_estimate_percent`` of ``stemmap map --motion
lidar``) against the measured end-point drift, at two frame rates.

Until Dec 4 the estimate summed every frame's floored registration covariance (2 cm per axis)
as an independent step: it grew with the square root of the frame count, 9x the measured end
drift at 10 Hz and 26x at 75 Hz on 30 m simulated runs (docs/algorithms/odometry.md "Drift
estimate"). Scan-to-map poses drift per distance, so the estimate is now a random walk in
distance (``LidarOdometryConfig.drift_xy_per_sqrt_m``, chosen on other seeds and 30 m runs).

Tolerance: the estimate is the 1-sigma (RMS) of the end-point error of a random walk, so it is
compared with the RMS of the end errors over 5 seeds, within 0.5-2x, the RMS read robustly as the
median end error / 0.8326 (for a 2D Gaussian's norm, median / RMS = sqrt(ln 2) = 0.8326). With 5
draws the median's 95 % range is 0.48-1.67x its true value (Monte Carlo); the calibration
runs gave 0.7-1.6x over rates, speeds and stands. The old estimate is 9x or more.

Why the median (Dec 6): with the simulator's SICK at the real LMS200's return threshold (0.3)
seed 12's lidar-only run at 75 Hz drifts 1.52 %, 6.5x the RMS of 14 other seeds (10-24), and
makes 92 % of the 5 seeds' sum of squares; it drifts 0.7-1.3 % in 4 of 8 re-runs at 0.5 too. It
is an excursion of the scan matcher on edge returns (docs/algorithms/odometry.md, "Seed 12's 75 Hz
excursion"), not the random walk the estimate describes (0.96-1.09x the other 14 seeds' RMS).
The tail is its own property, asserted separately and loosely: no run beyond 10x the estimate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._map_motion import Motion, motion_trajectory
from stemmap.eval.trajectory import path_length
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.slam.motion import compose

runner = CliRunner()
SEEDS = (10, 11, 12, 13, 14)  # not the calibration seeds (0-5)


def _run(tmp: Path, rate: int, seed: int) -> tuple[float, float]:
    """(reported drift %, measured end drift %) of a 20 m lidar-only run of a 2D log."""
    out = tmp / f"r{rate}_s{seed}.npz"
    args = ["sim", "scans", "--out", str(out), "--seed", str(seed), "--speed", "1",
            "--rate-hz", str(rate), "--n-scans", str(20 * rate), "-q"]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    truth = read_trajectory_csv(out.with_name(f"{out.stem}_poses.csv"))
    traj, info = motion_trajectory(out, Motion.lidar, camera=None, imu=None)
    assert np.allclose(traj.times, truth.times)
    end = compose(truth.poses[0], traj.poses[-1])[:2] - truth.poses[-1, :2]
    true_m = path_length(truth, min_step=0.0)
    return float(info["drift_estimate_percent"]), 100.0 * float(np.hypot(*end)) / true_m


@pytest.mark.slow
@pytest.mark.parametrize("rate", [10, 75])
def test_drift_estimate_matches_measured_drift(rate: int, tmp_path: Path) -> None:
    runs = np.array([_run(tmp_path, rate, s) for s in SEEDS])
    estimate = float(np.median(runs[:, 0]))
    measured = float(np.median(runs[:, 1])) / np.sqrt(np.log(2.0))
    assert 0.5 <= estimate / measured <= 2.0, (rate, runs.round(3).tolist())
    assert float(np.max(runs[:, 1])) <= 10.0 * estimate, (rate, runs.round(3).tolist())
