"""Stem maps (CSV, GeoJSON), observations CSV, trajectories (CSV, TUM) and atomic writes."""

from __future__ import annotations

import doctest
import json
import logging
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stemmap.io.maps as maps_mod
import stemmap.io.trajectory as traj_mod
from stemmap.errors import InputError
from stemmap.io import (
    OBSERVATION_CSV_COLUMNS,
    TREE_CSV_COLUMNS,
    local_to_lonlat,
    lonlat_to_local,
    read_observations_csv,
    read_trajectory_csv,
    read_trajectory_csv_with_covariance,
    read_trajectory_tum,
    read_trees_csv,
    read_trees_geojson,
    write_observations_csv,
    write_scans_npz,
    write_trajectory_csv,
    write_trajectory_tum,
    write_trees_csv,
    write_trees_geojson,
)
from stemmap.types import ScanBatch, StemMap, StemObservations, Trajectory, Tree


def _map(rng: np.random.Generator, n: int = 12, crs: str | None = None) -> StemMap:
    trees = []
    for i in range(n):
        sx, sy = rng.uniform(0.01, 0.2, 2)
        rho = rng.uniform(-0.9, 0.9)
        cov = np.array([[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]])
        trees.append(
            Tree(
                id=100 + i,
                x=float(rng.uniform(-50, 50)),
                y=float(rng.uniform(-50, 50)),
                diameter=float(rng.uniform(0.08, 0.8)),
                cov=cov if i != 3 else np.full((2, 2), np.nan),  # tree 3: unknown covariance
                n_obs=int(rng.integers(1, 40)),
                first_time=float(rng.uniform(0, 10)),
                last_time=float(rng.uniform(10, 20)) if i != 5 else math.nan,
                confidence=float(rng.uniform(0, 1)),
                diameter_std=float(rng.uniform(0, 0.02)) if i != 7 else math.nan,
            )
        )
    return StemMap(tuple(trees), frame="map", crs=crs)


def _same_trees(a: StemMap, b: StemMap) -> None:
    assert len(a) == len(b)
    for s, t in zip(a, b, strict=True):
        assert (s.id, s.n_obs) == (t.id, t.n_obs)
        # positions, diameters, times: shortest-repr floats read back bit-exactly
        for f in ("x", "y", "diameter", "first_time", "last_time", "confidence", "diameter_std"):
            np.testing.assert_array_equal(getattr(s, f), getattr(t, f), err_msg=f)
        # covariance goes through std = sqrt(var) and back: 1 ulp-level relative error
        np.testing.assert_allclose(s.cov, t.cov, rtol=1e-14, atol=0)


# ---------------------------------------------------------------- trees CSV


def test_trees_csv_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    m = _map(rng)
    p = tmp_path / "trees.csv"
    write_trees_csv(p, m)
    header = p.read_text().splitlines()[0].split(",")
    assert tuple(header) == TREE_CSV_COLUMNS
    assert header[:7] == ["id", "x", "y", "diameter", "std_x", "std_y", "n_obs"]
    _same_trees(m, read_trees_csv(p))
    assert read_trees_csv(p, frame="utm", crs="EPSG:3067").crs == "EPSG:3067"


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-1e7, 1e7, allow_nan=False),
            st.floats(-1e7, 1e7, allow_nan=False),
            st.floats(0, 5, allow_nan=False),
        ),
        max_size=8,
    )
)
def test_trees_csv_round_trip_property(
    tmp_path_factory: pytest.TempPathFactory, rows: list
) -> None:
    m = StemMap(tuple(Tree(i, x, y, d) for i, (x, y, d) in enumerate(rows)))
    p = tmp_path_factory.mktemp("h") / "t.csv"
    write_trees_csv(p, m)
    _same_trees(m, read_trees_csv(p))


