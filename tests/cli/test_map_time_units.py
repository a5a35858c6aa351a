"""`stemmap map` on a log whose times are not seconds or whose yaw rate is not rad/s: the
real FORTLS loop log (tests/cli/test_map_handedness.py) stamped in nanoseconds gave 0 trees,
exit 0 and no word before Dec 5; now each reader refuses it naming the unit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tests.cli.test_map_handedness import _imu_csv, _loop_log
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._map_inputs import read_odometry_csv
from stemmap.errors import InputError
from stemmap.io.imu import read_imu_csv
from stemmap.io.scans import read_scans

runner = CliRunner()


def _ns(folder: Path, datasets_dir: Path) -> dict[str, Path]:
    """The loop log with ROS-style nanosecond stamps (Unix time, as `rostopic echo -p` and
    many loggers write them)."""
    logs = _loop_log(datasets_dir, folder)
    d = dict(np.load(logs["loop"]))
    d["time"] = d["time"] * 1e9 + 1.7e18
    np.savez(folder / "ns.npz", **d)
    odo = np.genfromtxt(folder / "loop_odometry.csv", delimiter=",", names=True)
    np.savetxt(folder / "ns_odometry.csv",
               np.column_stack((odo["time_s"] * 1e9 + 1.7e18, odo["speed"], odo["yaw_rate"])),
               delimiter=",", header="time_s,speed,yaw_rate", comments="",
               fmt="%.0f,%.6f,%.6f")  # fmt: skip
    deg = np.column_stack((odo["time_s"], odo["speed"], np.degrees(odo["yaw_rate"])))
    np.savetxt(folder / "deg_odometry.csv", deg, delimiter=",", header="time_s,speed,yaw_rate",
               comments="")  # fmt: skip
    return {"loop": logs["loop"], "ns": folder / "ns.npz"}


def test_times_in_nanoseconds_and_yaw_rate_in_degrees_are_refused(
    tmp_path: Path, datasets_dir: Path
) -> None:
    logs = _ns(tmp_path, datasets_dir)
    res = runner.invoke(app, ["map", str(logs["ns"]), "--out", str(tmp_path / "m"), "-q"])
    assert res.exit_code == 2, res.output
    assert "nanoseconds" in " ".join(res.output.split())
    with pytest.raises(InputError, match="nanoseconds"):
        read_scans(logs["ns"])
    with pytest.raises(InputError, match="nanoseconds"):
        read_odometry_csv(tmp_path / "ns_odometry.csv")
    # the loop turns at 1/3 rad/s = 19.1 deg/s: read as rad/s, three turns a second
    with pytest.raises(InputError, match="degrees per second"):
        read_odometry_csv(tmp_path / "deg_odometry.csv")
    imu = np.genfromtxt(_imu_csv(tmp_path / "imu.csv", 1.0), delimiter=",", names=True)
    imu["time_s"] *= 1e9  # relative times in ns: steps of 2e7
    np.savetxt(tmp_path / "imu_ns.csv", imu, delimiter=",", comments="",
               header=",".join(imu.dtype.names or ()))  # fmt: skip
    with pytest.raises(InputError, match="nanoseconds"):
        read_imu_csv(tmp_path / "imu_ns.csv")
    # the same log in seconds reads as before
    assert read_scans(logs["loop"]).times[-1] == pytest.approx(20.7)
    t, _, w = read_odometry_csv(tmp_path / "loop_odometry.csv")
    assert t.size > 100 and np.allclose(w, 1 / 3)


def test_rostopic_echo_csv_of_laser_scans_is_read(tmp_path: Path, datasets_dir: Path) -> None:
    """`rostopic echo -p /scan > scans.csv` (header %time,field.header.seq,...,
    field.ranges0..,field.intensities0..; stamps in integer ns; inf = no return): refused
    before Dec 5 ("the header must start with time,..."), now the same scans as the NPZ,
    times in seconds from the header stamps, the frame from frame_id."""
    logs = _loop_log(datasets_dir, tmp_path)
    d = np.load(logs["loop"])
    r, t, n = d["ranges"], d["time"], d["ranges"].shape[1]
    amin, inc = float(d["angle_min"]), float(d["angle_increment"])
    head = ["%time", "field.header.seq", "field.header.stamp", "field.header.frame_id",
            "field.angle_min", "field.angle_max", "field.angle_increment",
            "field.time_increment", "field.scan_time", "field.range_min", "field.range_max",
            *[f"field.ranges{i}" for i in range(n)],
            *[f"field.intensities{i}" for i in range(n)]]  # fmt: skip
    stamp0 = 1_700_000_000 * 10**9
    lines = [",".join(head)]
    for k in range(t.size):
        ns = stamp0 + round(t[k] * 1e9)
        ranges = ["inf" if not np.isfinite(v) else repr(float(v)) for v in r[k]]
        lines.append(",".join([str(ns + 1234), str(k), str(ns), "base_laser", repr(amin),
                               repr(amin + (n - 1) * inc), repr(inc), "0.0", "0.1", "0.0",
                               "30.0", *ranges, *["100.0"] * n]))  # fmt: skip
    path = tmp_path / "rostopic.csv"
    path.write_text("\n".join(lines) + "\n")
    got, want = read_scans(path), read_scans(logs["loop"])
    assert got.ranges.shape == want.ranges.shape
    assert np.array_equal(np.isfinite(got.ranges), np.isfinite(want.ranges))
    ok = np.isfinite(want.ranges)
    assert np.array_equal(got.ranges[ok], want.ranges[ok])
    assert got.angle_min == want.angle_min and got.angle_increment == want.angle_increment
    # the stamps, exact to float64 at 1.7e9 s (2.4e-7 s)
    assert np.allclose(got.times - 1.7e9, want.times, atol=1e-6)
    assert got.frame == "base_laser"
