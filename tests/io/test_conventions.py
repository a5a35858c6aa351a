"""Other tools' conventions at the readers: units, up axis, scan CSV intensity columns,
ranges in millimetres, start angles in degrees (docs/reliability.md, "Input conventions")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.io.clouds import read_cloud
from stemmap.io.conventions import CloudConvention, check_scan_ranges, crs_unit, unit_for_factor
from stemmap.io.scans import read_scans, write_scans_npz
from stemmap.types import ScanBatch


def test_y_up_cloud_turns_back_to_z_up(rng: np.random.Generator) -> None:
    xyz = rng.normal(size=(50, 3))
    y_up = np.column_stack((xyz[:, 0], xyz[:, 2], -xyz[:, 1]))  # what a Y-up exporter writes
    assert np.allclose(CloudConvention(up_axis="y").apply(y_up), xyz)
    x_up = np.column_stack((xyz[:, 2], xyz[:, 1], -xyz[:, 0]))
    assert np.allclose(CloudConvention(up_axis="x").apply(x_up), xyz)
    # proper rotations: right-handed frames stay right-handed (determinant +1)
    for axis in ("y", "x"):
        m = CloudConvention(up_axis=axis).apply(np.eye(3))
        assert np.linalg.det(m) == pytest.approx(1.0)


def test_units_scale_to_metres(tmp_path, rng: np.random.Generator) -> None:
    xyz = rng.uniform(0, 10, size=(20, 3))
    path = tmp_path / "mm.xyz"
    np.savetxt(path, xyz * 1000.0, fmt="%.4f")
    assert np.allclose(read_cloud(path, convention=CloudConvention("mm")).xyz, xyz, atol=1e-6)
    feet = CloudConvention("us-ft").apply(xyz / (1200 / 3937))
    assert np.allclose(feet, xyz)
    with pytest.raises(ConfigError, match="--units"):
        CloudConvention("inch")
    with pytest.raises(ConfigError, match="--up-axis"):
        CloudConvention(up_axis="-z")


def test_crs_unit_reads_feet() -> None:
    name, factor = crs_unit("EPSG:2264") or ("", 0.0)  # NC State Plane, US survey feet
    assert "foot" in name.lower() and unit_for_factor(factor) == "us-ft"
    assert crs_unit("EPSG:32633") == ("metre", 1.0)
    assert crs_unit(None) is None


def _scan_csv(path, n: int, header_extra: list[str], extra_values: list[float]) -> None:
    head = "time,angle_min,angle_increment,range_min,range_max," + ",".join(
        [f"r{i}" for i in range(n)] + header_extra
    )
    rows = []
    for k in range(3):
        ranges = [5.0 + 0.01 * i for i in range(n)]
        rows.append(
            ",".join(map(str, [0.1 * k, -0.5, 0.01, 0.0, math.inf, *ranges, *extra_values]))
        )
    path.write_text(head + "\n" + "\n".join(rows) + "\n")


def test_scan_csv_intensity_columns_are_not_beams(tmp_path) -> None:
    # a 100-beam, 57-degree scan exported with its intensities (normalised 0..1): read as
    # ranges they made a 200-beam scan with returns 0.2-0.9 m away behind the field of view
    n = 100
    path = tmp_path / "with_intensity.csv"
    _scan_csv(path, n, [f"i{i}" for i in range(n)], list(np.linspace(0.2, 0.9, n)))
    batch = read_scans(path)
    assert batch.n_beams == n
    assert np.allclose(batch.ranges[0], 5.0 + 0.01 * np.arange(n))


def test_scan_csv_unknown_columns_are_refused(tmp_path) -> None:
    path = tmp_path / "odd.csv"
    _scan_csv(path, 10, ["x", "y"], [1.0, 2.0])
    with pytest.raises(InputError, match="other column"):
        read_scans(path)


def _batch(ranges: np.ndarray, angle_min: float = -1.0) -> ScanBatch:
    return ScanBatch(ranges, np.arange(ranges.shape[0]) * 0.1, angle_min, 0.01)


def test_scan_ranges_in_millimetres_are_refused_then_converted(tmp_path) -> None:
    metres = np.full((2, 50), 7.5)
    metres[:, ::7] = np.nan
    path = tmp_path / "mm.npz"
    write_scans_npz(path, _batch(metres * 1000.0))
    with pytest.raises(InputError, match="--range-unit"):
        read_scans(path)
    got = read_scans(path, range_unit="mm")
    assert np.allclose(got.ranges, metres, equal_nan=True)
    check_scan_ranges(metres, "metres")  # real metres pass


def test_scan_start_angle_in_degrees_is_refused(tmp_path) -> None:
    path = tmp_path / "deg.npz"
    write_scans_npz(path, _batch(np.full((2, 50), 5.0), angle_min=-90.0))
    with pytest.raises(InputError, match="degrees"):
        read_scans(path)


def test_semicolon_text_with_decimal_commas(tmp_path, rng: np.random.Generator) -> None:
    # "X;Y;Z;Intensity" with decimal commas, as spreadsheet / CloudCompare exports write it in
    # many locales (before: "has a malformed line ... could not convert '101,10200'")
    xyz = rng.uniform(-50, 50, size=(30, 3))
    for header in ("X;Y;Z;Intensity\n", ""):
        path = tmp_path / f"comma{len(header)}.csv"
        body = "".join(f"{x:.5f};{y:.5f};{z:.5f};{i}\n" for i, (x, y, z) in enumerate(xyz))
        path.write_text(header + body.replace(".", ","))
        cloud = read_cloud(path)
        assert np.allclose(cloud.xyz, xyz, atol=1e-5)
        assert np.array_equal(cloud.fields["col3"], np.arange(30.0))
