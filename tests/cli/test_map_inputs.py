"""`stemmap map` on files: scans from `stemmap sim scans`, detections from `stemmap detect`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.eval.matching import match_points
from stemmap.io.maps import read_trees_csv


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("simrun")
    res = CliRunner().invoke(
        app, ["sim", "scans", "--out", str(d / "run.npz"), "--seed", "2", "--n-scans", "900"]
    )
    assert res.exit_code == 0, res.output
    return d


def _in_world(trees_csv: Path, poses_csv: Path) -> np.ndarray:
    """Map frame = the first scan's pose (the simulator's sensor sits at the vehicle point)."""
    _, x0, y0, th0 = np.loadtxt(poses_csv, delimiter=",", skiprows=1, max_rows=1)
    c, s = math.cos(th0), math.sin(th0)
    xy = read_trees_csv(trees_csv).xy
    return xy @ np.array([[c, s], [-s, c]]) + [x0, y0]


@pytest.mark.slow
def test_map_scans_and_detections(sim_run: Path) -> None:
    run = CliRunner()
    truth = np.loadtxt(sim_run / "run_trees.csv", delimiter=",", skiprows=1)[:, 1:3]
    out1 = sim_run / "m_scans"
    res = run.invoke(app, ["map", str(sim_run / "run.npz"), "--backend", "ekf", "--out", str(out1)])
    assert res.exit_code == 0, res.output
    world = _in_world(out1 / "trees.csv", sim_run / "run_poses.csv")
    assert len(world) >= 5
    # mapped trees are stand trees (12 m of driving: odometry drift stays < 0.5 m); the
    # default scene has clutter (bushes, rocks, a wall) that may add a spurious landmark or two
    assert match_points(world, truth, gate=0.5).n_matched >= 0.8 * len(world)

    det = sim_run / "det.csv"
    assert run.invoke(app, ["detect", str(sim_run / "run.npz"), "--out", str(det)]).exit_code == 0
    out2 = sim_run / "m_det"
    args = ["map", str(det), "--backend", "ekf", "--out", str(out2)]
    res = run.invoke(app, [*args, "--odometry", str(sim_run / "run_odometry.csv")])
    assert res.exit_code == 0, res.output
    world2 = _in_world(out2 / "trees.csv", sim_run / "run_poses.csv")
    assert match_points(world2, world, gate=0.05).n_matched == len(world)  # same detections

    res = run.invoke(app, args)  # no odometry beside det.csv
    assert res.exit_code == 2 and "--odometry" in res.output


@pytest.mark.parametrize("name", ["missing.npz", "missing.csv"])
def test_map_missing_input_says_so(tmp_path: Path, name: str) -> None:
    # the user audit (docs/cli.md): a mistyped input was reported as "has no odometry"
    out = tmp_path / "m"
    res = CliRunner().invoke(app, ["map", str(tmp_path / name), "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "does not exist" in res.output and "odometry" not in res.output
    assert not out.exists()


@pytest.mark.parametrize("name", ["plot.laz", "frame.pcd"])
def test_map_point_cloud_points_to_stems(tmp_path: Path, name: str) -> None:
    # the user walk (Dec 4): a point cloud given to map was "has no odometry: pass --odometry"
    src = tmp_path / name
    src.write_bytes(b"not read")
    out = tmp_path / "m"
    res = CliRunner().invoke(app, ["map", str(src), "--out", str(out)])
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert "is a point cloud" in text and f"stemmap stems {name}" in text
    assert "odometry" not in text
    assert not out.exists()


def test_map_dataset_without_a_datasets_folder_names_the_option(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the user audit (docs/cli.md): run outside the project, the error said "pass the Victoria
    # Park folder" without saying how (--data)
    monkeypatch.delenv("STEMMAP_DATASETS", raising=False)
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["map", "--dataset", "victoria-park", "--out", "m"])
    assert res.exit_code == 2, res.output
    assert "--data FOLDER" in " ".join(res.output.split())


@pytest.mark.parametrize(("col", "value"), [("speed", 1e5), ("yaw_rate", -1e3)])
def test_map_odometry_row_beyond_any_vehicle_names_the_line(
    tmp_path: Path, col: str, value: float
) -> None:
    # the user walk (Dec 4): one odometry row of 1e5 m/s ended the map in a GTSAM
    # RuntimeError traceback (a k-d tree overflow with ekf / treedb at 1e300)
    from stemmap.cli._map_inputs import read_odometry_csv

    t = np.arange(0.0, 2.0, 0.1)
    speed, yaw = np.ones_like(t), np.zeros_like(t)
    (speed if col == "speed" else yaw)[7] = value
    p = tmp_path / "odo.csv"
    np.savetxt(p, np.c_[t, speed, yaw], delimiter=",", header="time_s,speed,yaw_rate", comments="")
    with pytest.raises(InputError, match=rf"line 9: {col} .* is beyond"):
        read_odometry_csv(p)
    speed[7], yaw[7] = 30.0, 3.0  # a fast machine turning hard is fine
    np.savetxt(p, np.c_[t, speed, yaw], delimiter=",", header="time_s,speed,yaw_rate", comments="")
    assert read_odometry_csv(p)[1][7] == 30.0
