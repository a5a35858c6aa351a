"""Camera frames folders (io/camera_frames.py) and ``stemmap odometry --camera``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.io.camera_frames import (
    calibration_from_dict,
    read_camera_frames,
    write_camera_frames,
)
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.odometry.visual import VisualFrame


def test_stereo_folder_round_trip(tmp_path, drive):
    frames = [VisualFrame(f.time, f.left, f.right) for f in drive.frames[:3]]
    write_camera_frames(tmp_path, frames, drive.stereo, vehicle_from_camera=np.eye(4))
    back = read_camera_frames(tmp_path)
    assert len(back) == 3 and back.calibration == drive.stereo
    np.testing.assert_allclose(back.times, [f.time for f in frames])
    np.testing.assert_array_equal(back.vehicle_from_camera, np.eye(4))
    for a, b in zip(back, frames, strict=True):
        np.testing.assert_array_equal(a.left, b.left)
        np.testing.assert_array_equal(a.right, b.right)


def test_rgbd_folder_round_trip_keeps_depth_to_a_millimetre(tmp_path, drive):
    frames = [VisualFrame(f.time, f.left, depth=f.depth) for f in drive.frames[:2]]
    write_camera_frames(tmp_path, frames, drive.rgbd)
    back = list(read_camera_frames(tmp_path))
    d = back[0].depth  # float metres again
    ref = frames[0].depth
    ok = np.isfinite(ref) & (ref < 65.0)
    assert np.max(np.abs(d[ok] - ref[ok])) <= 0.0005 + 1e-6
    assert np.all(np.isnan(d[~np.isfinite(ref)]))  # sky: no depth


def test_camera_info_dict_gives_the_baseline():
    fx, b = 350.0, 0.12
    info = {
        "width": 672,
        "height": 376,
        "k": [fx, 0, 336, 0, fx, 188, 0, 0, 1],
        "p": [fx, 0, 336, -fx * b, 0, fx, 188, 0, 0, 0, 1, 0],
    }
    cal = calibration_from_dict(info)
    assert cal.fx == fx and cal.cy == 188 and cal.baseline == pytest.approx(b)


def test_folder_errors_name_the_problem(tmp_path, drive):
    with pytest.raises(InputError, match=r"camera\.json"):
        read_camera_frames(tmp_path)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 1}))
    with pytest.raises(InputError, match="width"):
        read_camera_frames(tmp_path)
    frames = [VisualFrame(f.time, f.left, f.right) for f in drive.frames[:2]]
    write_camera_frames(tmp_path, frames, drive.stereo)
    (tmp_path / "right" / "000001.png").unlink()
    with pytest.raises(InputError, match="2 left/rgb images but 1 right"):
        read_camera_frames(tmp_path)


def test_cli_odometry_camera_writes_the_path(tmp_path, drive):
    n = 25
    frames = [VisualFrame(f.time, f.left, f.right) for f in drive.frames[:n]]
    write_camera_frames(
        tmp_path / "frames",
        frames,
        drive.stereo,
        vehicle_from_camera=drive.camera.vehicle_from_camera(),
    )
    out = tmp_path / "traj.csv"
    res = CliRunner().invoke(
        app, ["odometry", "--camera", str(tmp_path / "frames"), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert "stereo frames" in res.output
    traj = read_trajectory_csv(out)
    assert len(traj) == n
    truth = drive.truth_in_start_frame()[:n]
    dist = float(np.sum(np.hypot(*np.diff(truth, axis=0).T)))
    # PNG round trip is lossless: the same 2 % drift bound as the library test
    assert np.hypot(*(traj.poses[-1, :2] - truth[-1])) < 0.02 * dist


def test_cli_odometry_errors(tmp_path):
    res = CliRunner().invoke(app, ["odometry", "--camera", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "error:" in res.output and "nope" in res.output
    res = CliRunner().invoke(app, ["odometry"])
    assert res.exit_code == 2 and "--camera" in res.output


def test_cli_odometry_camera_warns_about_lost_frames(tmp_path, drive):
    """Frames the VO cannot track (here three blank images: no corners) are extrapolated at
    constant velocity; the command says so instead of reporting a path as if it were seen."""
    frames = [VisualFrame(f.time, f.left, f.right) for f in drive.frames[:12]]
    for i in (8, 9, 10):
        blank = np.full_like(frames[i].left, 128)
        frames[i] = VisualFrame(frames[i].time, blank, blank.copy())
    write_camera_frames(tmp_path / "frames", frames, drive.stereo)
    out = tmp_path / "traj.csv"
    res = CliRunner().invoke(
        app, ["odometry", "--camera", str(tmp_path / "frames"), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert "warning: the visual odometry lost" in res.output
    assert "extrapolated at constant velocity" in res.output
    # a drive it tracks throughout gets no warning
    ok = tmp_path / "ok"
    write_camera_frames(
        ok, [VisualFrame(f.time, f.left, f.right) for f in drive.frames[:8]], drive.stereo
    )
    res = CliRunner().invoke(
        app, ["odometry", "--camera", str(ok), "--out", str(tmp_path / "t2.csv")]
    )
    assert res.exit_code == 0, res.output
    assert "warning: the visual odometry lost" not in res.output
