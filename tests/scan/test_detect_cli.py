import csv
import json
import math

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import cast_rays

runner = CliRunner()


def _ranges(n_scans):
    a = np.radians(np.arange(-90.0, 90.0 + 1e-9, 0.5))
    stand = Stand(np.array([[3.0, 0.0], [2.0, 2.0]]), np.array([0.3, 0.2]))
    r, _ = cast_rays(np.zeros(2), a, stand, 30.0)
    rng = np.random.default_rng(0)
    return np.tile(r, (n_scans, 1)) + rng.normal(0, 0.005, (n_scans, a.size)), a


def test_detect_writes_rows_and_reports_a_corrupt_frame(tmp_path):
    ranges, a = _ranges(4)
    times = np.array([0.0, np.nan, 0.2, 0.3])  # frame 1 is damaged (no valid time stamp)
    src = tmp_path / "scans.npz"
    np.savez(
        src,
        ranges=ranges,
        time=times,
        angle_min=a[0],
        angle_increment=math.radians(0.5),
        range_min=0.05,
        range_max=30.0,
    )
    out = tmp_path / "stems.csv"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "--fit", "kasa"])
    assert res.exit_code == 0, res.output
    assert "skipped frame 1" in res.output
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    required = {"scan_index", "time_s", "x", "y", "diameter", "radius_std", "n_points"}
    assert required <= set(rows[0])
    # two trunks in each of the three good frames; scan_index is the position in the file
    assert sorted({int(r["scan_index"]) for r in rows}) == [0, 2, 3]
    assert len(rows) == 6
    d = sorted(float(r["diameter"]) for r in rows if int(r["scan_index"]) == 0)
    # 5 mm noise, >= 10 returns per trunk: diameters within 2 cm
    assert abs(d[0] - 0.2) < 0.02 and abs(d[1] - 0.3) < 0.02


def test_detect_bad_inputs_exit_2(tmp_path):
    res = runner.invoke(app, ["detect", str(tmp_path / "missing.npz"), "--out", "x.csv"])
    assert res.exit_code == 2 and "does not exist" in " ".join(res.output.split())
    trunc = tmp_path / "trunc.npz"
    ranges, a = _ranges(2)
    np.savez(trunc, ranges=ranges, time=np.zeros(2), angle_min=a[0], angle_increment=0.01)
    trunc.write_bytes(trunc.read_bytes()[:100])
    res = runner.invoke(app, ["detect", str(trunc), "--out", str(tmp_path / "o.csv")])
    assert res.exit_code == 2 and "error" in res.output
    assert not (tmp_path / "o.csv").exists()
    ok = tmp_path / "ok.npz"
    np.savez(ok, ranges=ranges, time=np.zeros(2), angle_min=a[0], angle_increment=0.01)
    res = runner.invoke(app, ["detect", str(ok), "--out", "x.csv", "--preset", "ohman2007"])
    assert res.exit_code == 2 and "Öhman" in " ".join(res.output.split())