def test_trees_csv_minimal_columns(tmp_path: Path) -> None:
    p = tmp_path / "t.csv"
    p.write_text("# hand-made\nid,x,y,diameter\n1,0.5,2.5,0.31\n2,-1,3,0.2\n")
    m = read_trees_csv(p)
    assert [t.id for t in m] == [1, 2] and m.trees[0].diameter == 0.31
    assert np.isnan(m.trees[0].cov).all() and m.trees[0].n_obs == 0
    assert m.trees[1].confidence == 1.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty"),
        ("id,x,y\n1,2,3\n", "lacks column.*diameter"),
        ("id,x,y,diameter\n1,2,3\n", "line 2 has 3 fields.*truncated"),
        ("id,x,y,diameter\n1,2,nan,0.3\n", "line 2: column 'y' is nan"),
        ("id,x,y,diameter\n1,2,3,inf\n", "column 'diameter' is inf"),
        ("id,x,y,diameter\n1.5,2,3,0.3\n", "column 'id' is 1.5.*whole number"),
        ("id,x,y,diameter\n1,2,3,0.3\n1,4,5,0.2\n", "repeats tree id 1"),
        ("id,x,y,diameter\n1,2,3,-0.3\n", "diameter -0.3 is negative"),
        ("id,x,y,diameter\n1,2,abc,0.3\n", "line 2, column 'y': 'abc' is not a number"),
        ("id,x,y,y,diameter\n1,2,3,4,0.3\n", "repeats column"),
        ("id,x,y,diameter,n_obs\n1,2,3,0.3,2.5\n", "'n_obs' is 2.5"),
    ],
)
def test_trees_csv_bad_files(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        read_trees_csv(p)


def test_missing_and_binary_files(tmp_path: Path) -> None:
    for reader in (read_trees_csv, read_observations_csv, read_trajectory_csv, read_trees_geojson):
        with pytest.raises(InputError, match="does not exist"):
            reader(tmp_path / "none.csv")
    b = tmp_path / "bin.csv"
    b.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xff")
    with pytest.raises(InputError, match="not UTF-8"):
        read_trees_csv(b)
    with pytest.raises(InputError, match="not a regular file"):
        read_trees_csv(tmp_path)


# ---------------------------------------------------------------- GeoJSON


def _strict_json(path: Path) -> dict:
    def bad_constant(c: str) -> None:
        raise AssertionError(f"GeoJSON contains {c}, which is not JSON")

    return json.loads(path.read_text(), parse_constant=bad_constant)


def _check_rfc7946(doc: dict) -> None:
    assert doc["type"] == "FeatureCollection"
    for f in doc["features"]:
        assert f["type"] == "Feature" and f["geometry"]["type"] == "Point"
        c = f["geometry"]["coordinates"]
        assert len(c) == 2 and all(isinstance(v, float) for v in c)
        assert isinstance(f["properties"], dict)
    if doc["features"]:
        xs = [f["geometry"]["coordinates"][0] for f in doc["features"]]
        ys = [f["geometry"]["coordinates"][1] for f in doc["features"]]
        assert doc["bbox"] == [min(xs), min(ys), max(xs), max(ys)]


def test_geojson_local_frame(tmp_path: Path, rng: np.random.Generator) -> None:
    """Without a CRS the geometry stays in metres and is declared a local engineering CRS:
    GDAL reads LOCAL_CS metres, not WGS84 degrees (the map must not land at latitude 152)."""
    from pyogrio.raw import read as ogr_read

    m = _map(rng)
    p = tmp_path / "trees.geojson"
    write_trees_geojson(p, m)
    doc = _strict_json(p)
    _check_rfc7946(doc)
    assert doc["stemmap"]["units"] == "m" and doc["stemmap"]["crs"] is None
    f3 = doc["features"][3]
    assert f3["properties"]["std_x"] is None and f3["geometry"]["coordinates"][0] == m.trees[3].x
    meta, _, geom, _ = ogr_read(p)
    assert meta["crs"].startswith("LOCAL_CS") and "metre" in meta["crs"]
    x, y = np.frombuffer(geom[3][5:], "<f8")
    assert (x, y) == (m.trees[3].x, m.trees[3].y)
    back = read_trees_geojson(p)
    assert back.crs is None
    _same_trees(m, back)


def test_geojson_projected_is_rfc7946_lonlat(tmp_path: Path) -> None:
    """A UTM map is written in WGS84 lon/lat: the central-meridian point (500000 m, 0 m) of
    UTM 33N (EPSG:32633) is (15 E, 0 N) by definition; GDAL reads it back as WGS84."""
    from pyogrio.raw import read as ogr_read

    m = StemMap((Tree(1, 500000.0, 0.0, 0.3), Tree(2, 500000.0, 6651411.19, 0.3)), crs="EPSG:32633")
    p = tmp_path / "utm.geojson"
    write_trees_geojson(p, m)
    doc = _strict_json(p)
    assert "crs" not in doc and doc["stemmap"]["units"] == "degrees"
    assert doc["features"][0]["geometry"]["coordinates"] == [15.0, 0.0]
    # 6 651 411.19 m of meridian arc from the equator is 60 N on WGS84 (UTM k0 = 0.9996)
    assert doc["features"][1]["geometry"]["coordinates"] == pytest.approx([15.0, 60.0], abs=1e-7)
    meta, _, _, _ = ogr_read(p)
    assert "WGS 84" in meta["crs"] or meta["crs"] == "EPSG:4326"
    back = read_trees_geojson(p)
    assert back.crs == "EPSG:32633"
    np.testing.assert_array_equal(back.xy, m.xy)  # the native x, y properties


def test_geojson_with_origin_is_lonlat(tmp_path: Path, rng: np.random.Generator) -> None:
    m = _map(rng)
    origin = (24.95, 60.17)
    p = tmp_path / "lonlat.geojson"
    write_trees_geojson(p, m, origin_lonlat=origin, precision=9)
    doc = _strict_json(p)
    _check_rfc7946(doc)
    assert "crs" not in doc and doc["stemmap"]["units"] == "degrees"
    lon = np.array([f["geometry"]["coordinates"][0] for f in doc["features"]])
    lat = np.array([f["geometry"]["coordinates"][1] for f in doc["features"]])
    assert np.all(np.abs(lon - origin[0]) < 0.01) and np.all(np.abs(lat - origin[1]) < 0.01)
    # the transverse Mercator of the origin and the tangent-plane formulas agree to < 1 mm
    # within 50 m of the origin
    np.testing.assert_allclose(lonlat_to_local(lon, lat, origin), m.xy, atol=1e-3)
    _same_trees(m, read_trees_geojson(p))  # the metric x, y properties are kept


def test_wgs84_radii_of_curvature() -> None:
    # Published WGS84 values: meridional radius M = 6 335 439 m and prime vertical N =
    # 6 378 137 m at the equator; 1 deg of latitude = 110 574 m at 0 deg, 111 694 m at 90 deg.
    lon, lat = local_to_lonlat(np.array([[1000.0, 1000.0]]), (0.0, 0.0))
    assert math.radians(lat[0]) * 6335439.3 == pytest.approx(1000.0, abs=1e-3)
    assert math.radians(lon[0]) * 6378137.0 == pytest.approx(1000.0, abs=1e-6)
    _, lat1 = local_to_lonlat(np.array([[0.0, 110574.3]]), (0.0, 0.0))
    assert lat1[0] == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(InputError, match="origin_lonlat"):
        local_to_lonlat(np.zeros((1, 2)), (60.0, 95.0))


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ("not json", "not valid JSON"),
        ('{"type": "Feature"}', "not a FeatureCollection"),
        ('{"type": "FeatureCollection"}', "no 'features' list"),
        (
            '{"type":"FeatureCollection","features":[{"type":"Feature","geometry":'
            '{"type":"LineString","coordinates":[[0,0],[1,1]]},"properties":{}}]}',
            "feature 0 is not a Point",
        ),
        (
            '{"type":"FeatureCollection","features":[{"type":"Feature","geometry":'
            '{"type":"Point","coordinates":[0,0]},"properties":{}}]}',
            "feature 0 lacks a finite position or diameter",
        ),
        (
            '{"type":"FeatureCollection","features":[{"type":"Feature","geometry":'
            '{"type":"Point","coordinates":[0,0]},"properties":{"diameter":"big"}}]}',
            "feature 0 has a malformed field",
        ),
    ],
)
def test_geojson_bad_files(tmp_path: Path, doc: str, match: str) -> None:
    p = tmp_path / "bad.geojson"
    p.write_text(doc)
    with pytest.raises(InputError, match=match):
        read_trees_geojson(p)


