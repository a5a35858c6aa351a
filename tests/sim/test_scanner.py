import math

import numpy as np
import pytest

from stemmap.sim.forest import Stand, random_stand
from stemmap.sim.scanner import ScannerModel, cast_rays, simulate_scan
from stemmap.types import Pose2


def test_ray_hits_circle_at_exact_distance():
    stand = Stand([[5.0, 0.0]], [0.4])
    r, hit = cast_rays(np.zeros(2), np.array([0.0, math.pi / 2]), stand, 30.0)
    assert r[0] == pytest.approx(4.8, abs=1e-12) and hit[0] == 0
    assert math.isinf(r[1]) and hit[1] == -1


def test_nearest_obstacle_occludes_farther_one():
    stand = Stand([[5.0, 0.0], [10.0, 0.0]], [0.4, 0.6], segments=[[3.0, -1.0, 3.0, 1.0]])
    r, hit = cast_rays(np.zeros(2), np.array([0.0]), stand, 30.0)
    assert r[0] == 3.0 and hit[0] == -2


def test_simulated_scan_noise_matches_model():
    stand = Stand([[0.0, 0.0]], [0.5])
    model = ScannerModel(range_noise=0.01, range_max=30.0)
    scan, hit = simulate_scan(stand, Pose2(-10.0, 0.0, 0.0), model, rng=1)
    pts = Pose2(-10.0, 0.0, 0.0).transform_points(scan.points())
    resid = np.hypot(*pts.T) - 0.25
    assert np.sum(hit == 0) == scan.valid.sum() > 3
    assert abs(resid.mean()) < 0.01  # few beams: mean of N(0, 1 cm) within 1 cm
    assert resid.std() < 0.02


def test_random_stand_respects_spacing():
    st = random_stand(40, (30, 30), min_spacing=1.0, rng=3)
    d = np.hypot(*(st.trees_xy[:, None] - st.trees_xy[None]).transpose(2, 0, 1))
    gap = d - (st.radii[:, None] + st.radii[None])
    np.fill_diagonal(gap, np.inf)
    assert gap.min() >= 1.0
