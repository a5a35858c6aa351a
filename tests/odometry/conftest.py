"""A rendered stereo drive shared by the visual odometry tests (rendering dominates their cost)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from stemmap.odometry.visual import StereoCalibration
from stemmap.sim.forest import row_stand
from stemmap.sim.render import StereoCamera, StereoFrame, render_stereo, stand3d_from_stand
from stemmap.types import Trajectory


@dataclass
class Drive:
    frames: list[StereoFrame]
    truth: Trajectory
    camera: StereoCamera
    stereo: StereoCalibration
    rgbd: StereoCalibration

    def truth_in_start_frame(self) -> np.ndarray:
        """True vehicle xy in the frame of the first vehicle pose (the odometry frame)."""
        p = self.truth.poses
        c, s = np.cos(p[0, 2]), np.sin(p[0, 2])
        d = p[:, :2] - p[0, :2]
        return np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))


def s_curve(n: int, rate_hz: float = 10.0, speed: float = 1.0) -> Trajectory:
    """A gentle S-curve along the aisle y = 2 m of a 3-row orchard (rows at y = 0, 4, 8)."""
    t = np.arange(n) / rate_hz
    x = -2.0 + speed * t
    y = 2.0 + 0.3 * np.sin(x / 4.0)
    th = np.arctan2(0.3 / 4.0 * np.cos(x / 4.0), 1.0)
    return Trajectory(t, np.column_stack((x, y, th)), frame="world")


@pytest.fixture(scope="session")
def drive() -> Drive:
    stand = row_stand(3, 10, row_spacing=4.0, tree_spacing=3.0, rng=1)
    cam = StereoCamera()
    truth = s_curve(50)
    frames = render_stereo(stand3d_from_stand(stand, rng=2), truth, cam, rng=0)
    k = cam.K
    stereo = StereoCalibration(
        cam.fx, cam.fx, k[0, 2], k[1, 2], cam.width, cam.height, baseline=cam.baseline
    )
    rgbd = StereoCalibration(cam.fx, cam.fx, k[0, 2], k[1, 2], cam.width, cam.height)
    return Drive(frames, truth, cam, stereo, rgbd)
