"""The Munjer 2025 chain on a simulated drive: ``stemmap sim munjer`` -> ``stemmap odometry``
(KISS-ICP + IMU / wheel EKF on the bundle's lidar frames) -> ``stemmap map --odometry traj.csv``,
and the same in one command, ``stemmap map --motion lidar --imu``."""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.imu import read_imu_csv
from stemmap.io.lidar_frames import open_frames
from stemmap.io.trajectory import read_trajectory_csv

runner = CliRunner()


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("munjer_lo")
    out = d / "drive.npz"
    # 10 s at 4 m/s: the first straight and the first half circle, lidar only
    res = runner.invoke(
        app,
        ["sim", "munjer", "--out", str(out), "--seed", "1", "--duration", "10",
         "--camera-every", "0", "-q"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def traj(drive: Path) -> Path:
    out = drive.with_name("traj.csv")
    imu = drive.with_name("drive_imu.csv")
    res = runner.invoke(app, ["odometry", str(drive), "--imu", str(imu), "--out", str(out), "-q"])
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def chain_map(
    drive: Path, traj: Path, tmp_path_factory: pytest.TempPathFactory
) -> Callable[[str], Path]:
    """``stemmap map DRIVE --frontend F --odometry traj.csv``, run once per frontend in this
    module: the accuracy test and the one-command test read the same run of ``ours``."""
    done: dict[str, Path] = {}

    def run(frontend: str) -> Path:
        if frontend not in done:
            out = tmp_path_factory.mktemp("chain") / frontend
            res = runner.invoke(
                app,
                ["map", str(drive), "--frontend", frontend, "--odometry", str(traj),
                 "--out", str(out), "--no-progress"],
            )  # fmt: skip
            assert res.exit_code == 0, res.output
            done[frontend] = out
        return done[frontend]

    return run


def _xy(path: Path) -> np.ndarray:
    rows = list(csv.DictReader(path.open()))
    return np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(-1, 2)


def _in_world(drive: Path, xy: np.ndarray) -> np.ndarray:
    """Odometry-frame points (origin = the first lidar pose) -> the simulator's world frame."""
    x0, y0, th = read_trajectory_csv(drive.with_name("drive_poses.csv")).poses[0]
    c, s = np.cos(th), np.sin(th)
    return xy @ np.array([[c, s], [-s, c]]) + (x0, y0)


def test_bundle_frames_and_imu(drive: Path) -> None:
    seq = open_frames(drive)
    assert seq.kind == "bundle" and len(seq) == 101
    t, first = next(iter(seq))
    assert t == 0.0 and first.xyz.shape[1] == 3 and len(first.xyz) > 1000  # type: ignore[union-attr]
    log = read_imu_csv(drive.with_name("drive_imu.csv"))
    assert log.has_gyro and log.has_wheel and log.times[-1] == pytest.approx(9.98)


def test_odometry_trajectory_is_a_map_motion_source(drive: Path, traj: Path) -> None:
    """One pose per frame on the bundle's time base, drift well under the 1 % target."""
    est = read_trajectory_csv(traj)
    truth = read_trajectory_csv(drive.with_name("drive_poses.csv"))
    np.testing.assert_allclose(est.times, truth.times, atol=1e-9)
    err = np.hypot(*(_in_world(drive, est.poses[:, :2]) - truth.poses[:, :2]).T)
    dist = np.hypot(*np.diff(truth.poses[:, :2], axis=0).T).sum()
    # measured: <= 0.09 m over a 59 m lap (seed 0); 1 % of 40 m = 0.4 m
    assert err.max() < 0.01 * dist, err.max()


@pytest.mark.parametrize("frontend", ["eb-lidar", "ours"])
def test_chain_map_accuracy(drive: Path, chain_map: Callable[[str], Path], frontend: str) -> None:
    """Measured on 10 s drives, seeds 0/1/2 (matched within 1 m, position RMSE): ours 10/12,
    12/13, 10/12 trees, 0.04-0.09 m; EB-LiDAR 4-5 trees, 0.07-0.13 m (its recall on 16-beam
    frames is issue 15's other bullet). Bounds: every mapped tree true (EB-LiDAR may map one
    bush), ours >= 10, EB-LiDAR >= 3, RMSE <= 0.2 m (issue target 0.3 m)."""
    mapped = _in_world(drive, _xy(chain_map(frontend) / "trees.csv"))
    truth = _xy(drive.with_name("drive_trees.csv"))
    d = np.min(np.hypot(*(mapped[:, None, :] - truth[None]).transpose(2, 0, 1)), axis=1)
    ok = d < 1.0
    assert ok.sum() >= (10 if frontend == "ours" else 3), d
    assert ok.sum() >= len(d) - (1 if frontend == "eb-lidar" else 0), d
    assert np.sqrt(np.mean(d[ok] ** 2)) <= 0.2, d


def test_one_command_equals_chain(
    drive: Path, chain_map: Callable[[str], Path], tmp_path: Path
) -> None:
    """``--motion lidar --imu`` runs the same odometry (``stemmap odometry``'s defaults)."""
    imu = str(drive.with_name("drive_imu.csv"))
    out = tmp_path / "lidar"
    res = runner.invoke(
        app,
        ["map", str(drive), "--frontend", "ours", "--motion", "lidar", "--imu", imu,
         "--out", str(out), "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    chain = _xy(chain_map("ours") / "trees.csv")  # the chain: --odometry traj.csv
    np.testing.assert_allclose(chain, _xy(out / "trees.csv"), atol=1e-3)  # CSV rounding of poses


def test_imu_needs_lidar_odometry(drive: Path, tmp_path: Path) -> None:
    imu = str(drive.with_name("drive_imu.csv"))
    res = runner.invoke(app, ["map", str(drive), "--imu", imu, "--out", str(tmp_path / "x")])
    assert res.exit_code != 0 and "--motion lidar or fused" in res.output