# ---------------------------------------------------------------- observations CSV


def _obs(rng: np.random.Generator, k: int = 30) -> StemObservations:
    covs = np.zeros((k, 3, 3))
    covs[:, 0, 0], covs[:, 1, 1], covs[:, 2, 2] = rng.uniform(1e-5, 1e-3, (3, k))
    covs[k // 2] = np.nan  # a fit without covariance
    return StemObservations(
        centers=rng.uniform(-10, 10, (k, 2)),
        radii=rng.uniform(0.04, 0.4, k),
        covs=covs,
        n_points=rng.integers(3, 80, k),
        arc_deg=rng.uniform(20, 180, k),
        widths=rng.uniform(0.05, 0.8, k),
        quality=rng.uniform(0, 1, k),
        index=np.sort(rng.integers(0, 500, k)),
        times=np.sort(rng.uniform(0, 60, k)),
        source="scan:ours",
        frame="laser",
    )


def test_observations_csv_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    o = _obs(rng)
    p = tmp_path / "stems.csv"
    write_observations_csv(p, o)
    lines = p.read_text().splitlines()
    assert tuple(lines[0].split(",")) == OBSERVATION_CSV_COLUMNS
    assert lines[0].startswith("scan_index,time_s,x,y,diameter,radius_std,n_points")
    assert len(lines) == len(o) + 1
    b = read_observations_csv(p, source="scan:ours")
    for name in ("centers", "radii", "n_points", "arc_deg", "widths", "quality", "index", "times"):
        np.testing.assert_array_equal(getattr(o, name), getattr(b, name), err_msg=name)
    # variances go through sqrt and back
    d_in = np.diagonal(o.covs, axis1=1, axis2=2)
    d_out = np.diagonal(b.covs, axis1=1, axis2=2)
    np.testing.assert_allclose(d_out, d_in, rtol=1e-14)
    assert b.source == "scan:ours" and b.frame == "laser"


def test_observations_csv_empty_and_minimal(tmp_path: Path) -> None:
    p = tmp_path / "none.csv"
    write_observations_csv(p, StemObservations.empty())
    assert len(read_observations_csv(p)) == 0
    q = tmp_path / "min.csv"
    q.write_text("scan_index,time,x,y,diameter\n3,0.5,1,2,0.3\n")
    o = read_observations_csv(q)
    assert o.index.tolist() == [3] and o.radii.tolist() == [0.15] and np.isnan(o.covs[0, 2, 2])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("scan_index,time,x,y\n1,2,3,4\n", "lacks column.*diameter"),
        ("scan_index,time,x,y,diameter\n1.5,0,0,0,0.3\n", "'scan_index' is 1.5"),
        ("scan_index,time,x,y,diameter\n1,nan,0,0,0.3\n", "'time_s' is nan"),
        ("scan_index,time,x,y,diameter\n1,0,0,0,-1\n", "negative"),
        ("scan_index,time,x,y,diameter,n_points\n1,0,0,0,1,2.5\n", "'n_points' is 2.5"),
    ],
)
def test_observations_csv_bad_files(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        read_observations_csv(p)


# ---------------------------------------------------------------- trajectories


def _traj(rng: np.random.Generator, n: int = 50) -> Trajectory:
    t = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.2, n))
    th = np.angle(np.exp(1j * np.cumsum(rng.normal(0, 0.5, n))))
    return Trajectory(t, np.column_stack((rng.normal(0, 100, (n, 2)), th)), frame="odom")


