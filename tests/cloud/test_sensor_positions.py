"""Sensor positions for cloud files (stemmap.cloud.sensor, detect_stems_file(sensor=),
`stemmap stems --origin / --trajectory`): a simulated mobile scan written to LAS with
gps_time and its trajectory written separately must give exactly what detect_stems gives with
the true per-point sensor positions, and reduce the DBH bias of the 3 cm range noise."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from _mobile_files import (
    point_times,
    vehicle_trajectory,
    write_las,
    write_ply,
    write_trajectory,
)
from stemmap.cli import app
from stemmap.cloud.sensor import SensorPositions
from stemmap.cloud.stems import CloudStems, detect_stems, detect_stems_file
from stemmap.errors import ConfigError, InputError
from stemmap.eval.matching import match_points
from stemmap.io.clouds import read_cloud
from stemmap.sim.lidar import (
    MobileScan,
    Stand3D,
    lidar_preset,
    random_stand3d,
    simulate_mobile,
    simulate_tls,
)
from stemmap.types import Trajectory

LEVER = (1.2, -0.3)  # scanner 1.2 m ahead of and 0.3 m right of the trajectory's point


@pytest.fixture(scope="module")
def mobile(tmp_path_factory: pytest.TempPathFactory) -> tuple[Stand3D, MobileScan, Path, Path]:
    """The mobile scene of test_stems.py (VLP-16, 3 cm noise, 25 revolutions), as files."""
    stand = random_stand3d(10, (14.0, 14.0), dbh_min=0.12, n_shrubs=4, rng=3)
    path = np.column_stack((np.linspace(0.5, 13.5, 25), np.full(25, 7.0)))
    mob = simulate_mobile(stand, path, lidar_preset("vlp16"), rng=1, keep_frames=False)
    d = tmp_path_factory.mktemp("mobile")
    las = d / "drive.las"
    write_las(las, mob.cloud.xyz, point_times(mob))
    traj = d / "path.csv"
    write_trajectory(traj, vehicle_trajectory(mob, LEVER))
    return stand, mob, las, traj


def _bias(det: CloudStems, stand: Stand3D) -> float:
    m = match_points(det.xy, stand.trees_xy, 0.5)
    return float(np.mean(det.diameter[m.pairs[:, 0]] - stand.dbh[m.pairs[:, 1]]))


def _true_origins(mob: MobileScan) -> np.ndarray:
    return mob.poses[mob.cloud.fields["frame_index"], :2]


def test_trajectory_origins_are_the_scanner_positions(
    mobile: tuple[Stand3D, MobileScan, Path, Path],
) -> None:
    """Interpolated between every other revolution and moved by the lever arm, the sensor
    position of each point is the simulator's scanner position (straight path at constant
    speed: linear interpolation is exact up to rounding)."""
    _, mob, _, traj = mobile
    from stemmap.io.trajectory import read_trajectory_csv

    sp = SensorPositions(trajectory=read_trajectory_csv(traj), sensor_offset=LEVER)
    got = sp.origins(len(mob.cloud), point_times(mob), "test")
    np.testing.assert_allclose(got, _true_origins(mob), atol=1e-9)


def test_file_with_trajectory_equals_in_memory_with_true_origins(
    mobile: tuple[Stand3D, MobileScan, Path, Path],
) -> None:
    """Streaming in several chunks with origins from the trajectory gives the stems that
    detect_stems gives on the same (1 mm quantised) points with the true origins; and the
    DBH bias shrinks against the run without sensor positions (-0.5 .. -1 cm -> ~0)."""
    stand, mob, las, traj = mobile
    from stemmap.io.trajectory import read_trajectory_csv

    sp = SensorPositions(trajectory=read_trajectory_csv(traj), sensor_offset=LEVER)
    streamed = detect_stems_file(las, chunk_size=100_000, sensor=sp)
    xyz = read_cloud(las).xyz
    ref = detect_stems(xyz, origins=np.column_stack((_true_origins(mob), np.zeros(len(xyz)))))
    assert len(streamed) == len(ref) > 0
    np.testing.assert_allclose(streamed.xy, ref.xy, atol=1e-6)
    np.testing.assert_allclose(streamed.diameter, ref.diameter, atol=1e-6)
    plain = detect_stems_file(las, chunk_size=100_000)
    assert abs(_bias(streamed, stand)) < abs(_bias(plain, stand))
    assert _bias(plain, stand) < -0.002  # the range-noise bias is there without the rays


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_cli_trajectory(mobile: tuple[Stand3D, MobileScan, Path, Path], tmp_path: Path) -> None:
    """`stemmap stems drive.las --trajectory path.csv --sensor-offset 1.2,-0.3` writes what
    detect_stems_file writes with those sensor positions."""
    _, _, las, traj = mobile
    out = tmp_path / "s.csv"
    res = CliRunner().invoke(
        app,
        [
            *("stems", str(las), "--out", str(out), "--trajectory", str(traj)),
            *("--sensor-offset", f"{LEVER[0]},{LEVER[1]}", "--read-points", "150000"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "along-ray fits" in res.output
    from stemmap.io.trajectory import read_trajectory_csv

    sp = SensorPositions(trajectory=read_trajectory_csv(traj), sensor_offset=LEVER)
    det = detect_stems_file(las, sensor=sp)
    rows = _csv_rows(out)
    assert len(rows) == len(det)
    # the CSV holds diameters to 0.1 mm
    np.testing.assert_allclose([float(r["diameter"]) for r in rows], det.diameter, atol=5.01e-5)


def test_time_offset_and_tum_and_ply_time_field(
    mobile: tuple[Stand3D, MobileScan, Path, Path], tmp_path: Path
) -> None:
    """A PLY with a double 'time' property on another time base, a TUM trajectory, and
    time_offset bringing the two together: same stems as the LAS + CSV run. Without the
    offset the times do not overlap and the error says so."""
    _, mob, las, traj = mobile
    ply = tmp_path / "drive.ply"
    write_ply(ply, read_cloud(las).xyz, point_times(mob) - 1e6)
    tum = tmp_path / "path.tum"
    write_trajectory(tum, vehicle_trajectory(mob, LEVER))
    from stemmap.io.trajectory import read_trajectory_csv, read_trajectory_tum

    ref = detect_stems_file(
        las, sensor=SensorPositions(trajectory=read_trajectory_csv(traj), sensor_offset=LEVER)
    )
    tr = read_trajectory_tum(tum)
    det = detect_stems_file(
        ply, sensor=SensorPositions(trajectory=tr, sensor_offset=LEVER, time_offset=1e6)
    )
    np.testing.assert_allclose(det.diameter, ref.diameter, atol=1e-6)
    with pytest.raises(InputError, match=r"outside the trajectory.*--time-offset"):
        detect_stems_file(ply, sensor=SensorPositions(trajectory=tr, sensor_offset=LEVER))


def test_cli_origin_single_station(tmp_path: Path) -> None:
    """A terrestrial scan as PLY with --origin: the stems of detect_stems(origins=station)."""
    stand = random_stand3d(6, (12.0, 12.0), dbh_min=0.12, n_shrubs=0, rng=5)
    station = np.array([6.0, 6.0])
    cloud = simulate_tls(stand, [station], lidar_preset("tls_coarse"), rng=2)
    ply = tmp_path / "tls.ply"
    write_ply(ply, cloud.xyz)
    out = tmp_path / "s.csv"
    res = CliRunner().invoke(app, ["stems", str(ply), "--out", str(out), "--origin", "6,6,1.5"])
    assert res.exit_code == 0, res.output
    ref = detect_stems(cloud.xyz, origins=np.array([6.0, 6.0, 1.5]))
    rows = _csv_rows(out)
    assert len(rows) == len(ref) > 0
    np.testing.assert_allclose([float(r["diameter"]) for r in rows], ref.diameter, atol=5.01e-5)


@pytest.fixture
def small_las(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A small random cloud with gps_time 0..10 s, the same without times, a trajectory."""
    rng = np.random.default_rng(0)
    xyz = rng.uniform([0, 0, 0], [10, 10, 3], (3000, 3))
    t = np.linspace(0.0, 10.0, 3000)
    a, b = tmp_path / "t.las", tmp_path / "no_time.las"
    write_las(a, xyz, t)
    write_las(b, xyz)
    traj = tmp_path / "p.csv"
    write_trajectory(traj, Trajectory(np.array([0.0, 5.0, 10.0]), np.zeros((3, 3))))
    return a, b, traj


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--origin", "1,2", "--trajectory", "{traj}"], "not both"),
        (["--time-offset", "5"], "only apply with --trajectory"),
        (["--sensor-offset", "1,0", "--time-field", "t"], "--time-field, --sensor-offset only"),
        (["--origin", "1,2,3,4"], "--origin must be 'X,Y' or 'X,Y,Z'"),
        (["--origin", "1,nan"], "--origin must be"),
        (["--trajectory", "{traj}", "--sensor-offset", "1"], "--sensor-offset must be 'A,B'"),
        (["--origin", "1,2", "--preset", "munjer2025"], "only by preset 'ours'; munjer2025"),
        (["--origin", "1,2", "--preset", "ours_kasa"], "Kasa fit"),
        (["--trajectory", "{traj}", "--time-field", "stamp"], "no per-point time field 'stamp'"),
        (["--trajectory", "{traj}", "--time-offset", "100"], "outside the trajectory"),
        (["--trajectory", "{nope}"], "does not exist"),
    ],
)
def test_cli_sensor_option_errors(
    small_las: tuple[Path, Path, Path], tmp_path: Path, args: list[str], match: str
) -> None:
    las, _, traj = small_las
    argv = [a.format(traj=traj, nope=tmp_path / "nope.csv") for a in args]
    res = CliRunner().invoke(app, ["stems", str(las), "--out", str(tmp_path / "o.csv"), *argv])
    assert res.exit_code == 2, res.output
    assert match in " ".join(res.output.split())
    assert not (tmp_path / "o.csv").exists()


