"""``stemmap map SCANS --motion visual|fused --camera FOLDER``: the real visual odometry (not a
trajectory CSV) wired into the mapper, on the rendered S-curve drive of conftest.py (50 stereo
frames at 10 Hz, 5 m) and 2D scans simulated from the same poses through the same rows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.camera_frames import write_camera_frames
from stemmap.io.scans import write_scans_npz
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.odometry.visual import VisualFrame
from stemmap.sim.forest import row_stand
from stemmap.sim.scanner import simulate_scans

runner = CliRunner()


def _log(tmp_path: Path, drive) -> tuple[Path, Path]:
    cam = tmp_path / "frames"
    frames = [VisualFrame(f.time, f.left, f.right) for f in drive.frames]
    write_camera_frames(
        cam, frames, drive.stereo, vehicle_from_camera=drive.camera.vehicle_from_camera()
    )
    stand = row_stand(3, 10, row_spacing=4.0, tree_spacing=3.0, rng=1)  # conftest's stand
    batch, _, _ = simulate_scans(stand, drive.truth.poses, "sick_lms", times=drive.truth.times,
                                 rng=0)  # fmt: skip
    scans = tmp_path / "scans.npz"
    write_scans_npz(scans, batch)
    return scans, cam


def test_visual_and_fused_motion_from_a_camera_folder(tmp_path: Path, drive) -> None:
    """Measured: the visual path ends 0.0036 m and the fused path 0.0035 m from the true end of
    the 5 m drive. Bound 0.05 m = 1 % of the distance (half issue 16's VO drift target): a
    wrong camera mount or time base puts the end metres off, a lost scale a few percent."""
    scans, cam = _log(tmp_path, drive)
    truth = drive.truth_in_start_frame()
    for motion in ("visual", "fused"):
        out = tmp_path / motion
        args = ["--motion", motion, "--camera", str(cam), "--backend", "treedb"]
        res = runner.invoke(app, ["map", str(scans), *args, "--out", str(out), "--no-progress"])
        assert res.exit_code == 0, res.output
        m = json.loads((out / "metrics.json").read_text())["motion"]
        assert m["source"] == motion
        assert m["visual"]["frames"] == 50 and m["visual"]["lost_frames"] == 0
        est = read_trajectory_csv(out / "trajectory.csv")
        end = np.hypot(*(est.poses[-1, :2] - truth[-1]))
        assert end < 0.05, (motion, end)


def test_odometry_command_fuses_lidar_frames_with_a_camera(tmp_path: Path, drive) -> None:
    """``stemmap odometry SCANS --camera FOLDER``: the same EKF as ``map --motion fused``; one
    pose per scan, ending within 1 % of the distance of the true end (as above)."""
    scans, cam = _log(tmp_path, drive)
    out = tmp_path / "traj.csv"
    res = runner.invoke(app, ["odometry", str(scans), "--camera", str(cam), "--out", str(out)])
    assert res.exit_code == 0, res.output
    # the summary (sentences since main's 7b982b7, no longer the dict's keys) names the camera
    # and the EKF's visual odometry measurements; the visual-vs-lidar disagreement over 10 m
    # is not printed for this 4.9 m run
    assert "camera (stereo): 50 frames" in res.output
    assert "visual odometry" in res.output
    est = read_trajectory_csv(out)
    assert len(est) == 50
    end = np.hypot(*(est.poses[-1, :2] - drive.truth_in_start_frame()[-1]))
    assert end < 0.05, end
