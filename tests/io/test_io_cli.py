"""``stemmap io topics`` and ``stemmap io convert-scans``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from _ros_bags import BagFactory
from stemmap.cli import app
from stemmap.io import read_scans, write_scans_npz
from stemmap.types import ScanBatch

runner = CliRunner()


def test_topics_and_convert_bag(tmp_path: Path) -> None:
    f = BagFactory(2)
    msgs = [("/scan", f.laserscan(1.0 + i, np.full(12, 2.5))) for i in range(4)]
    bag = f.write(tmp_path / "run", msgs, raw=[("/scan", "sensor_msgs/msg/LaserScan", b"xx")])
    res = runner.invoke(app, ["io", "topics", str(bag)])
    assert res.exit_code == 0 and "/scan" in res.stdout and "LaserScan" in res.stdout
    assert "5" in res.stdout  # 4 good + 1 corrupt message
    res = runner.invoke(app, ["io", "convert-scans", str(bag), "--out", str(tmp_path / "s.csv")])
    assert res.exit_code == 0, res.output
    assert "4 scans x 12 beams (1 skipped)" in res.stdout
    np.testing.assert_array_equal(read_scans(tmp_path / "s.csv").ranges, np.full((4, 12), 2.5))


def test_convert_npz_to_csv_round_trip(tmp_path: Path) -> None:
    b = ScanBatch(np.arange(12.0).reshape(3, 4), np.array([0.0, 0.1, 0.2]), -0.2, 0.1)
    write_scans_npz(tmp_path / "a.npz", b)
    res = runner.invoke(
        app, ["io", "convert-scans", str(tmp_path / "a.npz"), "-o", str(tmp_path / "a.csv"), "-q"]
    )
    assert res.exit_code == 0 and res.stdout == ""
    np.testing.assert_array_equal(read_scans(tmp_path / "a.csv").ranges, b.ranges)


def test_cli_errors_are_one_line(tmp_path: Path) -> None:
    res = runner.invoke(app, ["io", "topics", str(tmp_path / "none.bag")])
    text = " ".join(res.output.split())  # rich wraps long lines
    assert res.exit_code == 2 and "does not exist" in text and "Traceback" not in text
    (tmp_path / "a.npz").write_bytes(b"junk")
    res = runner.invoke(app, ["io", "convert-scans", str(tmp_path / "a.npz"), "-o", "x.txt"])
    assert res.exit_code == 2 and "must end in .npz, .csv or .bag" in " ".join(res.output.split())


def test_convert_to_bags_and_back(tmp_path: Path) -> None:
    b = ScanBatch(np.arange(12.0).reshape(3, 4) / 4, np.array([0.5, 0.6, 0.7]), -0.2, 0.1)
    write_scans_npz(tmp_path / "a.npz", b)
    for out, extra in (("a.bag", []), ("a_ros2", ["--storage", "mcap"])):
        args = ["io", "convert-scans", str(tmp_path / "a.npz"), "-o", str(tmp_path / out)]
        res = runner.invoke(app, [*args, "--out-topic", "/laser", *extra])
        assert res.exit_code == 0, res.output
        back = read_scans(tmp_path / out, topic="/laser")
        np.testing.assert_array_equal(back.ranges, b.ranges)  # quarter-metres: exact in float32
        np.testing.assert_allclose(back.times, b.times, atol=1e-9)
