"""`stemmap stems` on a real cloud re-expressed in other tools' conventions (feet, Y up, a LAS
CRS in US survey feet): the same stems with --units / --up-axis, a warning or a refusal
without them (docs/reliability.md, "Input conventions")."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()
FOOT = 0.3048


def _xyz(datasets_dir: Path) -> np.ndarray:
    import laspy

    las = laspy.read(datasets_dir / "lidr_dbh" / "dbh.laz")  # a real 16-beam trunk slice
    return np.column_stack((las.x, las.y, las.z)).astype(np.float64)


def _stems(tmp_path: Path, cloud: Path, *extra: str) -> tuple[list[dict[str, str]], str]:
    out = tmp_path / f"{cloud.stem}_{len(extra)}.csv"
    res = runner.invoke(app, ["stems", str(cloud), "-o", str(out), "-q", *extra])
    assert res.exit_code == 0, res.output
    with out.open() as fh:
        return list(csv.DictReader(fh)), res.output


@pytest.fixture
def metres(tmp_path: Path, datasets_dir: Path) -> list[dict[str, str]]:
    path = tmp_path / "m.xyz"
    np.savetxt(path, _xyz(datasets_dir), fmt="%.9f")
    rows, _ = _stems(tmp_path, path)
    assert len(rows) == 1
    return rows


def test_cloud_in_feet_warns_then_matches_with_units(
    tmp_path: Path, datasets_dir: Path, metres: list[dict[str, str]]
) -> None:
    path = tmp_path / "ft.xyz"
    np.savetxt(path, _xyz(datasets_dir) / FOOT, fmt="%.9f")
    rows, output = _stems(tmp_path, path)
    # read as metres: one "stem" of ~0.94 m (x3.28) and, since Dec 4, a warning naming --units
    assert float(rows[0]["diameter"]) > 0.6
    assert "--units ft" in " ".join(output.split())
    rows, _ = _stems(tmp_path, path, "--units", "ft")
    # the conversion is exact up to the text's 1e-9 digits: the same fit to 1e-6 m
    assert float(rows[0]["diameter"]) == pytest.approx(float(metres[0]["diameter"]), abs=1e-6)
    assert float(rows[0]["x"]) == pytest.approx(float(metres[0]["x"]), abs=1e-6)


def test_y_up_cloud_matches_with_up_axis(
    tmp_path: Path, datasets_dir: Path, metres: list[dict[str, str]]
) -> None:
    xyz = _xyz(datasets_dir)
    path = tmp_path / "yup.xyz"
    np.savetxt(path, np.column_stack((xyz[:, 0], xyz[:, 2], -xyz[:, 1])), fmt="%.9f")
    rows, _ = _stems(tmp_path, path, "--up-axis", "y")
    assert len(rows) == 1
    for key in ("x", "y", "diameter"):
        assert float(rows[0][key]) == pytest.approx(float(metres[0][key]), abs=1e-6)


def test_las_in_state_plane_feet_is_refused_without_units(
    tmp_path: Path, datasets_dir: Path, metres: list[dict[str, str]]
) -> None:
    import laspy
    import pyproj

    xyz = _xyz(datasets_dir) / (1200.0 / 3937.0)
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(2264))  # NC State Plane, US survey feet
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    path = tmp_path / "feet.las"
    las.write(path)
    res = runner.invoke(app, ["stems", str(path), "-o", str(tmp_path / "s.csv"), "-q"])
    assert res.exit_code == 2
    assert "--units us-ft" in " ".join(res.output.split())
    rows, _ = _stems(tmp_path, path, "--units", "us-ft")
    assert float(rows[0]["diameter"]) == pytest.approx(float(metres[0]["diameter"]), abs=2e-4)


def _feet_las(tmp_path: Path, xyz: np.ndarray) -> tuple[Path, np.ndarray]:
    """A real cloud moved to a State Plane position and written in US survey feet with the
    CRS EPSG:2264 in its header; returns the path and the points as written (feet)."""
    import laspy
    import pyproj

    usft = 1200.0 / 3937.0
    xyz = (xyz - xyz.mean(axis=0) + [600_000.0, 200_000.0, 100.0]) / usft
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(2264))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    path = tmp_path / "stateplane.las"
    las.write(path)
    return path, np.column_stack((las.x, las.y, las.z))


def test_georeferenced_products_of_a_cloud_in_feet_are_in_its_crs(
    tmp_path: Path, datasets_dir: Path
) -> None:
    """`--units us-ft --geojson --gpkg --dtm` on a LAS in EPSG:2264: the CSV in metres, the
    GeoJSON's lon/lat those of the stem's position in feet, the GeoPackage and DTM in the
    CRS's feet. Before Dec 5 these were refused with --units."""
    import json

    import laspy
    import pyproj
    import rasterio

    pine = laspy.read(datasets_dir / "treels" / "pine.laz")  # a real tree with its ground
    path, xyz = _feet_las(tmp_path, np.column_stack((pine.x, pine.y, pine.z)))
    out = tmp_path / "s.csv"
    res = runner.invoke(
        app,
        ["stems", str(path), "-o", str(out), "--units", "us-ft", "-q",
         "--geojson", str(tmp_path / "s.geojson"), "--gpkg", str(tmp_path / "s.gpkg"),
         "--dtm", str(tmp_path / "dtm.tif")],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    with out.open() as fh:
        (row,) = list(csv.DictReader(fh))
    usft = 1200.0 / 3937.0
    x_ft, y_ft = float(row["x"]) / usft, float(row["y"]) / usft
    # the stem lies inside the cloud's footprint in feet (the CSV is in metres)
    assert xyz[:, 0].min() < x_ft < xyz[:, 0].max()
    feat = json.loads((tmp_path / "s.geojson").read_text())["features"][0]
    lon, lat = pyproj.Transformer.from_crs(2264, 4326, always_xy=True).transform(x_ft, y_ft)
    # 1e-8 degrees ~ 1 mm: the GeoJSON's point is the CSV's, in the CRS's feet
    assert feat["geometry"]["coordinates"] == pytest.approx([lon, lat], abs=1e-8)
    with rasterio.open(tmp_path / "dtm.tif") as ds:
        assert ds.crs.to_epsg() == 2264
        b = ds.bounds  # in feet: around the cloud, one ground cell (1 m = 3.3 ft) of slack
        assert b.left <= xyz[:, 0].min() + 3.3 and b.right >= xyz[:, 0].max() - 3.3
        band = ds.read(1)
        z = band[band != ds.nodata]
        # ground heights in feet, as the cloud's z (not metres: those would be 30 % of it)
        assert z.size and xyz[:, 2].min() - 3.3 <= float(np.median(z)) <= xyz[:, 2].max()
    import sqlite3

    con = sqlite3.connect(tmp_path / "s.gpkg")
    minx, maxx = con.execute("select min_x, max_x from gpkg_contents").fetchone()
    con.close()
    assert minx == pytest.approx(x_ft, abs=1e-3) and maxx == pytest.approx(x_ft, abs=1e-3)


def test_units_contradicting_the_crs_and_up_axis_on_tiles_are_refused(
    tmp_path: Path, datasets_dir: Path
) -> None:
    path, _ = _feet_las(tmp_path, _xyz(datasets_dir))
    res = runner.invoke(app, ["stems", str(path), "-o", str(tmp_path / "s.csv"), "--units", "mm"])
    assert res.exit_code == 2
    assert "contradicts the cloud's CRS" in " ".join(res.output.split())
    res = runner.invoke(
        app,
        ["stems", str(tmp_path), "-o", str(tmp_path / "t.csv"), "--up-axis", "y", "--units",
         "us-ft"],
    )  # fmt: skip
    assert res.exit_code == 2
    assert "filters.transformation" in " ".join(res.output.split())


def test_y_up_single_tree_is_warned_and_the_axis_assumed_is_stated(
    tmp_path: Path, datasets_dir: Path
) -> None:
    """A real single tree (archi Tree_1) written Y up as (x, z, y) gave 2 "stems" and no
    word before Dec 5; now a warning names --up-axis y, and the summary (--json) states the
    up axis the run assumed. Its Z-up original gives no warning."""
    import json

    import laspy

    las = laspy.read(datasets_dir / "archi" / "Tree_1_point_cloud.las")
    xyz = np.column_stack((las.x, las.y, las.z))
    for name, pts, warned in (
        ("zup.xyz", xyz, False),
        ("yup.xyz", xyz[:, [0, 2, 1]], True),
    ):
        path = tmp_path / name
        np.savetxt(path, pts, fmt="%.4f")
        res = runner.invoke(
            app, ["stems", str(path), "-o", str(tmp_path / f"{name}.csv"), "-q", "--json"]
        )
        assert res.exit_code == 0, res.output
        text = " ".join(res.output.split())
        assert ("pass --up-axis y" in text) == warned, text
        payload = json.loads(res.stdout)
        assert payload["up_axis"] == "z" and payload["units"] == "m"


def test_y_up_pine_gives_the_z_up_stems_with_up_axis(tmp_path: Path, datasets_dir: Path) -> None:
    """TreeLS pine (a real tree with its ground) written Y up as (x, z, -y) on the file's own
    LAS grid: `--up-axis y` gives the stems of the Z-up file, bit for bit. Tolerance 0 is
    justified: the file's integers are only swapped and negated (the offsets with them), so
    the turned coordinates equal the original doubles exactly, and the detector does not
    depend on the point order (docs/algorithms/cloud.md, "Point order").

    Without --up-axis the cloud is a tree lying on its side; a horizontal branch (12.4 m up
    the trunk, reaching 1 m toward -y) then stands vertical and can pass as a 7.4 cm stem
    (it does on a 1 mm grid, not on this 0.1 mm one). Whatever it finds, the run warns and
    names --up-axis y (docs/reliability.md, "The up axis of a single tree")."""
    import laspy

    src = datasets_dir / "treels" / "pine.laz"
    las = laspy.read(src)
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = las.header.scales[[0, 2, 1]]
    header.offsets = las.header.offsets[[0, 2, 1]] * [1.0, 1.0, -1.0]
    turned = laspy.LasData(header)
    turned.X, turned.Y, turned.Z = las.X, las.Z, -np.asarray(las.Y)
    path = tmp_path / "pine_yup.las"
    turned.write(str(path))

    z_up, _ = _stems(tmp_path, src)
    y_up, _ = _stems(tmp_path, path, "--up-axis", "y")
    assert len(z_up) == 1 and float(z_up[0]["diameter"]) == pytest.approx(0.255, abs=0.005)
    assert y_up == z_up

    res = runner.invoke(app, ["stems", str(path), "-o", str(tmp_path / "as_read.csv"), "-q"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "like a tree lying on its side" in text and "pass --up-axis y" in text
