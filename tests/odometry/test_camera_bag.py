"""Camera frames from ROS bags (io/camera_bag.py): Image + CameraInfo topics."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from _ros_bags import BagFactory
from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.io.camera_bag import decode_image, read_camera_bag
from stemmap.odometry.visual import VisualFrame, run_visual_odometry


def _write_bag(path: Path, drive, n: int, *, ros: int = 2, depth: bool = False) -> Path:
    f = BagFactory(ros)
    cal = drive.stereo
    k = [cal.fx, 0, cal.cx, 0, cal.fy, cal.cy, 0, 0, 1]
    second = "/stereo/depth/image" if depth else "/stereo/right/image_rect"
    msgs: list[tuple[str, Any]] = []
    for fr in drive.frames[:n]:
        t = (round(fr.time * 1e9) + 1_000_000_000) * 1e-9
        msgs.append(("/stereo/left/image_rect", f.image(t, fr.left[..., ::-1], "bgr8")))
        if depth:
            mm = np.where(np.isfinite(fr.depth), np.rint(fr.depth * 1000), 0).astype(np.uint16)
            msgs.append((second, f.image(t, mm, "16UC1")))
        else:
            msgs.append((second, f.image(t, fr.right, "rgb8")))
        msgs.append(("/stereo/left/camera_info", f.camera_info(t, k, cal.width, cal.height)))
        tx = -cal.fx * cal.baseline
        msgs.append(("/stereo/right/camera_info", f.camera_info(t, k, cal.width, cal.height, tx)))
    return f.write(path, msgs)


@pytest.mark.parametrize("ros", [1, 2])
def test_stereo_bag_gives_the_same_odometry_as_the_frames(tmp_path, drive, ros):
    n = 12
    bag = _write_bag(tmp_path / ("b.bag" if ros == 1 else "b"), drive, n, ros=ros)
    cb = read_camera_bag(bag)
    assert cb.left_topic == "/stereo/left/image_rect"
    assert cb.right_topic == "/stereo/right/image_rect"
    assert cb.calibration.baseline == pytest.approx(drive.stereo.baseline)
    frames = list(cb)
    assert len(frames) == n
    np.testing.assert_array_equal(frames[3].left, drive.frames[3].left)  # bgr8 -> RGB
    a = run_visual_odometry(frames, cb.calibration)
    ref = run_visual_odometry(
        [VisualFrame(f.time + 1.0, f.left, f.right) for f in drive.frames[:n]], drive.stereo
    )
    # the baseline recovered from P (-P[3] / P[0]) may differ from 0.12 in the last bit, which
    # can flip a RANSAC inlier decision: same path to well under the odometry's own error
    np.testing.assert_allclose(a.poses, ref.poses, atol=1e-3)


def test_rgbd_bag_depth_in_millimetres(tmp_path, drive):
    bag = _write_bag(tmp_path / "d", drive, 3, depth=True)
    cb = read_camera_bag(bag)
    assert cb.depth_topic == "/stereo/depth/image" and not cb.calibration.is_stereo
    f = next(iter(cb))
    ok = np.isfinite(drive.frames[0].depth) & (drive.frames[0].depth < 60)
    assert np.max(np.abs(f.depth[ok] - drive.frames[0].depth[ok])) <= 0.0005 + 1e-6


def test_cli_odometry_reads_a_bag(tmp_path, drive):
    bag = _write_bag(tmp_path / "b", drive, 8)
    out = tmp_path / "t.csv"
    res = CliRunner().invoke(app, ["odometry", "--camera", str(bag), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert len(out.read_text().splitlines()) == 9


def test_decode_image_handles_row_padding_and_rejects_unknown_encodings():
    class Msg:
        encoding, height, width, step, is_bigendian = "mono8", 2, 3, 4, 0
        data = np.array([1, 2, 3, 0, 4, 5, 6, 0], np.uint8)

    np.testing.assert_array_equal(decode_image(Msg()), [[1, 2, 3], [4, 5, 6]])
    Msg.encoding = "yuv422"
    with pytest.raises(InputError, match="yuv422"):
        decode_image(Msg())


def test_bag_without_camera_topics_names_the_topics(tmp_path, drive):
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    batch = ScanBatch(
        np.ones((2, 5)), np.array([0.0, 0.1]), angle_min=0.0, angle_increment=0.1, range_max=10.0
    )
    bag = write_scans_bag(tmp_path / "s", batch, ros=2)
    with pytest.raises(InputError, match="Image topics: none"):
        read_camera_bag(bag)