def test_trajectory_csv_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    tr = _traj(rng)
    p = tmp_path / "path.csv"
    write_trajectory_csv(p, tr)
    assert p.read_text().splitlines()[0] == "time_s,x,y,theta"
    back = read_trajectory_csv(p, frame="odom")
    np.testing.assert_array_equal(back.times, tr.times)
    np.testing.assert_array_equal(back.poses, tr.poses)
    assert back.frame == "odom"


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, 3, 3)) * np.array([0.3, 0.3, 0.01])[None, :, None]
    return a @ np.swapaxes(a, 1, 2)


def test_trajectory_csv_covariance_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    tr = _traj(rng)
    covs = _spd(rng, len(tr))
    covs[[3, 7]] = np.nan  # rows without a covariance (e.g. poses a loop relaxation moved)
    p = tmp_path / "path.csv"
    write_trajectory_csv(p, tr, covs=covs)
    assert p.read_text().splitlines()[0].split(",") == [
        *traj_mod.TRAJECTORY_CSV_COLUMNS,
        *traj_mod.TRAJECTORY_COV_COLUMNS,
    ]
    back, bc = read_trajectory_csv_with_covariance(p, frame="odom")
    np.testing.assert_array_equal(back.poses, tr.poses)
    assert bc is not None
    np.testing.assert_array_equal(bc, covs)  # exact: shortest round-trip floats, NaN kept
    np.testing.assert_array_equal(read_trajectory_csv(p).poses, tr.poses)  # plain reader