def _write_ros1_bag(path, topics, ranges, angle_min, inc, corrupt_topic=None):
    """A ROS1 bag with sensor_msgs/LaserScan on every topic (plus one damaged message)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    with Writer(path) as w:
        conns = {t: w.add_connection(t, "sensor_msgs/msg/LaserScan", typestore=ts) for t in topics}
        for k, row in enumerate(ranges):
            stamp = T["builtin_interfaces/msg/Time"](sec=k, nanosec=0)
            msg = T["sensor_msgs/msg/LaserScan"](
                header=T["std_msgs/msg/Header"](seq=k, stamp=stamp, frame_id="laser"),
                angle_min=angle_min,
                angle_max=angle_min + inc * (len(row) - 1),
                angle_increment=inc,
                time_increment=0.0,
                scan_time=0.1,
                range_min=0.05,
                range_max=30.0,
                ranges=np.where(np.isfinite(row), row, np.inf).astype(np.float32),
                intensities=np.zeros(0, np.float32),
            )
            data = bytes(ts.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))
            for t in topics:
                w.write(conns[t], (k + 1) * 1_000_000_000, data)
        if corrupt_topic is not None:
            w.write(conns[corrupt_topic], (len(ranges) + 1) * 1_000_000_000, b"\x01\x02\x03")
    return path


def test_detect_reads_a_ros1_bag_topic(tmp_path):
    ranges, a = _ranges(3)
    bag = _write_ros1_bag(
        tmp_path / "run.bag",
        ["/scan", "/scan_rear"],
        ranges,
        float(a[0]),
        math.radians(0.5),
        corrupt_topic="/scan",
    )
    out = tmp_path / "bag.csv"
    res = runner.invoke(
        app, ["detect", str(bag), "--out", str(out), "--topic", "/scan", "--fit", "kasa"]
    )
    assert res.exit_code == 0, res.output
    assert "skipped frame 3" in res.output  # the damaged 4th message
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert sorted({int(r["scan_index"]) for r in rows}) == [0, 1, 2] and len(rows) == 6
    # two LaserScan topics and none chosen: the reader's error names them
    res = runner.invoke(app, ["detect", str(bag), "--out", str(tmp_path / "x.csv")])
    assert res.exit_code == 2 and "/scan_rear" in " ".join(res.output.split())


#: A Unix time in 2023 (s): scan times as ROS bags and GNSS-stamped logs give them.
_EPOCH = 1_700_000_000.123


def test_detect_rejected_lists_dropped_candidates_with_their_test(tmp_path):
    ranges, a = _ranges(3)
    # a wall x = 5 m seen at bearings 20-40 deg: a straight segment the stemmap preset drops
    wall = (a > math.radians(20.0)) & (a < math.radians(40.0))
    ranges[:, wall] = 5.0 / np.cos(a[wall])
    src = tmp_path / "scans.npz"
    np.savez(
        src,
        ranges=ranges,
        time=_EPOCH + np.array([0.0, 0.1, 0.2]),
        angle_min=a[0],
        angle_increment=math.radians(0.5),
        range_min=0.05,
        range_max=30.0,
    )
    out, rej = tmp_path / "stems.csv", tmp_path / "rejected.csv"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "--rejected", str(rej)])
    assert res.exit_code == 0, res.output
    with rej.open() as fh:
        rows = list(csv.DictReader(fh))
    walls = [r for r in rows if abs(float(r["bearing_deg"]) - 30.0) < 5.0]
    # one wall candidate per scan, dropped as flat (sagitta <= 0 or a line within the noise)
    # before any fit
    assert sorted(int(r["scan_index"]) for r in walls) == [0, 1, 2]
    # epoch times read back exactly (they were printed to 6 digits: 1.70000e+09 for all three)
    assert sorted(float(r["time"]) for r in walls) == list(_EPOCH + np.array([0.0, 0.1, 0.2]))
    assert {r["reason"] for r in walls} <= {"depth", "straight"}
    assert all(r["radius"] == "nan" for r in walls)
    # dropped outright: the reason is the test, no piece was kept
    assert all(r["failed_test"] == r["reason"] and r["pieces_accepted"] == "0" for r in walls)
    with out.open() as fh:
        stems = list(csv.DictReader(fh))
    # the two trunks, still detected in every scan. (The wall's first returns, cut from it by
    # the splitting radius median filter, fit a 25 cm circle with an RMS of 2.1 sigma: the 3 %
    # bark-roughness allowance the real slices chose (issue 11) lets that piece through -- a
    # false alarm the leave-one-dataset-out objective does not count; scan-detection-history.md.)
    for x, y in ((3.0, 0.0), (2.0, 2.0)):
        near = [r for r in stems if math.hypot(float(r["x"]) - x, float(r["y"]) - y) < 0.3]
        assert sorted(int(r["scan_index"]) for r in near) == [0, 1, 2]


def test_detect_rejected_names_a_split_parent_and_its_pieces(tmp_path):
    # a 30 cm trunk at 3 m merged with a branch leaving its side towards the sensor: the
    # candidate fails as not convex, its corner split's trunk piece is detected
    from tests.scan.test_gaps_refit import _scan_with_branch

    b = _scan_with_branch((3.0, 0.0, 0.15), (3.0, 0.149), (2.7, 0.4))
    src = tmp_path / "scans.npz"
    np.savez(src, ranges=np.repeat(b.ranges, 2, axis=0), time=np.array([0.0, 0.1]),
             angle_min=b.angle_min, angle_increment=b.angle_increment, range_max=30.0)  # fmt: skip
    out, rej = tmp_path / "stems.csv", tmp_path / "rejected.csv"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "--rejected", str(rej)])
    assert res.exit_code == 0, res.output
    with out.open() as fh:
        stems = list(csv.DictReader(fh))
    assert sorted(int(r["scan_index"]) for r in stems) == [0, 1]
    with rej.open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[:13] == ["scan_index", "time", "reason", "n_points", "bearing_deg",
                                  "range", "width", "partial", "x", "y", "radius", "rms",
                                  "sigma"]  # fmt: skip
    assert [(r["scan_index"], r["reason"], r["failed_test"]) for r in rows] == [
        ("0", "split", "depth"),
        ("1", "split", "depth"),
    ]
    assert all(int(r["pieces_accepted"]) >= 1 for r in rows)
    assert "2 rejected candidates (2 of them re-fitted as pieces that were kept)" in res.output


def test_detect_edge_hit_narrows_the_averaging_edge_model(tmp_path):
    # --edge-hit 0 0: a scanner that returns when any part of its footprint hits puts the
    # tangent h = footprint / (2 step) beams nearer the edge return than the preset's half
    # footprint does, so every diameter shrinks (by ~0.25 deg x range at most); a bad
    # interval is a usage error
    ranges, a = _ranges(3)
    src = tmp_path / "scans.npz"
    np.savez(
        src,
        ranges=ranges,
        time=np.arange(3.0),
        angle_min=a[0],
        angle_increment=math.radians(0.5),
        range_min=0.05,
        range_max=30.0,
    )
    diam = {}
    for name, extra in (("half", []), ("any", ["--edge-hit", "0", "0"])):
        out = tmp_path / f"{name}.csv"
        res = runner.invoke(app, ["detect", str(src), "--out", str(out), *extra])
        assert res.exit_code == 0, res.output
        with out.open() as fh:
            diam[name] = sorted(float(r["diameter"]) for r in csv.DictReader(fh))
    assert len(diam["half"]) == len(diam["any"]) == 6
    shrink = np.subtract(diam["half"], diam["any"])
    assert np.all(shrink > 0) and np.all(shrink < math.radians(0.25) * 3.3)
    res = runner.invoke(
        app, ["detect", str(src), "--out", str(tmp_path / "x.csv"), "--edge-hit", "0.6", "0.5"]
    )
    assert res.exit_code == 2


def test_detect_edge_hit_window_reads_an_any_hit_scanners_slivers(tmp_path):
    # --edge-hit-window (edge_hit_window, Dec 5): on a scanner that returns when any sub-ray of
    # its footprint hits, an edge beam that grazes the trunk reports the sliver's own (nearer)
    # range; assuming the threshold unknown in [0, 0.5] without the window the fit reads it as
    # a wider trunk. Noise-free averaging scans (0.25 deg steps and footprint, 25 sub-beams,
    # one needed) of 40 and 60 cm trunks at 10 m, 30 beam phases: the window must take the
    # mean DBH error nearer zero by at least 0.3 cm (measured on the real-geometry
    # benchmark's discs at 0.25 deg: +1.48 -> +0.60 cm and +1.15 -> +0.20 cm,
    # docs/algorithms/scan-detection.md, "The averaging edge bias against textbook Kasa"),
    # and the run record names the option
    from stemmap.io.scans import write_scans_npz
    from stemmap.sim.scanner import ScannerModel, simulate_scans

    stand = Stand(np.array([[10.0, -1.5], [10.0, 1.5]]), np.array([0.40, 0.60]))
    model = ScannerModel(
        angle_increment=math.radians(0.25),
        range_noise=0.0,
        range_max=30.0,
        beam_divergence=math.radians(0.25),
        sub_beams=25,
        min_hit_fraction=0.01,
    )
    rng = np.random.default_rng(3)
    n = 30
    poses = np.column_stack(
        [np.zeros(n), rng.uniform(-0.05, 0.05, n), rng.uniform(-0.005, 0.005, n)]
    )
    scans, _, _ = simulate_scans(stand, poses, model, rng=1)
    src = tmp_path / "scans.npz"
    write_scans_npz(src, scans)
    err = {}
    for name, extra in (("off", []), ("on", ["--edge-hit-window"])):
        out = tmp_path / f"{name}.csv"
        args = ["detect", str(src), "--out", str(out), "-q", "--edge-hit", "0", "0.5", *extra]
        res = runner.invoke(app, args)
        assert res.exit_code == 0, res.output
        with out.open() as fh:
            d = np.array([float(r["diameter"]) for r in csv.DictReader(fh)])
        assert d.size == 2 * n  # both trunks in every scan
        truth = np.where(d > 0.5, 0.60, 0.40)
        err[name] = 100.0 * float(np.mean(d - truth))
    assert abs(err["on"]) < abs(err["off"]) - 0.3
    doc = json.loads((tmp_path / "on.csv.run.json").read_text())
    assert doc["parameters"]["edge_hit_window"] is True
