"""Laser-camera calibration on simulated rigs with known extrinsics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.sim.camera import simulate_plate_views, xue2018_rig
from stemmap.vision.calibrate import (
    HOMOGRAPHY_METHODS,
    fit_homography,
    fit_homography_dlt,
    fit_homography_ransac,
    fit_homography_xue2018,
    plate_edges_from_scan,
    reprojection_errors,
    solve_plate_points,
    solve_pnp,
)
from stemmap.vision.camera import (
    CameraModel,
    RigidTransform,
    apply_homography,
    laser_plane_homography,
    project_laser_points,
    project_points,
)

RIG = xue2018_rig()
G_TRUE = laser_plane_homography(RIG.camera, RIG.laser_to_camera)


def _laser_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """Random laser-plane points in front of the rig that fall inside the image."""
    out = []
    while len(out) < n:
        r = rng.uniform(1.5, 7.0)
        a = rng.uniform(-0.5, 0.5)
        p = np.array([r * math.cos(a), r * math.sin(a)])
        uv, front = project_laser_points(p, RIG.camera, RIG.laser_to_camera)
        if front[0] and RIG.camera.in_image(uv)[0]:
            out.append(p)
    return np.asarray(out)


def _held_out_error(G: np.ndarray, rng: np.random.Generator) -> float:
    xy = _laser_points(200, rng)
    return float(np.sqrt(np.mean(reprojection_errors(G, xy, apply_homography(G_TRUE, xy)) ** 2)))


def test_true_g_matches_projection() -> None:
    rng = np.random.default_rng(0)
    xy = _laser_points(50, rng)
    uv, _ = project_laser_points(xy, RIG.camera, RIG.laser_to_camera)
    np.testing.assert_allclose(apply_homography(G_TRUE, xy), uv, atol=1e-8)


@pytest.mark.parametrize("method", HOMOGRAPHY_METHODS)
def test_noise_free_recovery(method: str) -> None:
    rng = np.random.default_rng(1)
    xy = _laser_points(14, rng)  # Xue §3.1 used 14 pairs
    fit = fit_homography(xy, apply_homography(G_TRUE, xy), method)
    assert fit, fit.reason
    np.testing.assert_allclose(fit.G, G_TRUE, rtol=1e-6, atol=1e-9)
    assert fit.rms_px < 1e-6


def test_noise_and_point_count() -> None:
    """1 px image noise + 5 mm laser noise: held-out pixel error shrinks with more points, and
    the normalised DLT + LM stays comparable with the paper's g11 = 1 least squares."""
    rng = np.random.default_rng(2)
    errs: dict[tuple[str, int], list[float]] = {}
    for trial in range(8):
        for n in (7, 14, 56):
            xy = _laser_points(n, rng)
            uv = apply_homography(G_TRUE, xy) + rng.normal(0, 1.0, (n, 2))
            xy_m = xy + rng.normal(0, 0.005, xy.shape)
            for method in ("xue2018", "dlt_refined"):
                fit = fit_homography(xy_m, uv, method)
                assert fit, (trial, n, method, fit.reason)
                errs.setdefault((method, n), []).append(_held_out_error(fit.G, rng))
    med = {k: float(np.median(v)) for k, v in errs.items()}
    for method in ("xue2018", "dlt_refined"):
        assert med[(method, 56)] < med[(method, 7)]
        # With 56 pairs, 1 px noise and 5 mm laser noise (~1-2 px at 2-7 m), the model error
        # must be well under the per-point noise: < 1.5 px.
        assert med[(method, 56)] < 1.5
    # Both estimators are comparable here (the laser noise, not the conditioning, dominates):
    # benchmarks/vision_fusion.py records the numbers.
    assert med[("dlt_refined", 14)] < 2.0 * med[("xue2018", 14)]


def test_ransac_rejects_outliers() -> None:
    rng = np.random.default_rng(3)
    xy = _laser_points(40, rng)
    uv = apply_homography(G_TRUE, xy) + rng.normal(0, 0.5, (40, 2))
    bad = rng.choice(40, 12, replace=False)  # 30 % gross outliers
    uv[bad] += rng.uniform(40, 200, (12, 2)) * rng.choice([-1, 1], (12, 2))
    plain = fit_homography_dlt(xy, uv, refine=True)
    robust = fit_homography_ransac(xy, uv, threshold_px=3.0, rng=0)
    assert robust
    assert set(np.flatnonzero(~robust.inliers)) == set(bad)
    assert _held_out_error(robust.G, rng) < 1.0  # 0.5 px noise on 28 inliers
    assert _held_out_error(plain.G, rng) > 5.0


def test_plate_points_exact_and_pipeline() -> None:
    views = simulate_plate_views(RIG, 7, rng=4)
    edge_err = []
    for v in views:
        # Exact lengths -> exact plate coordinates (eqs. 4-6).
        lab = float(np.linalg.norm(v.abc_laser[0] - v.abc_laser[1]))
        lbc = float(np.linalg.norm(v.abc_laser[1] - v.abc_laser[2]))
        pp = solve_plate_points(lab, lbc)
        assert pp, pp.reason
        assert pp.residual < 1e-9  # eqs. 4-5 satisfied exactly
        # Eqs. 4-6 can have two roots close together (the plate is ill-conditioned, see
        # docs/algorithms/vision-fusion.md): A and B agree to 0.02 plate units (4 mm).
        np.testing.assert_allclose(pp.as_array()[:2], v.abc_plate[:2], atol=0.02)
        abc, ok, reason = plate_edges_from_scan(v.scan.points())
        assert ok, reason
        edge_err.append(np.linalg.norm(abc - v.abc_laser, axis=1))
    # Edges are found between beams 0.25 deg apart (~1.5 cm at 3.5 m): within 1.5 cm.
    assert np.max(edge_err) < 0.015


