import csv

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()


def test_sim_scans_writes_scans_and_truth(tmp_path):
    out = tmp_path / "run.npz"
    res = runner.invoke(app, ["sim", "scans", "--out", str(out), "--seed", "3", "--n-scans", "60"])
    assert res.exit_code == 0, res.output
    with np.load(out) as z:
        ranges = z["ranges"]
        assert ranges.shape == (60, 361)
        assert z["time"].shape == (60,)
        assert float(z["angle_increment"]) == np.radians(0.5)
        assert np.isfinite(ranges).any() and np.isinf(ranges).any()
    rows = list(csv.DictReader((tmp_path / "run_trees.csv").open()))
    assert list(rows[0]) == ["id", "x", "y", "diameter"] and len(rows) > 10
    poses = np.loadtxt(tmp_path / "run_poses.csv", delimiter=",", skiprows=1)
    assert poses.shape == (60, 4)
    with np.load(tmp_path / "run_truth.npz") as z:
        hit = z["hit_ids"]
        assert hit.shape == (60, 361)
        # ground truth agrees with the ranges: a beam has a return iff it hit something
        np.testing.assert_array_equal(np.isfinite(ranges), hit != -1)
        assert hit.max() < len(rows)
    odo = np.loadtxt(tmp_path / "run_odometry.csv", delimiter=",", skiprows=1)
    assert odo.shape[1] == 3 and odo[-1, 0] >= poses[-1, 0]  # odometry covers every scan
    gnss = np.loadtxt(tmp_path / "run_gnss.csv", delimiter=",", skiprows=1, ndmin=2)
    assert gnss.shape[1] == 4
    # the io area's reader reads what we wrote
    from stemmap.io.scans import read_scans

    batch = read_scans(out)
    assert len(batch) == 60
    np.testing.assert_array_equal(np.isfinite(batch.ranges), np.isfinite(ranges))


def test_sim_scans_same_seed_same_file(tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    for p in (a, b):
        res = runner.invoke(
            app,
            [
                "sim",
                "scans",
                "--out",
                str(p),
                "--seed",
                "5",
                "--n-scans",
                "20",
                "-q",
                "--preset",
                "rplidar",
                "--layout",
                "rows",
                "--path",
                "lawnmower",
            ],
        )
        assert res.exit_code == 0, res.output
    with np.load(a) as za, np.load(b) as zb:
        np.testing.assert_array_equal(za["ranges"], zb["ranges"])
        assert za["ranges"].shape == (20, 360)


def test_sim_scans_bad_preset_is_a_clean_error(tmp_path):
    res = runner.invoke(app, ["sim", "scans", "--out", str(tmp_path / "x.npz"), "--preset", "nope"])
    assert res.exit_code == 2
    assert not (tmp_path / "x.npz").exists()


def test_sim_score_perfect_and_degraded_detections(tmp_path):
    import json

    from stemmap.eval import detectable_trees
    from stemmap.io.maps import write_observations_csv
    from stemmap.types import StemObservations

    run = tmp_path / "run.npz"
    res = runner.invoke(
        app, ["sim", "scans", "--out", str(run), "--seed", "2", "--n-scans", "40", "-q"]
    )
    assert res.exit_code == 0, res.output
    trees = np.loadtxt(tmp_path / "run_trees.csv", delimiter=",", skiprows=1)
    poses = np.loadtxt(tmp_path / "run_poses.csv", delimiter=",", skiprows=1)
    with np.load(tmp_path / "run_truth.npz") as z:
        hit = z["hit_ids"].astype(np.int64)
    ok = detectable_trees(hit, trees.shape[0], min_returns=5)
    rows = []
    for k in range(poses.shape[0]):
        c, s = np.cos(poses[k, 3]), np.sin(poses[k, 3])
        for i in np.flatnonzero(ok[k]):
            dx, dy = trees[i, 1] - poses[k, 1], trees[i, 2] - poses[k, 2]
            rows.append((k, c * dx + s * dy, -s * dx + c * dy, trees[i, 3] / 2))
    a = np.array(rows)
    n = a.shape[0]
    obs = StemObservations(
        centers=a[:, 1:3],
        radii=a[:, 3],
        covs=np.zeros((n, 3, 3)),
        n_points=np.full(n, 5),
        arc_deg=np.zeros(n),
        widths=np.zeros(n),
        quality=np.ones(n),
        index=a[:, 0],
        times=poses[a[:, 0].astype(int), 0],
    )
    det = tmp_path / "stems.csv"
    write_observations_csv(det, obs)
    out_json = tmp_path / "m.json"
    res = runner.invoke(
        app,
        [
            "sim",
            "score",
            str(det),
            "--run",
            str(run),
            "--json",
            str(out_json),
            "--max-range",
            "1000",
            "--min-diameter",
            "0",
        ],
    )
    assert res.exit_code == 0, res.output
    m = json.loads(out_json.read_text())
    # the oracle reports exactly the detectable trees at their true positions (CSV rounding
    # of the written coordinates stays far below a millimetre)
    assert m["fa"] == 0 and m["fr"] == 0 and m["ta"] == n
    assert m["center_rmse"] < 1e-3
    # a mismatched run is refused with a clean error
    res = runner.invoke(app, ["sim", "score", str(det), "--run", str(tmp_path / "nope.npz")])
    assert res.exit_code == 2
