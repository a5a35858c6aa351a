"""Victoria Park loader: counts, conventions (tested against the data), bad input."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stemmap.datasets.victoria_park import (
    LASER_TIME_OFFSET_S,
    STEER_OFFSET_RAD,
    dataset_bearing_to_ours,
    estimate_steer_offset,
    load_victoria_park,
    reobservation_consistency,
    victoria_park_model,
)
from stemmap.errors import InputError
from stemmap.slam.base import observation_to_world
from stemmap.slam.motion import preintegrate


@pytest.fixture(scope="module")
def vp(datasets_dir):
    return load_victoria_park(datasets_dir / "victoria_park")


def test_counts_and_time_bases(vp):
    assert len(vp.frames) == 7249  # 7,230 scans with detections + 19 inferred empty scans
    assert vp.frames.n_detections == 52974
    assert len(vp.controls) == 61945
    assert vp.gps_xy.shape == (4466, 2)
    # first scan stamped 0.852 s; the GPS-free latency calibration moves it by -0.055 s
    assert vp.frames.times[0] == pytest.approx(0.852 + LASER_TIME_OFFSET_S)
    raw = load_victoria_park(vp.path, laser_time_offset=0.0)
    assert raw.frames.times[0] == pytest.approx(0.852)
    assert np.all(np.diff(vp.frames.times) > 0.2)  # scan period 0.2135 s
    assert np.all(np.abs(vp.frames.bearings) <= math.pi / 2 + 1e-9)  # 180 deg laser, ahead
    assert vp.skipped == {}


def test_bearing_conversion():
    np.testing.assert_allclose(
        dataset_bearing_to_ours([0.0, math.pi / 2, math.pi]), [-math.pi / 2, 0.0, math.pi / 2]
    )


def _consistency(vp, model, flip=False, lag=5):
    """Median world-frame distance between a tree seen now and the same tree `lag` scans later,
    both placed with dead reckoning: small when the geometry and conventions are right."""
    fr = vp.frames
    pre = preintegrate(model, vp.controls, fr.times)
    bear = -fr.bearings if flip else fr.bearings
    w = observation_to_world(pre.poses[fr.frame_index], fr.ranges, bear, model.sensor_offset)
    d = []
    for f in range(len(fr) - lag):
        A = w[fr.ptr[f] : fr.ptr[f + 1]]
        B = w[fr.ptr[f + lag] : fr.ptr[f + lag + 1]]
        if len(A) and len(B):
            dd, _ = cKDTree(A).query(B)
            d.append(dd[dd < 3.0])
    return float(np.median(np.concatenate(d)))


@pytest.mark.slow
def test_conventions_are_the_ones_the_data_supports(vp):
    part = vp.slice(0.0, 400.0)
    base = victoria_park_model(steer_offset=0.0)
    ours = _consistency(part, base)
    # full run, raw steering, measured: 0.17 m ours vs 0.75 m mirrored bearings, 0.23 m with
    # a = 0.95 m, 0.23 m with the encoder on the right wheel (H < 0), 0.20 m with the laser on
    # the right
    assert ours < 0.25
    assert _consistency(part, base, flip=True) > 2 * ours
    assert _consistency(part, replace(base, a=0.95)) > ours
    assert _consistency(part, replace(base, H=-0.76)) > ours
    assert _consistency(part, replace(base, b=-0.5)) > ours
    # same statistic helper in the library
    assert reobservation_consistency(part, base) == pytest.approx(ours)


@pytest.mark.slow
def test_steering_offset_is_estimated_without_gps(vp):
    part = vp.slice(0.0, 400.0)
    off = estimate_steer_offset(part)
    # full run: 0.0055 rad (grid 0.005-0.006); a 400 s slice agrees within 1.5 mrad
    assert abs(off - STEER_OFFSET_RAD) < 1.5e-3
    raw = reobservation_consistency(part, victoria_park_model(steer_offset=0.0), lag=25)
    cal = reobservation_consistency(part, victoria_park_model(), lag=25)
    assert cal < 0.8 * raw  # measured on the full run: 0.27 m vs 0.69 m at a 5-s lag


def test_slice_and_problem(vp):
    part = vp.slice(100.0, 130.0)
    assert 130 < len(part.frames) < 145  # 30 s / 0.2135 s
    assert part.frames.times[0] >= 100.0 and part.frames.times[-1] <= 130.0
    assert part.controls.times[0] <= 100.0  # hold value before the slice start is kept
    assert np.all((part.gps_times >= 100.0) & (part.gps_times <= 130.0))
    p = part.problem()
    assert p.sensor_offset == (3.78, 0.5)
    with pytest.raises(InputError):
        vp.slice(5000.0, 6000.0)


def _write_copy(src: Path, dst: Path, edit=None) -> None:
    dst.mkdir()
    for name in ("inputs.dat", "measurements.dat", "gps.dat"):
        lines = (src / name).read_text().splitlines()[:400]
        if edit and name in edit:
            lines = edit[name](lines)
        (dst / name).write_text("\n".join(lines) + "\n")


def test_missing_file_is_input_error(tmp_path, datasets_dir):
    with pytest.raises(InputError, match="does not exist"):
        load_victoria_park(tmp_path / "nope")
    _write_copy(datasets_dir / "victoria_park", tmp_path / "vp")
    (tmp_path / "vp" / "gps.dat").unlink()
    with pytest.raises(InputError, match=r"gps\.dat is missing"):
        load_victoria_park(tmp_path / "vp")


def test_truncated_and_backwards_rows_are_skipped_with_warning(tmp_path, datasets_dir, caplog):
    def damage(lines):
        lines = list(lines)
        lines[10] = lines[10].split()[0]  # truncated row
        t = lines[20].split()
        lines[20] = " ".join(["0.0", *t[1:]])  # time going backwards
        return lines

    _write_copy(
        datasets_dir / "victoria_park",
        tmp_path / "vp",
        {"measurements.dat": damage},
    )
    vp = load_victoria_park(tmp_path / "vp", max_bad_fraction=0.05)
    assert vp.skipped["measurements.dat"] == 2
    assert vp.frames.n_detections == 398
    assert "malformed" in caplog.text
    # 2 bad rows of 400 (0.5 %) exceed a 0.1 % budget
    with pytest.raises(InputError, match="more than"):
        load_victoria_park(tmp_path / "vp", max_bad_fraction=0.001)


def test_stemmap_map_cli_writes_every_product(tmp_path, datasets_dir):
    import json

    from typer.testing import CliRunner

    from stemmap.cli import app

    out = tmp_path / "out"
    res = CliRunner().invoke(
        app,
        [
            "map",
            "--dataset",
            "victoria-park",
            "--data",
            str(datasets_dir / "victoria_park"),
            "--t-end",
            "40",
            "--backend",
            "isam2",
            "--out",
            str(out),
            "--no-progress",
        ],
    )
    assert res.exit_code == 0, res.output
    for name in ("trees.csv", "trees.geojson", "trajectory.csv", "metrics.json", "map.png"):
        assert (out / name).stat().st_size > 100, name
    header = (out / "trees.csv").read_text().splitlines()[0].split(",")
    assert header[:7] == ["id", "x", "y", "diameter", "std_x", "std_y", "n_obs"]
    assert (out / "trajectory.csv").read_text().startswith("time_s,x,y,theta")
    m = json.loads((out / "metrics.json").read_text())
    assert m["n_trees"] > 10 and m["ate_rmse_m"] < 2.0
    assert m["frames"]["sensor_offset_m"][0] == pytest.approx(3.78)  # rear axle -> laser
    # the map in the GPS frame: the alignment moves the laser track onto the GPS fixes
    al = json.loads((out / "gps_alignment.json").read_text())
    from stemmap.eval.trajectory import Se2Alignment

    a = Se2Alignment(al["theta_rad"], tuple(al["t_m"]))
    t_map = np.loadtxt(out / "trees.csv", delimiter=",", skiprows=1, ndmin=2)[:, 1:3]
    t_gps = np.loadtxt(out / "gps_trees.csv", delimiter=",", skiprows=1, ndmin=2)[:, 1:3]
    np.testing.assert_allclose(a.apply(t_map), t_gps, atol=1e-9)
    conf = np.loadtxt(out / "trees.csv", delimiter=",", skiprows=1, ndmin=2)[:, 8]
    assert np.all((conf >= 0) & (conf <= 1))
    # bad input: no source / two sources -> exit code 2 with a message, no traceback
    bad = CliRunner().invoke(app, ["map", "--sim", "--dataset", "victoria-park", "--out", "x"])
    assert bad.exit_code == 2 and "exactly one input" in bad.output


def test_gps_screening_on_the_real_run(vp):
    from stemmap.eval.trajectory import screen_gps
    from stemmap.slam.base import sensor_poses

    pre = preintegrate(vp.model, vp.controls, vp.gps_times)
    sp = sensor_poses(pre.poses, vp.model.sensor_offset)
    s = screen_gps(
        vp.gps_times, vp.gps_xy, sp[:, :2], np.concatenate(([0.0], np.cumsum(pre.distance)))
    )
    # measured: 3,669 of 4,466 fixes kept; the rule must keep most fixes and drop the jumps
    assert 0.75 * s.n_total < s.n_kept < 0.9 * s.n_total
    kept = vp.gps_xy[s.keep]
    step = np.hypot(*np.diff(kept, axis=0).T)
    dt = np.diff(vp.gps_times[s.keep])
    # consecutive kept fixes never imply more than the car's top speed (6.6 m/s) + tolerance
    assert np.all(step <= 6.7 * dt + 0.5 + 0.1 * 6.7 * dt)
