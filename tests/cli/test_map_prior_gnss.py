"""`stemmap map --prior-map DIR --gnss FILE`: the prior map's frame rules. A map made in the
fixes' frame (with --gnss, same --crs) is continued with the fixes fused and the relocalised
start kept; any other map is one clear error line before any mapping."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.maps import write_trees_csv
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.types import StemMap, Tree

CRS = "EPSG:32633"
ORIGIN = np.array([500_000.0, 6_250_000.0])  # UTM 33N: the fixes are far from the sim's frame


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated log (90 s, 1 Hz fixes) with its fixes moved to UTM 33N coordinates."""
    d = tmp_path_factory.mktemp("priorgnss")
    args = ["sim", "scans", "--out", str(d / "run.npz"), "--seed", "3", "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    g = np.loadtxt(d / "run_gnss.csv", delimiter=",", skiprows=1, ndmin=2)
    g[:, 1:3] += ORIGIN
    np.savetxt(d / "utm.csv", g, delimiter=",", header="time_s,x,y,sigma", comments="")
    return d


def _map(d: Path, out: str, *extra: str) -> Any:
    args = ["map", str(d / "run.npz"), "--out", str(d / out), "--no-progress", *extra]
    return CliRunner().invoke(app, args)


def _error(res: Any) -> str:
    assert res.exit_code != 0, res.output
    err = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1, res.output
    return err[0]


def _hand_map(d: Path, name: str, **files: dict[str, Any]) -> Path:
    """A map folder with a trees.csv near the fixes and the given JSON files."""
    f = d / name
    f.mkdir()
    trees = tuple(
        Tree(id=i, x=float(ORIGIN[0] + 5 * i), y=float(ORIGIN[1]), diameter=0.3) for i in range(6)
    )
    write_trees_csv(f / "trees.csv", StemMap(trees))
    for fname, doc in files.items():
        (f / f"{fname}.json").write_text(json.dumps(doc))
    return f


def test_prior_map_not_in_the_gnss_frame_is_refused(sim_log: Path) -> None:
    """Refused before mapping, naming the map and what it records: no record at all, made
    without --gnss (metrics.json), another CRS (metrics.json), an old map's run.json."""
    gnss = ["--gnss", str(sim_log / "utm.csv")]
    bare = _hand_map(sim_log, "bare")
    err = _error(_map(sim_log, "o1", *gnss, "--prior-map", str(bare)))
    assert "records no frame" in err and str(bare) in err
    local = _hand_map(sim_log, "local", metrics={"frames": {"gnss_frame": False, "crs": None}})
    err = _error(_map(sim_log, "o2", *gnss, "--prior-map", str(local)))
    assert "made without --gnss" in err and "metrics.json" in err
    utm = _hand_map(sim_log, "utm", metrics={"frames": {"gnss_frame": True, "crs": CRS}})
    err = _error(_map(sim_log, "o3", *gnss, "--prior-map", str(utm)))
    assert f"CRS {CRS}" in err and f"give --crs {CRS}" in err
    old = _hand_map(sim_log, "old", run={"parameters": {"gnss": "fixes.csv", "crs": None}})
    err = _error(_map(sim_log, "o4", *gnss, "--crs", CRS, "--prior-map", str(old)))
    assert "no CRS" in err and "run.json" in err and "give no --crs" in err
    for out in ("o1", "o2", "o3", "o4"):
        assert not (sim_log / out).exists()  # nothing written


@pytest.mark.slow
def test_prior_map_in_the_gnss_frame_keeps_the_relocalised_start(sim_log: Path) -> None:
    """Session 1 with --gnss --crs: metrics.json records the GNSS frame. Session 2 on it with
    the same fixes: mapped in that frame from the relocalised start (the fixes agree with it;
    on the old code the start was overwritten and iSAM2 stopped with an indeterminate
    system). Session 2 without --gnss still records the GNSS frame (the map's frame rules);
    a map made without --gnss is refused."""
    gnss = ["--gnss", str(sim_log / "utm.csv"), "--crs", CRS]
    res = _map(sim_log, "s1", *gnss)
    assert res.exit_code == 0, res.output
    fr = json.loads((sim_log / "s1" / "metrics.json").read_text())["frames"]
    assert fr["gnss_frame"] is True and fr["crs"] == CRS

    res = _map(sim_log, "s2", *gnss, "--prior-map", str(sim_log / "s1"))
    assert res.exit_code == 0, res.output
    m = json.loads((sim_log / "s2" / "metrics.json").read_text())
    assert m["frames"]["gnss_frame"] is True and m["frames"]["crs"] == CRS
    rl = m["relocalisation"]
    assert rl["ok"] and rl["gnss_start_offset_m"] < 3.0 and abs(rl["gnss_start_heading_deg"]) < 10
    p1 = read_trajectory_csv(sim_log / "s1" / "trajectory.csv").poses
    p2 = read_trajectory_csv(sim_log / "s2" / "trajectory.csv").poses
    assert np.hypot(*(p2[0, :2] - p1[0, :2])) < 1.0  # the same start, in the fixes' frame
    assert np.hypot(*(p2[0, :2] - np.asarray(rl["pose"][:2]))) < 1.0  # the relocalised one
    assert m["backend_stats"]["gnss_fixes_fused"] > 30

    res = _map(sim_log, "s3", "--crs", CRS, "--prior-map", str(sim_log / "s1"))
    assert res.exit_code == 0, res.output
    assert json.loads((sim_log / "s3" / "metrics.json").read_text())["frames"]["gnss_frame"]

    res = _map(sim_log, "s0")  # no --gnss: a map in the odometry frame
    assert res.exit_code == 0, res.output
    err = _error(_map(sim_log, "s4", *gnss, "--prior-map", str(sim_log / "s0")))
    assert "made without --gnss" in err
