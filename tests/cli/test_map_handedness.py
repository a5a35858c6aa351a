"""`stemmap map` warns when the scans turn against the odometry (a clockwise scanner written
with a positive angle_increment, or a yaw rate of the wrong sign): real FORTLS trunks driven
in a loop (docs/reliability.md, "Input conventions")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._map_handedness import mirror_evidence
from stemmap.cli._map_inputs import file_problem

runner = CliRunner()


def _loop_log(datasets_dir: Path, folder: Path) -> dict[str, Path]:
    """Virtual 270-degree scans (0.25 deg, nearest point per beam) of the real FORTLS slice
    from a 3 m loop at 1 m/s and 10 Hz, its exact wheel odometry, and the same log with the
    beams reversed (mirrored) and reversed with a negative increment (correct)."""
    import laspy

    las = laspy.read(datasets_dir / "fortls_slice" / "diameters.laz")
    pts = np.column_stack((las.x, las.y))[::2]
    w = 1.0 / 3.0
    t = np.arange(0.0, 2 * np.pi / w * 1.1, 0.1)
    x, y, th = 3 * np.sin(w * t), 3 - 3 * np.cos(w * t), w * t
    inc, amin, n = np.radians(0.25), -0.75 * np.pi, 1081
    scans = np.full((t.size, n), np.nan)
    for k in range(t.size):
        d = pts - (x[k], y[k])
        c, s = np.cos(th[k]), np.sin(th[k])
        bx, by = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        beam = np.rint((np.arctan2(by, bx) - amin) / inc).astype(np.int64)
        r = np.hypot(bx, by)
        ok = (beam >= 0) & (beam < n) & (r < 30) & (r > 0.3)
        row = np.full(n, np.inf)
        np.minimum.at(row, beam[ok], r[ok])
        scans[k] = np.where(np.isfinite(row), row, np.nan)
    out = {}
    for name, ranges, a0, da in (
        ("loop", scans, amin, inc),
        ("mirrored", scans[:, ::-1], amin, inc),
        ("clockwise", scans[:, ::-1], amin + (n - 1) * inc, -inc),
    ):
        path = folder / f"{name}.npz"
        np.savez(path, ranges=ranges, time=t, angle_min=a0, angle_increment=da, range_max=30.0)
        odo = np.column_stack((t, np.ones_like(t), np.full_like(t, w)))
        np.savetxt(folder / f"{name}_odometry.csv", odo, delimiter=",", comments="",
                   header="time_s,speed,yaw_rate")  # fmt: skip
        out[name] = path
    return out


def test_mirrored_scans_are_reported(tmp_path: Path, datasets_dir: Path) -> None:
    logs = _loop_log(datasets_dir, tmp_path)
    for name, path in logs.items():
        problem, _ = file_problem(path, None, (0.0, 0.0))
        ev = mirror_evidence(problem, 0.0)  # the three scans are centred on the x axis
        assert ev.pairs > 100
        assert ev.mirrored == (name == "mirrored"), (name, ev)
    res = runner.invoke(app, ["map", str(logs["mirrored"]), "--out", str(tmp_path / "m"), "-q"])
    assert res.exit_code == 0, res.output
    assert "turn against the odometry" in " ".join(res.output.split())
    res = runner.invoke(app, ["map", str(logs["clockwise"]), "--out", str(tmp_path / "c"), "-q"])
    assert res.exit_code == 0, res.output
    assert "against the odometry" not in res.output
    trees = np.genfromtxt(tmp_path / "c" / "trees.csv", delimiter=",", names=True)
    assert 15 <= trees.size <= 25  # the slice's ~20 trunks (203 "trees" when mirrored)


def _imu_csv(path: Path, sign: float) -> Path:
    """The loop's gyro (yaw rate 1/3 rad/s counter-clockwise, ``sign`` -1: an FRD IMU whose z
    points down) and wheel speed at 50 Hz."""
    t = np.arange(0.0, 2 * np.pi * 3 * 1.1, 0.02)
    rows = np.column_stack((t, 0 * t, 0 * t, np.full_like(t, sign / 3.0), 0 * t, 0 * t + 1 / 3,
                            np.full_like(t, 9.81), np.ones_like(t)))  # fmt: skip
    head = "time_s,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,wheel_speed"
    np.savetxt(path, rows, delimiter=",", comments="", fmt="%.6f", header=head)
    return path


def test_lidar_motion_checks_the_scans_turns_against_the_gyro(
    tmp_path: Path, datasets_dir: Path
) -> None:
    """`--motion lidar` takes the motion from the scans: a mirrored log is consistent with
    itself (its map is the mirror image, 20 trees). With `--imu` the gyro tells: the scan
    matcher turned against it in every turn (193 of 193, docs/reliability.md). Before Dec 5:
    no word."""
    logs = _loop_log(datasets_dir, tmp_path)
    imu = _imu_csv(tmp_path / "imu.csv", 1.0)
    for name, warned in (("mirrored", True), ("loop", False)):
        res = runner.invoke(
            app,
            ["map", str(logs[name]), "--motion", "lidar", "--imu", str(imu), "--out",
             str(tmp_path / name), "-q"],
        )  # fmt: skip
        assert res.exit_code == 0, res.output
        assert ("turn against the IMU's gyro" in " ".join(res.output.split())) == warned, name


def test_turn_sense_counts_turns_of_each_sense() -> None:
    from stemmap.cli._map_handedness import turn_sense
    from stemmap.types import Trajectory

    t = np.arange(0.0, 60.0, 0.1)
    heading = 0.3 * t  # a steady left turn
    path = Trajectory(t, np.column_stack((0 * t, 0 * t, heading)))
    same, opposite = turn_sense(path.times, path.poses[:, 2], t, heading)
    assert same > 100 and opposite == 0
    same, opposite = turn_sense(path.times, path.poses[:, 2], t, -heading)
    assert opposite > 100 and same == 0
    # a reference that does not turn counts nothing (its sign would be noise)
    assert turn_sense(path.times, path.poses[:, 2], t, 0 * t) == (0, 0)