def test_pnp_recovers_extrinsics() -> None:
    rng = np.random.default_rng(5)
    # 3D points: laser plane points plus points on vertical structures (z != 0).
    xy = _laser_points(30, rng)
    P = np.column_stack((xy, rng.uniform(-0.5, 1.0, 30)))
    uv, _ = project_points(RIG.laser_to_camera.apply(P), RIG.camera)
    keep = RIG.camera.in_image(uv)
    P, uv = P[keep], uv[keep] + rng.normal(0, 0.5, (int(keep.sum()), 2))
    fit = solve_pnp(P, uv, RIG.camera)
    assert fit, fit.reason
    assert fit.transform is not None
    # 0.5 px noise on ~25 points at 1.5-7 m: rotation within 0.3 deg, translation within 3 cm.
    assert math.degrees(fit.transform.rotation_angle_to(RIG.laser_to_camera)) < 0.3
    assert np.linalg.norm(fit.transform.t - RIG.laser_to_camera.t) < 0.03
    assert fit.rms_px < 1.0
    # Coplanar laser points only (z = 0) with RANSAC and one gross outlier.
    P2 = np.column_stack((xy, np.zeros(30)))
    uv2, _ = project_points(RIG.laser_to_camera.apply(P2), RIG.camera)
    uv2[0] += 80.0
    fit2 = solve_pnp(P2, uv2, RIG.camera, ransac=True)
    assert fit2 and not fit2.inliers[0]
    assert fit2.transform is not None
    assert math.degrees(fit2.transform.rotation_angle_to(RIG.laser_to_camera)) < 0.1


def test_failures_are_falsy_with_reason() -> None:
    xy = np.column_stack((np.linspace(1, 3, 6), np.zeros(6)))  # collinear
    uv = np.column_stack((np.linspace(0, 100, 6), np.linspace(0, 50, 6)))
    for method in HOMOGRAPHY_METHODS:
        fit = fit_homography(xy, uv, method)
        assert not fit and "collinear" in fit.reason
    four = np.array([[1.0, 0.0], [1.0, 1.0], [2.0, 0.0], [3.0, 2.0]])
    few = fit_homography_xue2018(four, uv[:4])
    assert not few and "5" in few.reason
    assert not solve_plate_points(5.0, 5.0)  # longer than the notch
    assert not solve_pnp(np.zeros((3, 3)), np.zeros((3, 2)), RIG.camera)


def test_bad_inputs() -> None:
    with pytest.raises(InputError, match="shape"):
        fit_homography_dlt(np.zeros((5, 3)), np.zeros((5, 2)))
    with pytest.raises(InputError, match="NaN"):
        fit_homography_dlt(np.full((5, 2), np.nan), np.zeros((5, 2)))
    with pytest.raises(ConfigError, match="method"):
        fit_homography(np.zeros((5, 2)), np.zeros((5, 2)), "magic")
    with pytest.raises(InputError, match="positive"):
        solve_plate_points(-1.0, 0.1)
    with pytest.raises(InputError, match="proper rotation"):
        RigidTransform(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(InputError, match="K must"):
        CameraModel(np.eye(2), 10, 10)
    with pytest.raises(InputError, match="plate scan"):
        plate_edges_from_scan(np.zeros((3, 2)))


@settings(max_examples=25, deadline=None)
@given(
    st.floats(-0.3, 0.3),  # yaw of the camera, rad
    st.floats(0.0, 0.5),  # pitch down, rad
    st.floats(0.1, 0.6),  # height above the laser, m
    st.integers(0, 2**31 - 1),
)
def test_dlt_recovers_random_rigs(yaw: float, pitch: float, height: float, seed: int) -> None:
    """Property: for any rig looking forward, noise-free pairs give G up to scale and ~0 px."""
    from stemmap.sim.camera import xue2018_rig as rig_of

    rig = rig_of(
        tilt_deg=math.degrees(pitch), yaw_deg=math.degrees(yaw), camera_offset=(0.0, 0.0, height)
    )
    G = laser_plane_homography(rig.camera, rig.laser_to_camera)
    rng = np.random.default_rng(seed)
    xy = np.column_stack((rng.uniform(2.0, 8.0, 12), rng.uniform(-2.0, 2.0, 12)))
    uv, front = project_laser_points(xy, rig.camera, rig.laser_to_camera)
    assume(front.all())
    fit = fit_homography_dlt(xy, uv, refine=True)
    assert fit
    assert fit.rms_px < 1e-6
    Gn = fit.G / np.linalg.norm(fit.G) * np.sign(fit.G[0, 0] * G[0, 0])
    np.testing.assert_allclose(Gn, G / np.linalg.norm(G), atol=1e-7)
