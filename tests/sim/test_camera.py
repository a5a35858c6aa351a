"""Simulated laser + camera rigs, calibration plates and rendered scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.sim.camera import render_scene, simulate_plate_views, xue2018_rig
from stemmap.sim.forest import Stand
from stemmap.types import Pose2
from stemmap.vision.camera import project_points

RIG = xue2018_rig(width=640, height=360)


def test_rig_geometry() -> None:
    c = RIG.camera_position
    np.testing.assert_allclose(c, [0.0, 0.0, 0.3], atol=1e-12)
    # A point straight ahead, 15 deg below the camera, lands on the principal point.
    p = np.array([[5.0, 0.0, 0.3 - 5.0 * math.tan(math.radians(15.0))]])
    uv, front = project_points(RIG.laser_to_camera.apply(p), RIG.camera)
    assert front[0]
    np.testing.assert_allclose(uv[0], [RIG.camera.cx, RIG.camera.cy], atol=1e-9)


def test_plate_views_are_consistent() -> None:
    views = simulate_plate_views(RIG, 4, rng=0)
    assert len(views) == 4
    for v in views:
        # A, B, C lie on the laser plane (z = 0) and inside the image.
        P = v.plate_to_laser3d(v.abc_plate, 0.2)
        np.testing.assert_allclose(P[:, 2], 0.0, atol=1e-12)
        np.testing.assert_allclose(P[:, :2], v.abc_laser, atol=1e-12)
        assert np.all(RIG.camera.in_image(v.abc_uv))
        assert np.isfinite(v.scan.ranges).sum() > 10


def test_render_scene_truth() -> None:
    xy = np.array([[4.0, 0.5], [7.0, -1.5]])
    d = np.array([0.3, 0.25])
    stand = Stand(xy, d, clutter_xy=[[5.0, 2.5]], clutter_radius=[0.4])
    sc = render_scene(stand, Pose2(0, 0, 0), RIG, pixel_noise=0.0, rng=0)
    assert sc.image.shape == (360, 640, 3) and sc.image.dtype == np.uint8
    assert sc.truth.tree_visible.all()
    # Band width of tree 0 at its laser-plane row equals the projected diameter within 2 px.
    expected = RIG.camera.fx * 2 * math.asin(0.15 / math.hypot(4.0, 0.5))
    rows = sc.truth.label == 0
    widths = rows.sum(axis=1)
    assert abs(np.median(widths[widths > 0]) - expected) < 2.0
    # Depth on the trunk equals the z-depth of the trunk surface (camera frame).
    ys, xs = np.nonzero(rows)
    zd = sc.depth[ys, xs]
    assert np.all((zd > 3.5) & (zd < 4.4))
    # The laser hits both trees and the bush.
    assert {0, 1, -2} <= set(np.unique(sc.truth.hit_id).tolist())
    assert (sc.truth.label == -2).any()


def test_bad_options() -> None:
    with pytest.raises(ConfigError):
        render_scene(
            Stand(np.zeros((0, 2)), np.zeros(0), [[3.0, 0.0]], [0.3]),
            Pose2(0, 0, 0),
            RIG,
            mimic_mask=[True, False],
        )
