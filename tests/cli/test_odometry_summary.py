"""What ``stemmap odometry`` prints: sentences with units and the file written.

It used to print the summary dict key by key (``calibration: {'gyro.yaw_rate_bias': 0.0036,
'wheel.speed_scale': 0.0225}``, a fused run's ``lidar: {...}`` / ``visual: {...}`` as Python
reprs), without a unit or the output's name.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._odometry import summary_lines
from stemmap.io import write_scans_npz
from stemmap.types import ScanBatch

runner = CliRunner()


def _corridor(path: Path, n: int = 40) -> None:
    """Scans of a 2D corridor with posts, driven straight at 0.5 m/s, 10 Hz."""
    ang = np.linspace(-math.pi / 2, math.pi / 2, 181)
    posts = np.array([[x, y] for x in np.arange(-4.0, 30.0, 2.5) for y in (-3.0, 3.5)])
    ranges = np.full((n, ang.size), np.nan)
    for k in range(n):
        rel = posts - [0.05 * k, 0.0]
        b = np.arctan2(rel[:, 1], rel[:, 0])
        d = np.hypot(*rel.T)
        for bi, di in zip(b, d, strict=True):
            j = int(np.argmin(np.abs(ang - bi)))
            for jj in range(max(j - 2, 0), min(j + 3, ang.size)):
                if np.isnan(ranges[k, jj]) or di < ranges[k, jj]:
                    ranges[k, jj] = di
    write_scans_npz(path, ScanBatch(ranges, 0.1 * np.arange(n), ang[0], ang[1] - ang[0]))


def test_cli_prints_the_output_and_units(tmp_path: Path) -> None:
    scans = tmp_path / "scans.npz"
    _corridor(scans)
    out = tmp_path / "traj.csv"
    res = runner.invoke(app, ["odometry", str(scans), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "{" not in res.output  # no Python reprs
    assert "40 lidar frames" in res.output and "traj.csv" in res.output
    dist = json.loads(out.with_name("traj.csv.run.json").read_text())["extra"]["distance_m"]
    assert f"distance travelled: {dist:.3f} m" in res.output


def test_fused_summary_names_units_of_every_part() -> None:
    """The shape motion_trajectory returns for ``--camera`` (nested lidar / visual records)."""
    summary = {
        "source": "fused",
        "visual": {
            "camera": "f/",
            "frames": 50,
            "mode": "stereo",
            "keyframes": 9,
            "lost_frames": 1,
            "distance_m": 20.1,
        },
        "lidar": {
            "frames": 200,
            "held_frames": 2,
            "imu": True,
            "rejected": {"visual odometry": 3, "lidar": 0},
            "calibration": {"gyro.yaw_rate_bias": 0.0012, "visual odometry.speed_scale": -0.01},
            "distance_m": 20.0,
        },
        "imu": "imu.csv",
        "distance_m": 20.0,
        "drift_estimate_percent": 0.22,
        "ekf_final_position_std_m": 0.05,
        "visual_vs_lidar_percent": 1.5,
    }
    text = "\n".join(summary_lines(summary, Path("t.csv")))
    assert "{" not in text
    for part in (
        "200 lidar frames + IMU/wheels, 2 held",
        "-> t.csv",
        "camera (stereo): 50 frames, 9 keyframes, 1 lost",
        "visual odometry 3, lidar 0",
        "gyro.yaw_rate_bias +0.0012 (rad/s)",
        "visual odometry.speed_scale -0.01 (relative",
        "distance travelled: 20.000 m",
        "0.22 % of the distance",
        "0.05 m",
        "1.5 % over 10 m",
    ):
        assert part in text, part


def test_odometry_refuses_scans_that_are_not_metres_and_radians(tmp_path: Path) -> None:
    """`odometry` streams its scans (io.lidar_frames), past read_scans' unit checks: ranges in
    millimetres gave a standing-still trajectory (all 40 frames "held: too few points", 0 m)
    instead of naming the unit; a start angle in degrees went unnoticed."""
    scans = tmp_path / "scans.npz"
    _corridor(scans)
    with np.load(scans) as z:
        fields = dict(z)
    for name, change, expected in (
        ("mm.npz", {"ranges": fields["ranges"] * 1000.0}, "--range-unit"),
        ("deg.npz", {"angle_min": np.float64(-90.0)}, "degrees"),
    ):
        bad = tmp_path / name
        np.savez(bad, **{**fields, **change})
        res = runner.invoke(app, ["odometry", str(bad), "--out", str(tmp_path / f"{name}.csv")])
        assert res.exit_code == 2, res.output
        assert expected in " ".join(res.output.split())
        assert not (tmp_path / f"{name}.csv").exists()