def test_trajectory_csv_without_covariance(tmp_path: Path, rng: np.random.Generator) -> None:
    tr = _traj(rng, n=5)
    p = tmp_path / "path.csv"
    write_trajectory_csv(p, tr, covs=np.full((5, 3, 3), np.nan))  # none known: no columns
    assert p.read_text().splitlines()[0] == "time_s,x,y,theta"
    assert read_trajectory_csv_with_covariance(p)[1] is None
    # an empty covariance field (a hand-edited or other tool's file) reads as NaN
    head = ",".join((*traj_mod.TRAJECTORY_CSV_COLUMNS, *traj_mod.TRAJECTORY_COV_COLUMNS))
    p.write_text(f"{head}\n0,1,2,0.5,,,,,,\n1,1,2,0.5,1,0,1,0,0,0.01\n")
    _, c = read_trajectory_csv_with_covariance(p)
    assert c is not None and np.isnan(c[0]).all() and c[1, 2, 2] == 0.01
    p.write_text("time_s,x,y,theta,cov_xx_m2\n0,1,2,0.5,1\n")
    with pytest.raises(InputError, match="lacks cov_xy_m2"):
        read_trajectory_csv_with_covariance(p)
    with pytest.raises(InputError, match="shape"):
        write_trajectory_csv(p, tr, covs=np.zeros((4, 3, 3)))


def test_trajectory_tum_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    tr = _traj(rng)
    p = tmp_path / "path.tum"
    write_trajectory_tum(p, tr)
    first = p.read_text().splitlines()[1].split(" ")
    assert len(first) == 8 and first[3] == "0.0" and first[4] == first[5] == "0.0"
    back = read_trajectory_tum(p)
    np.testing.assert_array_equal(back.times, tr.times)
    np.testing.assert_array_equal(back.poses[:, :2], tr.poses[:, :2])
    # yaw -> half-angle quaternion -> atan2: a few ulp; compare on the circle
    dth = np.angle(np.exp(1j * (back.poses[:, 2] - tr.poses[:, 2])))
    assert np.max(np.abs(dth)) < 1e-14


@settings(max_examples=60, deadline=None)
@given(st.floats(-math.pi, math.pi))
def test_yaw_quaternion_inverse(yaw: float) -> None:
    q = traj_mod.yaw_to_quaternion(np.array([yaw]))
    back = traj_mod.yaw_from_quaternion(q)[0]
    assert abs(math.remainder(back - yaw, 2 * math.pi)) < 1e-14
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)


