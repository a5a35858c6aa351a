"""``stemmap detect --imu-topic``: a tilted scanner's bag with its AHRS (Zheng 2012 §2, eq. 1)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from _ros_bags import BagFactory
from stemmap.cli import app
from stemmap.harvester.simulate import zheng2012_scanner
from stemmap.sim.forest import Stand
from stemmap.sim.tilted import simulate_tilted_scan
from stemmap.types import Pose2

runner = CliRunner()
ROLL, PITCH = math.radians(10.0), math.radians(15.0)
_ANG = np.radians(np.linspace(-40, 40, 8))
_R = np.linspace(2.5, 6.0, 8)
XY = np.column_stack((_R * np.cos(_ANG), _R * np.sin(_ANG)))
D = np.linspace(0.18, 0.38, 8)


def _quat(roll: float, pitch: float) -> tuple[float, float, float, float]:
    cr, sr, cp, sp = (
        math.cos(roll / 2),
        math.sin(roll / 2),
        math.cos(pitch / 2),
        math.sin(pitch / 2),
    )
    return (sr * cp, cr * sp, -sr * sp, cr * cp)  # (x, y, z, w) of Rz(0) Ry(pitch) Rx(roll)


def _bag(tmp_path: Path, imu_from: float = 0.0) -> Path:
    bags = BagFactory(1)
    m = zheng2012_scanner(range_noise=0.01)
    stand = Stand(XY, D)
    msgs = []
    for k in np.arange(50) * 0.02 + imu_from:  # 50 Hz AHRS
        msgs.append(("/imu", bags.imu(float(k) + 1.0, _quat(ROLL, PITCH), (0.0, 0.0, 9.81))))
    for i in range(10):  # 10 Hz scanner
        s = simulate_tilted_scan(stand, Pose2(0, 0, 0), ROLL, PITCH, m, rng=i)
        r = np.where(np.isfinite(s.ranges), s.ranges, 0.0)  # 0 = no return (below range_min)
        msgs.append(("/scan", bags.laserscan(1.0 + 0.1 * i, r, s.angle_min, s.angle_increment,
                                             s.range_min, s.range_max)))  # fmt: skip
    msgs.sort(key=lambda tm: tm[1].header.stamp.sec + 1e-9 * tm[1].header.stamp.nanosec)
    return bags.write(tmp_path / "crane", msgs)


def _errors(path: Path) -> np.ndarray:
    rows = list(csv.DictReader(path.open(encoding="utf-8")))
    out = []
    for r in rows:
        c = np.array([float(r["x"]), float(r["y"])])
        k = int(np.argmin(np.hypot(*(XY - c).T)))
        if np.hypot(*(XY[k] - c)) < 0.3:
            out.append((float(r["diameter"]) - D[k], np.hypot(*c) - np.hypot(*XY[k])))
    return np.asarray(out)


def test_detect_with_imu_topic_undoes_the_tilt(tmp_path: Path) -> None:
    bag = _bag(tmp_path)
    a, b = tmp_path / "imu.csv", tmp_path / "raw.csv"
    res = runner.invoke(app, ["detect", str(bag), "--out", str(a), "--topic", "/scan",
                              "--imu-topic", "/imu", "-q"])  # fmt: skip
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["detect", str(bag), "--out", str(b), "--topic", "/scan", "-q"])
    assert res.exit_code == 0, res.output
    with_imu, raw = _errors(a), _errors(b)
    assert len(with_imu) >= 60 and len(raw) >= 60
    # as tests/scan/test_tilt_imu.py: level-scan accuracy with the AHRS, biased without it
    assert abs(with_imu[:, 1].mean()) < 0.01
    assert raw[:, 1].mean() > 0.03
    assert raw[:, 0].mean() - with_imu[:, 0].mean() > 0.003


def test_imu_topic_errors(tmp_path: Path) -> None:
    bag = _bag(tmp_path, imu_from=5.0)  # AHRS starts 4 s after the last scan
    res = runner.invoke(app, ["detect", str(bag), "--out", str(tmp_path / "o.csv"),
                              "--topic", "/scan", "--imu-topic", "/imu"])  # fmt: skip
    assert res.exit_code != 0 and "covers t =" in res.output
    npz = tmp_path / "s.npz"
    np.savez(npz, ranges=np.ones((2, 10)), times=np.arange(2.0), angle_min=0.0,
             angle_increment=0.01)  # fmt: skip
    res = runner.invoke(app, ["detect", str(npz), "--out", str(tmp_path / "o.csv"),
                              "--imu-topic", "/imu"])  # fmt: skip
    assert res.exit_code != 0 and "not a bag" in res.output
