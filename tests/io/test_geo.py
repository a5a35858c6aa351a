"""Georeferenced products read back through GDAL (pyogrio): CRS and coordinates."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
from pyogrio import list_layers
from pyogrio.raw import read as ogr_read
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import ConfigError
from stemmap.io.geo import (
    GeoLayer,
    array_fields,
    las_crs,
    local_crs,
    parse_crs,
    tangent_plane_crs,
    to_lonlat,
    write_gpkg,
    write_map_gpkg,
)
from stemmap.types import StemMap, Trajectory, Tree

# UTM zone 33N: the central meridian is 15 E and northing 6 651 411.19 m lies on 60 N
# (meridian arc 6 654 073.4 m on WGS84 times k0 = 0.9996), so (500 000, 6 651 411.19) is
# (15 E, 60 N) to < 1e-7 deg -- a published point, independent of our code.
UTM_E, UTM_N = 500000.0, 6651411.19


def _xy(geom: np.ndarray) -> np.ndarray:
    """WKB points (little-endian) to (N, 2)."""
    return np.array([np.frombuffer(g[5:21], "<f8") for g in geom])


def test_known_utm_point_to_lonlat() -> None:
    ll = to_lonlat([[UTM_E, UTM_N], [UTM_E, 0.0]], parse_crs("EPSG:32633"))
    np.testing.assert_allclose(ll, [[15.0, 60.0], [15.0, 0.0]], atol=1e-7)


def test_parse_crs_errors() -> None:
    with pytest.raises(ConfigError, match="not a CRS"):
        parse_crs("EPSG:999999")
    with pytest.raises(ConfigError, match="geographic"):
        parse_crs("EPSG:4326")
    assert parse_crs("EPSG:4326", allow_geographic=True).is_geographic


def test_tangent_plane_origin_is_origin() -> None:
    ll = to_lonlat([[0.0, 0.0], [0.0, 1000.0]], tangent_plane_crs((24.95, 60.17)))
    np.testing.assert_allclose(ll[0], [24.95, 60.17], atol=1e-12)
    # 1 km north along the meridian at 60.17 N: M = 6 383 xxx m -> 0.008976 deg
    assert ll[1, 0] == pytest.approx(24.95, abs=1e-12)
    assert ll[1, 1] - 60.17 == pytest.approx(np.degrees(1000.0 / 6383453.9), rel=1e-4)


def test_map_gpkg_native_crs_and_local(tmp_path: Path) -> None:
    trees = (Tree(1, UTM_E, UTM_N, 0.31, cov=np.diag([0.01, 0.04])), Tree(2, UTM_E + 5, UTM_N, 0.2))
    tr = Trajectory(np.array([0.0, 1.0, 2.0]), np.array([[UTM_E, UTM_N - 3, 0.0]] * 3))
    p = tmp_path / "m.gpkg"
    write_map_gpkg(p, StemMap(trees, crs="EPSG:32633"), tr)
    assert [tuple(r) for r in list_layers(p)] == [
        ("trees", "Point"),
        ("trajectory", "LineString"),
        ("poses", "Point"),
    ]
    meta, _, geom, fields = ogr_read(p, layer="trees")
    assert meta["crs"] == "EPSG:32633"
    np.testing.assert_array_equal(_xy(geom), [[UTM_E, UTM_N], [UTM_E + 5, UTM_N]])
    cols = dict(zip(meta["fields"], fields, strict=True))
    assert cols["diameter"][0] == 0.31 and cols["std_y"][0] == pytest.approx(0.2)
    assert np.isnan(cols["std_x"][1])  # unknown covariance stays NULL
    # no CRS: a local engineering CRS in metres, never WGS84
    q = tmp_path / "local.gpkg"
    write_map_gpkg(q, StemMap(trees), None)
    meta, _, _, _ = ogr_read(q, layer="trees")
    assert meta["crs"].startswith("LOCAL_CS") and "metre" in meta["crs"]
    assert not pyproj.CRS.from_user_input(meta["crs"]).is_geographic


def test_gpkg_write_is_atomic(tmp_path: Path) -> None:
    p = tmp_path / "x.gpkg"
    bad = GeoLayer("t", np.zeros((2, 2)), {"a": np.zeros(3)})  # field length mismatch
    with pytest.raises(Exception):  # noqa: B017, PT011 -- GDAL's error type
        write_gpkg(p, [bad], None, "map")
    assert list(tmp_path.iterdir()) == []


def test_gpkg_text_and_covariance_fields_round_trip(tmp_path: Path) -> None:
    from stemmap.cloud.result import CloudStems

    k = 3
    cov = np.array([[[4e-4, 1e-4], [1e-4, 9e-4]]] * k) * np.arange(1, k + 1)[:, None, None]
    cov[2] = np.nan  # not estimated -> NULL
    z = np.array([1.3, 1.3, 1.3])
    stems = CloudStems(
        np.array([[UTM_E, UTM_N], [UTM_E + 5, UTM_N], [UTM_E, UTM_N + 5]]),
        z, np.array([0.2, 0.3, 0.25]), np.array([50, 60, 70]), np.ones(k), np.full(k, 300.0),
        np.full(k, 0.003), np.array([3, 4, 5]), np.full(k, np.nan), np.array([20.0, 21.0, 22.0]),
        np.full(k, np.nan), diameter_std=np.array([0.004, 0.005, np.nan]), xy_cov=cov,
        dbh_height=np.array([1.3, 1.3, 1.8]),
        dbh_rule=np.array(["breast height", "breast height", "above buttress"], dtype=object),
        method="ours", base="ground",
    )  # fmt: skip
    fields = array_fields(stems, k, skip=("xy",), constants=("method", "base"))
    assert "xy_cov" not in fields and {"cov_xx", "cov_xy", "cov_yy"} <= set(fields)
    p = tmp_path / "s.gpkg"
    write_gpkg(p, [GeoLayer("stems", stems.xy, fields)], "EPSG:32633", "cloud")
    meta, _, geom, data = ogr_read(p, layer="stems")
    got = dict(zip(meta["fields"], data, strict=True))
    assert meta["crs"] == "EPSG:32633"
    np.testing.assert_allclose(_xy(geom), stems.xy)
    np.testing.assert_allclose(got["cov_xx"][:2], [4e-4, 8e-4])
    np.testing.assert_allclose(got["cov_xy"][:2], [1e-4, 2e-4])
    np.testing.assert_allclose(got["cov_yy"][:2], [9e-4, 18e-4])
    assert np.isnan(got["cov_xx"][2])  # NULL reads back as NaN
    assert list(got["dbh_rule"]) == ["breast height", "breast height", "above buttress"]
    assert list(got["base"]) == ["ground"] * k and list(got["method"]) == ["ours"] * k
    np.testing.assert_array_equal(got["n_points"], [50, 60, 70])
    np.testing.assert_allclose(got["diameter_std"][:2], [0.004, 0.005])


def _rings_las(path: Path, crs: str | None, rng: np.random.Generator) -> np.ndarray:
    """Three full trunk rings at 1.2-1.4 m (a height-normalised slice) in UTM 33N."""
    centres = np.array([[UTM_E + 2, UTM_N + 1], [UTM_E - 3, UTM_N + 4], [UTM_E + 5, UTM_N - 5]])
    pts = []
    for c, r in zip(centres, (0.12, 0.2, 0.31), strict=True):
        t = rng.uniform(0, 2 * np.pi, 800)
        ring = (
            c + np.column_stack((np.cos(t), np.sin(t))) * (r + rng.normal(0, 0.003, 800))[:, None]
        )
        pts.append(np.column_stack((ring, rng.uniform(1.2, 1.4, 800))))
    xyz = np.vstack(pts)
    header = laspy.LasHeader(point_format=0, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    if crs is not None:
        header.add_crs(pyproj.CRS(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.write(path)
    return centres


def test_stems_cli_carries_las_crs(tmp_path: Path, rng: np.random.Generator) -> None:
    f = tmp_path / "plot.las"
    centres = _rings_las(f, "EPSG:32633", rng)
    assert las_crs(f) == "EPSG:32633"
    gj, gp = tmp_path / "s.geojson", tmp_path / "s.gpkg"
    args = ["stems", str(f), "--out", str(tmp_path / "s.csv"), "--geojson", str(gj)]
    rep = tmp_path / "s.html"
    res = CliRunner().invoke(app, [*args, "--gpkg", str(gp), "--report", str(rep), "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["crs"] == "EPSG:32633" and summary["n_stems"] == 3
    page = rep.read_text()
    assert "data-key='n_stems'>3<" in page and "data:image/png;base64," in page
    assert not list(tmp_path.glob("*figure*"))  # the report's figure is inlined, not left behind
    doc = json.loads(gj.read_text())
    assert "crs" not in doc and doc["stemmap"]["crs"] == "EPSG:32633"
    lonlat = np.array([f["geometry"]["coordinates"] for f in doc["features"]])
    # the stems are within 10 m of (15 E, 60 N): 10 m = 1.8e-4 deg of longitude at 60 N
    assert np.all(np.abs(lonlat - [15.0, 60.0]) < 2e-4)
    native = np.array([[f["properties"]["x"], f["properties"]["y"]] for f in doc["features"]])
    np.testing.assert_allclose(to_lonlat(native, parse_crs("EPSG:32633")), lonlat, atol=1e-8)
    meta, _, geom, _ = ogr_read(gp)
    assert meta["crs"] == "EPSG:32633"
    got = _xy(geom)
    d = np.hypot(*(got[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    assert np.all(d.min(axis=1) < 0.01)  # every stem within 1 cm of a ring centre
    # the GPKG carries the CSV's uncertainty and text columns (same names)
    cols = set(meta["fields"])
    assert {"diameter_std", "cov_xx", "cov_xy", "cov_yy", "dbh_rule", "base", "method"} <= cols
    # --crs overrides the header; a geographic CRS is refused with a clear error
    res = CliRunner().invoke(app, [*args, "--crs", "EPSG:4326"])
    assert res.exit_code == 2 and "geographic" in res.output


def test_stems_cli_local_frame(tmp_path: Path, rng: np.random.Generator) -> None:
    f = tmp_path / "plot.las"
    _rings_las(f, None, rng)
    assert las_crs(f) is None
    gj = tmp_path / "s.geojson"
    res = CliRunner().invoke(
        app, ["stems", str(f), "--out", str(tmp_path / "s.csv"), "--geojson", str(gj)]
    )
    assert res.exit_code == 0, res.output
    meta, _, geom, _ = ogr_read(gj)
    assert meta["crs"] == local_crs("cloud").to_wkt(version="WKT1_GDAL")
    assert np.all(_xy(geom)[:, 0] > UTM_E - 10)  # metres, not degrees


@pytest.mark.slow
def test_map_cli_crs_gpkg_tum(tmp_path: Path) -> None:
    out = tmp_path / "m"
    res = CliRunner().invoke(
        app,
        [
            "map",
            "--sim",
            "--sim-trees",
            "40",
            "--sim-size",
            "30",
            "--backend",
            "ekf",
            "--no-progress",
            "--out",
            str(out),
            "--crs",
            "EPSG:32633",
            "--gpkg",
            "--trajectory-format",
            "tum",
            "--json",
        ],
    )
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)  # --json: one object on stdout, nothing else
    assert {"trees.csv", "map.gpkg", "trajectory.tum", "report.html"} <= set(doc["files"])
    assert int(doc["summary"]["trees mapped"]) == doc["metrics"]["n_trees"]
    trees = np.loadtxt(out / "trees.csv", delimiter=",", skiprows=1, ndmin=2)
    meta, _, geom, _ = ogr_read(out / "map.gpkg", layer="trees")
    assert meta["crs"] == "EPSG:32633"
    np.testing.assert_array_equal(_xy(geom), trees[:, 1:3])
    meta, _, geom, _ = ogr_read(out / "trees.geojson")
    np.testing.assert_allclose(
        _xy(geom), to_lonlat(trees[:, 1:3], parse_crs("EPSG:32633")), atol=1e-8
    )
    tum = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert tum.shape[1] == 8
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"]["crs"] == "EPSG:32633"


def test_las_crs_checks_the_file_before_laspy(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the user audit (docs/cli.md): `stems` read the CRS before the reader's checks, so a
    # missing, empty or non-LAS file was "an unreadable CRS record", and a damaged VLR count
    # (2^32 - 1) made laspy loop for minutes before any check ran
    import struct

    from stemmap.errors import InputError

    good = tmp_path / "plot.las"
    _rings_las(good, None, rng)
    bad = tmp_path / "vlrs.las"
    raw = bytearray(good.read_bytes())
    raw[100:104] = struct.pack("<I", 0xFFFFFFFF)  # number_of_vlrs
    bad.write_bytes(bytes(raw))
    (tmp_path / "empty.laz").write_bytes(b"")
    (tmp_path / "text.laz").write_text("x y z\n" * 30)

    def no_laspy(*args: object, **kwargs: object) -> None:
        raise AssertionError("laspy must not read a file the header checks refuse")

    monkeypatch.setattr(laspy, "open", no_laspy)
    for name, says in [
        ("missing.laz", "does not exist"),
        ("empty.laz", "is empty"),
        ("text.laz", "not a LAS/LAZ file"),
        ("vlrs.las", "header is corrupt"),
    ]:
        with pytest.raises(InputError, match=says) as err:
            las_crs(tmp_path / name)
        assert "CRS record" not in str(err.value)