def test_tum_tilted_poses_warn_and_project(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # 20 deg roll about x and yaw 0.3: q = q_yaw * q_roll
    r, y = math.radians(20), 0.3
    qr = np.array([math.sin(r / 2), 0, 0, math.cos(r / 2)])
    qy = np.array([0, 0, math.sin(y / 2), math.cos(y / 2)])
    x1, y1, z1, w1 = qy
    x2, y2, z2, w2 = qr
    q = [
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ]
    p = tmp_path / "t.txt"
    p.write_text("# tum\n1.0 1 2 3 " + " ".join(map(str, q)) + "\n2.0,1,2,3,0,0,0,1\n")
    with caplog.at_level(logging.WARNING):
        tr = read_trajectory_tum(p)
    assert tr.poses[0, 2] == pytest.approx(0.3, abs=1e-12)
    assert any("tilt up to 20.0 deg" in m.message for m in caplog.records)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "holds no poses"),
        ("1 2 3 4 5 6 7\n", "line 1 has 7 fields"),
        ("1 2 3 4 0 0 0 0\n", "zero quaternion"),
        ("1 2 3 4 0 0 0 x\n", "could not convert"),
        ("1 nan 3 4 0 0 0 1\n", "NaN or inf"),
        ("# c\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "line 3: time 1.0 does not increase"),
    ],
)
def test_tum_bad_files(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "bad.tum"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        read_trajectory_tum(p)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("time,x,y\n0,1,2\n", "lacks column.*theta"),
        ("time,x,y,theta\n0,1,2,nan\n", "'theta' is nan"),
        ("time,x,y,theta\n0,1,2,0\n0,1,2,0\n", "line 3: time 0.0 does not increase"),
        ("time,x,y,theta\n", None),
    ],
)
def test_trajectory_csv_bad_files(tmp_path: Path, text: str, match: str | None) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    if match is None:  # header only: an empty trajectory is valid
        assert len(read_trajectory_csv(p)) == 0
        return
    with pytest.raises(InputError, match=match):
        read_trajectory_csv(p)


# ---------------------------------------------------------------- atomic writes


class _BoomError(RuntimeError):
    pass


def _writers(tmp_path: Path, rng: np.random.Generator) -> list:
    m, o, tr = _map(rng, n=3), _obs(rng, k=3), _traj(rng, n=3)
    b = ScanBatch(np.ones((2, 3)), np.array([0.0, 1.0]), 0.0, 0.1)
    return [
        (write_trees_csv, m, "fmt_row", maps_mod),
        (write_observations_csv, o, "fmt_row", maps_mod),
        (write_trees_geojson, m, "_json_num", maps_mod),
        (write_trajectory_csv, tr, "fmt_row", traj_mod),
        (write_trajectory_tum, tr, "fmt_row", traj_mod),
        (write_scans_npz, b, None, None),
    ]


@pytest.mark.parametrize("which", range(6))
def test_exception_mid_write_leaves_no_file(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch, which: int
) -> None:
    writer, value, hook, module = _writers(tmp_path, rng)[which]
    out = tmp_path / "out" / "product.dat"
    calls = {"n": 0}
    if module is None:  # NPZ: fail inside numpy's zip writer
        import numpy

        def boom_savez(*a: object, **k: object) -> None:
            raise _BoomError("disk full")

        monkeypatch.setattr(numpy, "savez_compressed", boom_savez)
    else:
        real = getattr(module, hook)

        def flaky(*a: object, **k: object) -> object:
            calls["n"] += 1
            if calls["n"] == 2:  # fail after the first row is already written
                raise _BoomError("interrupted")
            return real(*a, **k)

        monkeypatch.setattr(module, hook, flaky)
    with pytest.raises(_BoomError):
        writer(out, value)
    # neither the target nor a temp file (GeoJSON fails before it even creates the folder)
    assert not out.parent.exists() or os.listdir(out.parent) == []


