"""`stemmap detect` / `stemmap map` over several drive logs (one Dask task per log)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._multilog import wants_logs
from stemmap.engine.logs import expand_logs, log_names
from stemmap.errors import InputError


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three small simulated logs (+ their side files) and a damaged one (truncated NPZ)."""
    d = tmp_path_factory.mktemp("logs")
    run = CliRunner()
    for seed in (1, 2, 3):
        args = ["sim", "scans", "--out", str(d / f"run{seed}.npz"), "--seed", str(seed)]
        res = run.invoke(app, [*args, "--n-scans", "150"])
        assert res.exit_code == 0, res.output
    (d / "run9.npz").write_bytes((d / "run3.npz").read_bytes()[:3000])
    (d / "run9_odometry.csv").write_bytes((d / "run3_odometry.csv").read_bytes())
    return d


def _summary(path: Path) -> dict[str, dict[str, str]]:
    with open(path, newline="") as fh:
        return {r["log"]: r for r in csv.DictReader(fh)}


def test_expand_logs(logs: Path, tmp_path: Path) -> None:
    found = expand_logs([logs])
    # the side files of `stemmap sim scans` (odometry, poses, trees, gnss, truth) are no logs
    assert [p.name for p in found] == ["run1.npz", "run2.npz", "run3.npz", "run9.npz"]
    assert expand_logs([str(logs / "run*.npz")]) == found
    lst = tmp_path / "logs.txt"
    lst.write_text(f"# two logs\n{logs / 'run2.npz'}\n\n{logs / 'run1.npz'}\n")
    assert [p.name for p in expand_logs([lst])] == ["run1.npz", "run2.npz"]
    # a ROS 2 bag folder is one log, given directly or inside a folder of logs
    bag = tmp_path / "fleet" / "drive_a"
    bag.mkdir(parents=True)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (bag / "drive_a_0.db3").write_bytes(b"")
    assert expand_logs([bag]) == [bag]
    assert expand_logs([bag.parent]) == [bag]
    assert not wants_logs([bag], None, None)
    assert wants_logs([bag.parent], None, None)
    assert not wants_logs([logs / "run1.npz"], None, None)
    assert wants_logs([logs / "run1.npz"], 2, None)
    assert wants_logs([lst], None, None)
    assert log_names([logs / "run1.npz", tmp_path / "run1.csv", bag]) == [
        "run1",
        "run1_2",
        "drive_a",
    ]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no"):
        expand_logs([tmp_path / "empty"])


def test_detect_many_logs(logs: Path, tmp_path: Path) -> None:
    run = CliRunner()
    out = tmp_path / "det"
    res = run.invoke(app, ["detect", str(logs), "--out", str(out), "--workers", "2"])
    assert res.exit_code == 1, res.output  # run9 is damaged; the others finish
    summary = _summary(out / "summary.csv")
    assert set(summary) == {"run1", "run2", "run3", "run9"}
    assert summary["run9"]["status"] == "failed"
    assert "run9.npz" in summary["run9"]["error"] and "cannot be read" in summary["run9"]["error"]
    assert "error:" in res.output and "1 of 4 logs failed" in res.output
    assert not (out / "run9").exists()
    assert (out / "summary.csv.run.json").is_file()
    for name in ("run1", "run2", "run3"):
        assert summary[name]["status"] == "done"
        single = tmp_path / f"{name}.csv"
        res1 = run.invoke(app, ["detect", str(logs / f"{name}.npz"), "--out", str(single)])
        assert res1.exit_code == 0, res1.output
        got = out / name / "observations.csv"
        assert got.read_bytes() == single.read_bytes()  # the single-log command's result
        assert (out / name / "observations.csv.run.json").is_file()
        n_rows = len(single.read_text().splitlines()) - 1
        assert int(summary[name]["n_observations"]) == n_rows > 0


@pytest.mark.slow
def test_map_many_logs(logs: Path, tmp_path: Path) -> None:
    run = CliRunner()
    out = tmp_path / "maps"
    lst = tmp_path / "list.txt"
    lst.write_text("\n".join(str(logs / f"run{i}.npz") for i in (1, 2, 9)) + "\n")
    args = ["map", str(lst), "--backend", "ekf", "--out", str(out), "--workers", "2"]
    res = run.invoke(app, args)
    assert res.exit_code == 1, res.output
    summary = _summary(out / "summary.csv")
    assert [summary[n]["status"] for n in ("run1", "run2", "run9")] == ["done", "done", "failed"]
    assert "run9.npz" in summary["run9"]["error"]
    single = tmp_path / "single"
    one = ["map", str(logs / "run2.npz"), "--backend", "ekf", "--out", str(single)]
    res1 = run.invoke(app, one)
    assert res1.exit_code == 0, res1.output
    for f in ("trees.csv", "trajectory.csv", "trees.geojson"):
        assert (out / "run2" / f).read_bytes() == (single / f).read_bytes(), f
    assert (out / "run1" / "run.json").is_file() and (out / "run1" / "metrics.json").is_file()
    n_trees = len((single / "trees.csv").read_text().splitlines()) - 1
    assert int(summary["run2"]["n_trees"]) == n_trees
    # the EKF has no false-tree removal: the column is empty, not 0
    assert summary["run2"]["backend"] == "ekf" and summary["run2"]["false_trees_removed"] == ""
    # one odometry file cannot serve several logs
    res2 = run.invoke(app, [*args, "--odometry", str(logs / "run1_odometry.csv")])
    assert res2.exit_code == 2 and "--odometry" in res2.output


def test_map_summary_false_trees(logs: Path, tmp_path: Path) -> None:
    """forestrix on raw scans runs Öhman's ray-cast false-tree removal: summary.csv carries
    its count and the other per-log metrics, equal to each log's own metrics.json."""
    import json

    out = tmp_path / "fx"
    args = ["map", str(logs / "run1.npz"), str(logs / "run2.npz"), "--backend", "forestrix"]
    res = CliRunner().invoke(app, [*args, "--out", str(out), "--workers", "1"])
    assert res.exit_code == 0, res.output
    summary = _summary(out / "summary.csv")
    assert set(summary) == {"run1", "run2"}
    for name, row in summary.items():
        m = json.loads((out / name / "metrics.json").read_text(encoding="utf-8"))
        assert m["false_trees"]["ran"] is True
        assert row["backend"] == "forestrix"
        assert int(row["false_trees_removed"]) == m["false_trees"]["removed"] >= 0
        assert (
            int(row["n_trees"]) == m["n_trees"] and int(row["duplicates_1m"]) == m["duplicates_1m"]
        )
        assert row["motion_source"] == "wheel"
        assert float(row["distance_m"]) == m["motion"]["distance_m"] > 0
        assert float(row["drift_estimate_percent"]) == m["motion"]["drift_estimate_percent"]
        frac = float(row["associated_fraction"])
        assert frac == m["uncertainty"]["associated_fraction"] and 0 < frac <= 1
