"""``stemmap demo``: the main job runs end to end with no input and its numbers make sense."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.maps import read_trees_csv, read_trees_geojson

FILES = (
    "detections.csv",
    "trees.csv",
    "trees.geojson",
    "trajectory.csv",
    "truth_trees.csv",
    "metrics.json",
    "demo.png",
)


def test_demo_writes_every_product_and_scores_well(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    res = CliRunner().invoke(app, ["demo", "--out", str(out), "--no-progress"])
    assert res.exit_code == 0, res.output
    for name in FILES:
        assert (out / name).stat().st_size > 0, name
    assert "detection.precision" in res.output  # the summary names each number's metrics key
    assert (out / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    m = json.loads((out / "metrics.json").read_text())
    det, mp, slam = m["detection"], m["map"], m["slam"]
    # per-scan detection on a SICK-like scanner: the detection benchmark measures 0.95-0.99;
    # 0.9 leaves room for this smaller, different stand
    assert det["precision"] >= 0.9 and det["recall"] >= 0.9
    assert abs(det["diameter_bias"]) < 0.01  # metres: |bias| < 1 cm
    # every tree the drive showed the laser (>= 5 returns in >= 3 scans) is in the map, and
    # mapped trees are real trees within the 1 m gate
    assert mp["recall_of_seen"] >= 0.9 and mp["precision"] >= 0.9
    assert mp["position_rmse"] < 0.25
    # the loop-closure target: at least 3x smaller than dead reckoning
    assert slam["loop_closure_error_m"] * 3 < slam["dead_reckoning_loop_closure_error_m"]
    # evo's RPE vs the true poses per 10 m (measured 0.019 m / 0.11 deg on the default demo;
    # the bounds only catch a broken wiring: a lost loop gives metres / tens of degrees)
    assert slam["rpe_n"] >= 3 and slam["rpe_delta_unit"] == "m"
    assert 0 <= slam["rpe_trans_rmse_m"] < 1 and 0 <= slam["rpe_rot_rmse_deg"] < 5

    # the files agree with the metrics and with each other
    trees = read_trees_csv(out / "trees.csv")
    assert len(trees) == mp["n_map"]
    assert len(read_trees_geojson(out / "trees.geojson")) == len(trees)
    with (out / "detections.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == det["n_detections"]
    assert {"scan_index", "time_s", "x", "y", "diameter", "radius_std", "n_points"} <= set(rows[0])
    truth = np.loadtxt(out / "truth_trees.csv", delimiter=",", skiprows=1)
    assert truth.shape == (m["n_trees_in_stand"], 4)


def test_demo_bad_option_is_a_clear_error(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--n-trees", "5000"])
    assert res.exit_code == 2
    assert "could place only" in res.output
    assert not (tmp_path / "d" / "metrics.json").exists()