def test_failed_write_keeps_previous_file(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    p = tmp_path / "trees.csv"
    m = _map(rng, n=4)
    write_trees_csv(p, m)
    before = p.read_bytes()

    def boom(*a: object) -> str:
        raise _BoomError("killed")

    monkeypatch.setattr(maps_mod, "fmt_row", boom)
    with pytest.raises(_BoomError):
        write_trees_csv(p, _map(rng, n=9))
    assert p.read_bytes() == before and os.listdir(tmp_path) == ["trees.csv"]


def test_docstring_examples_run() -> None:
    for mod in (maps_mod, traj_mod):
        res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS)
        assert res.failed == 0


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-179.0, 179.0),
    st.floats(-80.0, 80.0),
    st.floats(-2000.0, 2000.0),
    st.floats(-2000.0, 2000.0),
)
def test_local_lonlat_inverse(lon0: float, lat0: float, x: float, y: float) -> None:
    lon, lat = local_to_lonlat(np.array([[x, y]]), (lon0, lat0))
    back = lonlat_to_local(lon, lat, (lon0, lat0))
    # exact inverses up to float rounding of degrees near 180 (1e-13 deg ~ 1e-8 m)
    np.testing.assert_allclose(back[0], [x, y], atol=1e-6)


def test_atomic_write_gives_plain_file_permissions(tmp_path: Path) -> None:
    """A product must be readable like a file from open(): 0666 less the umask (not mkstemp's
    0600), and a rewrite keeps an existing file's mode."""
    import os

    from stemmap.io.atomic import atomic_write

    old = os.umask(0o022)
    try:
        new = tmp_path / "new.csv"
        with atomic_write(new) as fh:
            fh.write("a\n")
        assert new.stat().st_mode & 0o777 == 0o644
        new.chmod(0o640)
        with atomic_write(new) as fh:
            fh.write("b\n")
        assert new.stat().st_mode & 0o777 == 0o640
        assert new.read_text() == "b\n"
    finally:
        os.umask(old)


def _info_map(rng: np.random.Generator, n: int = 4) -> StemMap:
    a = rng.normal(size=(2 * n, 2 * n))
    info = a @ a.T + 2 * n * np.eye(2 * n)  # positive definite, with correlations
    trees = tuple(
        Tree(id=10 + 3 * i, x=float(i), y=float(-i), diameter=0.3, cov=np.eye(2) * 0.01)
        for i in range(n)
    )
    return StemMap(trees, information=info)


def test_trees_information_round_trip_reorders_by_id(tmp_path: Path) -> None:
    from dataclasses import replace

    rng = np.random.default_rng(3)
    sm = _info_map(rng)
    p = tmp_path / maps_mod.TREES_INFORMATION_NPZ
    maps_mod.write_trees_information(p, sm)
    back = maps_mod.read_trees_information(p, replace(sm, information=None))
    assert back.information is not None
    assert np.array_equal(back.information, sm.information)  # exact: float64 in NPZ
    # a map whose trees come in another order (a hand-sorted CSV): the matrix follows the ids
    order = [2, 0, 3, 1]
    shuffled = StemMap(tuple(sm.trees[k] for k in order))
    got = maps_mod.read_trees_information(p, shuffled)
    cols = np.array([[2 * k, 2 * k + 1] for k in order]).reshape(-1)
    assert got.information is not None
    assert np.array_equal(got.information, np.asarray(sm.information)[np.ix_(cols, cols)])


def test_trees_information_rejects_a_foreign_or_broken_file(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    sm = _info_map(rng)
    p = tmp_path / "ti.npz"
    maps_mod.write_trees_information(p, sm)
    other = StemMap(sm.trees[:3])  # one tree fewer: not the CSV it was written with
    with pytest.raises(InputError, match="differ"):
        maps_mod.read_trees_information(p, other)
    np.savez(p, tree_ids=np.arange(4))
    with pytest.raises(InputError, match="information"):
        maps_mod.read_trees_information(p, StemMap(sm.trees))
    with pytest.raises(InputError, match="no joint information"):
        maps_mod.write_trees_information(p, StemMap(sm.trees))