def test_las_without_gps_time(small_las: tuple[Path, Path, Path]) -> None:
    _, no_time, traj = small_las
    from stemmap.io.trajectory import read_trajectory_csv

    sp = SensorPositions(trajectory=read_trajectory_csv(traj))
    with pytest.raises(InputError, match=r"no_time\.las.*no per-point time.*gps_time"):
        detect_stems_file(no_time, sensor=sp)


def test_sensor_positions_validation() -> None:
    tr = Trajectory(np.array([0.0, 1.0, 2.0]), np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]))
    with pytest.raises(ConfigError, match="exactly one"):
        SensorPositions()
    with pytest.raises(ConfigError, match="exactly one"):
        SensorPositions(station=(0.0, 0.0), trajectory=tr)
    with pytest.raises(ConfigError, match="2 or 3 finite"):
        SensorPositions(station=(0.0,))
    with pytest.raises(InputError, match="at least 2 poses"):
        SensorPositions(trajectory=Trajectory(np.array([0.0]), np.zeros((1, 3))))
    with pytest.raises(ConfigError, match="max_gap"):
        SensorPositions(trajectory=tr, max_gap=-1.0)
    st = SensorPositions(station=(3.0, 4.0, 1.0))
    np.testing.assert_array_equal(st.origins(2, None, "x"), [[3, 4], [3, 4]])
    assert not st.needs_time
    sp = SensorPositions(trajectory=tr, sensor_offset=(0.5, 0.0))
    # the default gap is one median step (1 s): 2.9 s is fine (end pose), 3.1 s is not
    np.testing.assert_allclose(
        sp.origins(3, np.array([0.25, 2.9, -0.5]), "x")[:, 0], [0.75, 2.5, 0.5]
    )
    with pytest.raises(InputError, match="1 of 1 points"):
        sp.origins(1, np.array([3.1]), "x")
    with pytest.raises(InputError, match="NaN"):
        sp.origins(1, np.array([np.nan]), "x")
    assert sp.pick_time_field(["x", "time", "gps_time"], "f") == "gps_time"
    assert sp.pick_time_field(["x", "timestamp"], "f") == "timestamp"
    with pytest.raises(InputError, match="its fields: x, y"):
        sp.pick_time_field(["x", "y"], "f")


def test_in_memory_origins_with_the_kasa_fit_are_refused() -> None:
    """The Kasa fit has no along-ray refinement: origins would be silently unused."""
    from stemmap.cloud.stems import PRESETS

    xyz = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(ConfigError, match="only by the geometric fit"):
        detect_stems(xyz, PRESETS["ours_kasa"], origins=np.zeros(3))
