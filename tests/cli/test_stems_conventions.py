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
    res = runner.invoke(
        app,
        ["stems", str(path), "-o", str(tmp_path / "g.csv"), "--units", "us-ft", "--geojson",
         str(tmp_path / "g.geojson")],
    )  # fmt: skip
    assert res.exit_code == 2 and "--geojson" in res.output
