"""``stemmap stems --dtm``: the terrain GeoTIFF opens in GDAL (rasterio) at the right place,
with the CRS, the plane it was sampled from, and nodata where no point fell (issue 14)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from typer.testing import CliRunner

from _mobile_files import write_las
from stemmap.cli import app
from stemmap.cloud.dtm import DTM_NODATA, ground_of_file, write_dtm
from stemmap.errors import InputError

# UTM 33N coordinates: a georeferenced plot, so a wrong CRS or transform is visible
X0, Y0 = 500_000.0, 6_651_000.0


def _slope(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 120.0 + 0.10 * (x - X0) - 0.05 * (y - Y0)


def _plot(rng: np.random.Generator) -> np.ndarray:
    """A 20 x 16 m sloping plot (ground +-1 cm) with a 3 x 3 m hole and two trunks."""
    xy = rng.uniform([X0, Y0], [X0 + 20, Y0 + 16], (60_000, 2))
    # (1 cm margin: the 1 mm LAS grid must not round a point onto the hole's cells)
    lo, hi = np.array([X0 + 13.99, Y0 + 1.99]), np.array([X0 + 17.01, Y0 + 5.01])
    hole = np.all((xy > lo) & (xy < hi), axis=1)
    xy = xy[~hole]
    ground = np.column_stack((xy, _slope(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.01, len(xy))))
    pts = [ground]
    for cx, cy in ((X0 + 5.3, Y0 + 4.6), (X0 + 12.2, Y0 + 11.5)):
        t = rng.uniform(0, 2 * math.pi, 4000)
        h = rng.uniform(0, 8, 4000)
        pts.append(
            np.column_stack(
                (
                    cx + 0.15 * np.cos(t),
                    cy + 0.15 * np.sin(t),
                    _slope(np.full(4000, cx), np.full(4000, cy)) + h,
                )
            )
        )
    return np.vstack(pts)


def test_dtm_geotiff_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    cloud = tmp_path / "plot.las"
    write_las(cloud, _plot(rng))
    dtm = tmp_path / "dtm.tif"
    res = CliRunner().invoke(
        app,
        ["stems", str(cloud), "--out", str(tmp_path / "s.csv"), "--dtm", str(dtm),
         "--crs", "EPSG:32633"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    with rasterio.open(dtm) as r:
        assert r.crs.to_epsg() == 32633
        assert r.res == (1.0, 1.0)
        # the grid covers the plot (1 m cells aligned on multiples of 1 m)
        assert r.bounds.left == pytest.approx(X0) and r.bounds.bottom == pytest.approx(Y0)
        # (a point rounded to the 1 mm LAS grid at x = X0 + 20 opens one more column / row)
        assert X0 + 20 <= r.bounds.right <= X0 + 21 and Y0 + 16 <= r.bounds.top <= Y0 + 17
        band = r.read(1)
        rows, cols = np.indices(band.shape)
        xs, ys = rasterio.transform.xy(r.transform, rows.ravel(), cols.ravel())
        xs, ys = np.asarray(xs).reshape(band.shape), np.asarray(ys).reshape(band.shape)
    measured = band != DTM_NODATA
    # every cell of the hole is empty -> nodata; nothing else is
    in_hole = (xs > X0 + 14) & (xs < X0 + 17) & (ys > Y0 + 2) & (ys < Y0 + 5)
    inside = (xs < X0 + 20) & (ys < Y0 + 16)
    assert np.array_equal(~measured[inside], in_hole[inside])
    # values: the sampled plane at the pixel centre; 2 cm = 2 x the ground noise (the local
    # plane of a 3 x 3 neighbourhood of cell minima sits ~1 sigma below the mean surface)
    m = measured & inside
    err = band[m] - _slope(xs[m], ys[m])
    assert np.max(np.abs(err)) < 0.04
    assert abs(float(np.median(err))) < 0.02


def test_dtm_refused_for_a_cloud_without_ground(tmp_path: Path, rng: np.random.Generator) -> None:
    t = rng.uniform(0, 2 * math.pi, 5000)
    z = rng.uniform(0, 10, 5000)
    cloud = tmp_path / "tree.las"
    write_las(cloud, np.column_stack((0.2 * np.cos(t), 0.2 * np.sin(t), z)))
    with pytest.raises(InputError, match="no ground"):
        ground_of_file(cloud)
    args = ["stems", str(cloud), "--out", str(tmp_path / "s.csv"), "--dtm", str(tmp_path / "d.tif")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code != 0 and "no ground" in res.output
    # all-or-nothing: the stems CSV of the failed run is not left behind either
    assert not (tmp_path / "s.csv").exists() and not (tmp_path / "d.tif").exists()


def test_dtm_without_crs_is_a_local_frame(tmp_path: Path, rng: np.random.Generator) -> None:
    cloud = tmp_path / "plot.las"
    write_las(cloud, _plot(rng))
    out = tmp_path / "dtm.tif"
    write_dtm(out, ground_of_file(cloud), None, frame="plot.las")
    with rasterio.open(out) as r:
        assert r.crs is not None and r.crs.to_epsg() is None
        assert "plot.las" in r.crs.to_wkt() and "LOCAL_CS" in r.crs.to_wkt()


def test_dtm_carries_the_las_header_crs(tmp_path: Path, rng: np.random.Generator) -> None:
    import laspy
    import pyproj

    xyz = _plot(rng)
    header = laspy.LasHeader(point_format=0, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(pyproj.CRS("EPSG:32633"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    cloud = tmp_path / "plot.las"
    las.write(cloud)
    out = tmp_path / "dtm.tif"
    args = ["stems", str(cloud), "--out", str(tmp_path / "s.csv"), "--dtm", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    with rasterio.open(out) as r:
        assert r.crs.to_epsg() == 32633
        assert r.bounds.left == pytest.approx(X0) and r.bounds.bottom == pytest.approx(Y0)
