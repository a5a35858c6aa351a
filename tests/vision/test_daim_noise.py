"""The first-order covariance of a DAIM fit from the depth-noise model
(stemmap.vision._daim_noise): the analytic three-point Jacobian against central differences,
and the Monte Carlo spread of the three-point centre against the propagated covariance."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.scan.circle import fit_circle
from stemmap.vision._daim_noise import (
    arc_point_covariances,
    bound_covariance,
    centre_behind_arc,
    fit_covariance,
    physical_bound,
    surface_centre,
)
from stemmap.vision.depth import arc_width

K = 0.08 / (447.0 * 0.05)  # the D435 model, sigma = k z^2


def _arc(rho: float, radius: float, half_angle: float, n: int) -> np.ndarray:
    """n points on the camera-facing side of a trunk at (rho, 0)."""
    a = np.pi + np.linspace(-half_angle, half_angle, n)
    return np.column_stack((rho + radius * np.cos(a), radius * np.sin(a)))


@pytest.mark.parametrize("method", ["three_point", "kasa"])
def test_fit_covariance_matches_monte_carlo(method: str) -> None:
    """Points moved along their rays by a tenth of the D435's k rho^2 (3 m: 3 mm) and across
    by the pixel quantisation: the spread of 2000 refits matches the propagated sigmas within
    6 %. (At the full 3 cm the three-point circle's errors are heavy-tailed: their sd is
    1.6-2.8x the first order's, their 1.4826 MAD within 18 % of it, measured.)"""
    arc = _arc(3.0, 0.2, 1.2, 9)
    o = np.zeros(2)
    f = fit_circle(arc, method, origin=o)
    kw = {"depth_noise_k": K / 10, "pixel_angle": 2 / 447.0}
    cov = fit_covariance(arc, f.center, o, method, **kw)
    pc = arc_point_covariances(arc, o, **kw)
    rng = np.random.default_rng(0)
    sq = np.linalg.cholesky(pc + 1e-18 * np.eye(2))
    draws = []
    for _ in range(2000):
        p = arc + np.einsum("mij,mj->mi", sq, rng.standard_normal(arc.shape))
        g = fit_circle(p, method, origin=o)
        draws.append([*g.center, g.radius])
    sd = np.asarray(draws).std(axis=0)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), sd, rtol=0.06)


def test_flat_arc_gives_a_large_centre_sigma() -> None:
    """The same trunk seen at 10 m with a narrow arc (the far, flat case): the three-point
    centre's range sigma is many times the point noise (0.36 m), and collinear points give
    NaN."""
    arc = _arc(10.0, 0.15, 0.6, 9)
    f = fit_circle(arc, "three_point", origin=[0, 0])
    cov = fit_covariance(arc, f.center, [0, 0], "three_point", depth_noise_k=K, pixel_angle=0)
    assert np.sqrt(cov[0, 0]) > 3 * K * 100
    line = np.column_stack((np.full(3, 5.0), [-0.1, 0.0, 0.1]))
    bad = fit_covariance(line, [5.0, 0.0], [0, 0], "three_point", depth_noise_k=K, pixel_angle=0)
    assert np.isnan(bad).all()


def test_flat_arc_covariance_is_bounded_by_the_trunk_geometry() -> None:
    """The flat 10 m arc above: its first-order centre sigma is several metres; bounded by
    the centre being the middle arc point plus a radius of at most r_lim along the ray, it is
    at most sqrt(0.35^2 + r_lim^2) along the ray (and below the first order everywhere). A
    well-conditioned near arc is left within 1 %; a degenerate fit gets the bound."""
    o = np.zeros(2)
    arc = _arc(10.0, 0.15, 0.6, 9)
    f = fit_circle(arc, "three_point", origin=o)
    kw = {"depth_noise_k": K, "pixel_angle": 2 / 447.0}
    cov = fit_covariance(arc, f.center, o, "three_point", **kw)
    r_lim = 0.5 * 1.5 * arc_width(arc, o)  # MUNJER2025's width check
    bound = physical_bound(arc, o, r_lim, **kw, keep_cross=cov)
    capped = bound_covariance(cov, bound)
    assert np.sqrt(cov[0, 0]) > 1.0  # metres
    along = np.sqrt(capped[0, 0])
    assert 0.05 < along <= np.sqrt((K * 9.85**2) ** 2 + r_lim**2) + 1e-9
    # Loewner order: below the bound and below the first order
    assert np.linalg.eigvalsh(bound - capped).min() > -1e-12
    assert np.linalg.eigvalsh(cov - capped).min() > -1e-9 * np.abs(cov).max()
    near = _arc(3.0, 0.2, 1.2, 9)
    fn = fit_circle(near, "three_point", origin=o)
    cn = fit_covariance(near, fn.center, o, "three_point", **kw)
    bn = physical_bound(near, o, 0.5 * 1.5 * arc_width(near, o), **kw, keep_cross=cn)
    np.testing.assert_allclose(bound_covariance(cn, bn), cn, rtol=0.01, atol=1e-9)
    # without keep_cross the bound's cross-range part is the middle point's alone, below
    # the fit's (7.6 mm): clipped to 3.6 mm, over-confident
    b0 = physical_bound(near, o, 0.5 * 1.5 * arc_width(near, o), **kw)
    assert bound_covariance(cn, b0)[1, 1] < 0.5 * cn[1, 1]
    np.testing.assert_array_equal(bound_covariance(np.full((3, 3), np.nan), bn), bn)


def test_a_wide_fit_is_placed_one_visible_half_width_behind_its_arc() -> None:
    """A fit failing the width check has no trunk centre: the detection's centre is the
    middle arc point plus half the visible width along its ray -- for a true 0.3 m trunk at
    10 m within half its radius of its centre, where the flat three-point circle's can be metres
    off."""
    o = np.zeros(2)
    arc = _arc(10.0, 0.15, 0.6, 9)
    c = surface_centre(arc, o, 0.5 * arc_width(arc, o))
    # (this arc shows +-0.6 rad of the trunk: 0.17 m of its 0.3 m, so 6.5 cm short)
    assert np.hypot(*(c - [10.0, 0.0])) < 0.5 * 0.15
    assert c[0] > arc[:, 0].min()  # behind the visible surface


def test_centre_behind_arc_rejects_a_circle_on_the_cameras_side() -> None:
    """A trunk shows the camera its convex near side, so its centre lies beyond the arc's
    middle point along the ray; noise that bends the three points the other way (middle
    pushed back, ends pulled in) gives a circle on the camera's side, which is no trunk."""
    o = np.zeros(2)
    arc = _arc(8.0, 0.15, 1.2, 7)
    fit = fit_circle(arc, "three_point", origin=o)
    assert centre_behind_arc(arc, fit.center, o)
    bent = arc.copy()
    bent[3, 0] += 0.4  # the middle point 0.4 m further: the arc now bulges away
    fit = fit_circle(bent, "three_point", origin=o)
    assert fit and 2 * fit.radius < 1.5 * arc_width(bent, o)  # passes the width check
    assert not centre_behind_arc(bent, fit.center, o)
