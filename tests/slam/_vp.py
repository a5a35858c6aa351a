"""Victoria Park scoring shared by the back-end tests: the benchmark's scorer (GPS fixes
screened by odometry consistency, one SE(2) fit, the laser point; see
benchmarks/slam_victoria_park.py)."""

from __future__ import annotations

import numpy as np

from stemmap.eval.trajectory import ate, screen_gps
from stemmap.slam.base import SlamResult, sensor_poses
from stemmap.slam.motion import preintegrate


def screened_ate(vp, res: SlamResult) -> float:
    """ATE RMSE (m) of ``res`` against the screened GPS of ``vp`` (a ``VictoriaPark``)."""
    m = vp.model
    pre = preintegrate(m, vp.controls, vp.gps_times)
    sp = sensor_poses(pre.poses, m.sensor_offset)
    screen = screen_gps(
        vp.gps_times, vp.gps_xy, sp[:, :2], np.concatenate(([0.0], np.cumsum(pre.distance)))
    )
    r = ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=m.sensor_offset, keep=screen.keep)
    assert r, r
    return float(r.rmse)
