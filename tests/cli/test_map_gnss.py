"""`stemmap map --gnss` writes both estimates: trajectory.csv (the tree-consistent path) and the
GNSS-frame track (trajectory_gnss.csv / .tum, its GeoJSON with --crs, map.gpkg layers)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.trajectory import (
    TRAJECTORY_COV_COLUMNS,
    TRAJECTORY_CSV_COLUMNS,
    read_trajectory_csv,
    read_trajectory_csv_with_covariance,
    read_trajectory_tum,
)

CRS = "EPSG:32633"
#: a UTM 33N origin (m) the simulated world frame is shifted to, so lon/lat are on Earth
ORIGIN = np.array([500_000.0, 6_250_000.0])


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated log (90 s, 1 Hz GNSS with a Gauss-Markov error) with its fixes moved into
    UTM 33N coordinates, and the same fixes cut to 10 (too few for the offset model)."""
    d = tmp_path_factory.mktemp("gnsslog")
    args = ["sim", "scans", "--out", str(d / "run.npz"), "--seed", "3", "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    g = np.loadtxt(d / "run_gnss.csv", delimiter=",", skiprows=1, ndmin=2)
    g[:, 1:3] += ORIGIN
    head = "time_s,x,y,sigma"
    np.savetxt(d / "utm.csv", g, delimiter=",", header=head, comments="", fmt="%.17g")
    np.savetxt(d / "few.csv", g[:10], delimiter=",", header=head, comments="", fmt="%.17g")
    return d


def _map(d: Path, out: str, *extra: str) -> Path:
    args = ["map", str(d / "run.npz"), "--out", str(d / out), "--no-progress", *extra]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return d / out


def _header(p: Path) -> list[str]:
    with open(p, newline="") as fh:
        return next(csv.reader(fh))


def test_gnss_writes_the_track_csv_geojson_and_gpkg_layers(sim_log: Path) -> None:
    """CSV columns (poses + covariance: position block std² I, heading the path's), the track =
    path + a smooth offset with the model recorded in metrics.json, the GeoPackage layers in
    the given CRS read back through GDAL with the same coordinates, and the GeoJSON in WGS84
    lon/lat that projects back to the CSV's x, y."""
    from pyogrio import list_layers, read_info
    from pyogrio.raw import read as ogr_read
    from pyproj import Transformer

    out = _map(sim_log, "m", "--gnss", str(sim_log / "utm.csv"), "--crs", CRS, "--gpkg")
    path = read_trajectory_csv(out / "trajectory.csv")
    assert _header(out / "trajectory_gnss.csv") == [
        *TRAJECTORY_CSV_COLUMNS,
        *TRAJECTORY_COV_COLUMNS,
    ]
    track, covs = read_trajectory_csv_with_covariance(out / "trajectory_gnss.csv")
    assert covs is not None
    np.testing.assert_array_equal(track.times, path.times)
    np.testing.assert_array_equal(track.poses[:, 2], path.poses[:, 2])
    shift = track.xy - path.xy
    assert 0.05 < float(np.sqrt(np.mean(shift**2))) < 3.0  # an offset, not a copy or a jump
    assert float(np.abs(np.diff(shift, axis=0)).max()) < 0.5  # continuous at 75 Hz poses
    assert (covs[:, 0, 0] > 0).all() and np.allclose(covs[:, 0, 0], covs[:, 1, 1])
    np.testing.assert_array_equal(covs[:, 0, 1], 0.0)
    _, path_covs = read_trajectory_csv_with_covariance(out / "trajectory.csv")
    assert path_covs is not None
    np.testing.assert_allclose(covs[:, 2, 2], path_covs[:, 2, 2])
    gt = json.loads((out / "metrics.json").read_text())["gnss_track"]
    assert gt["written"] is True and gt["model"]["time_constant_s"] > 0
    assert gt["model"]["n_fixes"] > 30 and "smoothed" in gt["estimate"]

    layers = {name for name, _ in list_layers(out / "map.gpkg")}
    assert {"trajectory", "poses", "trajectory_gnss", "poses_gnss"} <= layers
    info = read_info(out / "map.gpkg", layer="poses_gnss")
    assert info["crs"] == CRS and set(info["fields"]) == {"time_s", "theta", "std_m"}
    meta, _, geom, fields = ogr_read(out / "map.gpkg", layer="poses_gnss")
    assert meta["crs"] == CRS
    xy = np.array([np.frombuffer(g[-16:], "<f8") for g in geom])  # WKB point: x, y at the end
    np.testing.assert_allclose(xy, track.xy, atol=1e-6)
    std = fields[list(meta["fields"]).index("std_m")]
    np.testing.assert_allclose(std, np.sqrt(covs[:, 0, 0]), rtol=1e-9)

    doc = json.loads((out / "trajectory_gnss.geojson").read_text())
    assert "crs" not in doc and doc["stemmap"]["crs"] == CRS  # RFC 7946: WGS84 lon/lat
    lonlat = np.array([f["geometry"]["coordinates"] for f in doc["features"]])
    assert np.all((lonlat[:, 0] > 14.0) & (lonlat[:, 0] < 16.0))  # UTM 33N: 12-18 deg E
    back = Transformer.from_crs("EPSG:4326", CRS, always_xy=True).transform(*lonlat.T)
    np.testing.assert_allclose(np.column_stack(back), track.xy, atol=0.01)  # 8 decimals: 1 mm
    assert {"time_s", "theta", "std_m", "x", "y"} <= set(doc["features"][0]["properties"])


def test_gnss_track_tum_and_too_few_fixes(sim_log: Path) -> None:
    """--trajectory-format tum writes trajectory_gnss.tum beside trajectory.tum; with 10 fixes
    the offset model cannot be estimated: a warning, no track file, the reason in
    metrics.json."""
    out = _map(sim_log, "tum", "--gnss", str(sim_log / "utm.csv"), "--trajectory-format", "tum")
    tum = read_trajectory_tum(out / "trajectory_gnss.tum")
    assert len(tum) == len(read_trajectory_tum(out / "trajectory.tum"))
    assert not (out / "trajectory_gnss.geojson").exists()  # no --crs
    res = CliRunner().invoke(
        app,
        ["map", str(sim_log / "run.npz"), "--out", str(sim_log / "few"), "--no-progress",
         "--gnss", str(sim_log / "few.csv")],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "no trajectory_gnss written" in res.output
    assert not (sim_log / "few" / "trajectory_gnss.csv").exists()
    gt = json.loads((sim_log / "few" / "metrics.json").read_text())["gnss_track"]
    assert gt["written"] is False and "need at least 30" in gt["reason"]
