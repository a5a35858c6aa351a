"""Tests of the registered circle fits (kasa, fletcher_reeves, three_point, chord_width, ours)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap import ConfigError, InputError
from stemmap.scan.circle import (
    FIT_METHODS,
    chord_width,
    fit_circle,
    fit_circle_chord_width,
    fit_circle_fletcher_reeves,
    fit_circle_kasa,
    fit_circle_ours,
    fit_circle_three_point,
    fit_circles_batch,
)

ALL = tuple(FIT_METHODS)
#: methods that reproduce any circle exactly from noise-free points on it
EXACT = ("kasa", "fletcher_reeves", "three_point")
DTH = math.radians(0.5)


def visible_arc(
    center: tuple[float, float],
    radius: float,
    *,
    dtheta: float = DTH,
    sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    offset: float | None = None,
) -> np.ndarray:
    """Returns of a scanner at (0, 0) with beams every ``dtheta`` on a circle: exact ray
    casting (first hit), beam phase ``offset`` in [0, dtheta), Gaussian range noise."""
    c = np.asarray(center, dtype=float)
    d = float(np.hypot(*c))
    half = math.asin(radius / d)
    b0 = math.atan2(c[1], c[0])
    if offset is None:
        offset = 0.5 * dtheta if rng is None else float(rng.uniform(0.0, dtheta))
    ang = np.arange(b0 - half + offset, b0 + half, dtheta)
    u = np.column_stack((np.cos(ang), np.sin(ang)))
    b = u @ c
    rng_ = b - np.sqrt(np.maximum(b * b - (c @ c - radius * radius), 0.0))
    if sigma > 0:
        assert rng is not None
        rng_ = rng_ + rng.normal(0.0, sigma, rng_.shape)
    return u * rng_[:, None]


def arc_batch(
    dist: float, n_arcs: int, sigma: float, rng: np.random.Generator, r_range=(0.05, 0.3)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts, ids, radii = [], [], []
    while len(radii) < n_arcs:
        r = rng.uniform(*r_range)
        bearing = rng.uniform(-1.2, 1.2)
        p = visible_arc(
            (dist * math.cos(bearing), dist * math.sin(bearing)), r, sigma=sigma, rng=rng
        )
        if p.shape[0] < 3:
            continue
        pts.append(p)
        ids.append(np.full(p.shape[0], len(radii)))
        radii.append(r)
    return np.vstack(pts), np.concatenate(ids), np.asarray(radii)


# ------------------------------------------------------------------------------------------
# closed-form cases
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", EXACT)
def test_exact_methods_recover_a_noise_free_visible_arc(method: str) -> None:
    p = visible_arc((4.0, 1.0), 0.2)
    fit = fit_circle(p, method)
    assert fit and fit.method == method
    np.testing.assert_allclose(fit.center, [4.0, 1.0], atol=1e-8)
    assert fit.radius == pytest.approx(0.2, abs=1e-8)
    assert fit.rms < 1e-8


def test_ours_recovers_noise_free_arc_with_and_without_silhouette() -> None:
    p = visible_arc((4.0, 1.0), 0.2)
    plain = fit_circle_ours(p, edges=(False, False))
    np.testing.assert_allclose(plain.center, [4.0, 1.0], atol=1e-7)
    assert plain.radius == pytest.approx(0.2, abs=1e-7)
    # With the silhouette term the (noise-free) points dominate: sigma falls to the 0.2 mm
    # floor, so the pull of the beam-quantised silhouette is far below a millimetre.
    sil = fit_circle_ours(p, angle_increment=DTH)
    assert sil.radius == pytest.approx(0.2, abs=5e-4)
    np.testing.assert_allclose(sil.center, [4.0, 1.0], atol=5e-4)


def test_fletcher_reeves_equals_kasa_and_respects_k_max() -> None:
    rng = np.random.default_rng(3)
    p = visible_arc((3.0, -2.0), 0.25, sigma=0.01, rng=rng)
    fr, ka = fit_circle_fletcher_reeves(p), fit_circle_kasa(p)
    np.testing.assert_allclose(fr.center, ka.center, atol=1e-9)
    assert fr.radius == pytest.approx(ka.radius, abs=1e-9)
    # one iteration cannot solve a 3-unknown system: reported as a failure, not a wrong fit
    one = fit_circle_fletcher_reeves(p, k_max=1)
    assert not one and "k_max=1" in one.reason
    with pytest.raises(ConfigError):
        fit_circle_fletcher_reeves(p, k_max=0)


def test_three_point_uses_first_middle_last_by_bearing() -> None:
    # a quarter circle given in shuffled order; a far-off extra point in the middle of the
    # list must not matter because only first/middle/last *by bearing* are used
    t = np.radians([100.0, 90.0, 80.0, 85.0, 95.0])
    p = np.column_stack((np.cos(t), 5.0 + np.sin(t)))  # circle centre (0, 5), r = 1
    p[3] += [0.0, 0.05]  # perturb a point that is neither first, middle nor last
    fit = fit_circle_three_point(p, origin=(0.0, 0.0))
    np.testing.assert_allclose(fit.center, [0.0, 5.0], atol=1e-9)
    assert fit.radius == pytest.approx(1.0, abs=1e-9)


def test_chord_width_is_the_law_of_cosines() -> None:
    # Xue eq. 12 on two beams at 4 m and 5 m, 3 degrees apart
    a, b = np.radians(10.0), np.radians(13.0)
    p = np.array([[4 * math.cos(a), 4 * math.sin(a)], [5 * math.cos(b), 5 * math.sin(b)]])
    w, bis, theta = chord_width(p)
    assert w == pytest.approx(math.sqrt(16 + 25 - 40 * math.cos(np.radians(3.0))), rel=1e-12)
    assert w == pytest.approx(float(np.hypot(*(p[0] - p[1]))), rel=1e-12)
    assert theta == pytest.approx(np.radians(3.0), rel=1e-9)
    assert bis == pytest.approx(np.radians(11.5), rel=1e-9)
    fit = fit_circle_chord_width(p)
    assert fit.diameter == pytest.approx(w, rel=1e-12)


def test_chord_width_underestimates_as_the_paper_reports() -> None:
    # the edge returns lie inside the silhouette, so width < diameter (Xue: 6-16.7 %)
    p = visible_arc((5.0, 0.0), 0.15)
    fit = fit_circle_chord_width(p)
    assert 0.7 * 0.3 < fit.diameter < 0.3
    # centre on the bisecting ray, behind the front surface
    assert fit.center[0] > 5.0 - 0.15


# ------------------------------------------------------------------------------------------
# property tests
# ------------------------------------------------------------------------------------------

circles = st.tuples(
    st.floats(1.0, 20.0),  # distance of the centre from the sensor, m
    st.floats(-math.pi, math.pi),  # bearing of the centre
    st.floats(0.05, 0.6),  # radius, m
)


@settings(max_examples=30, deadline=None)
@given(circles, st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-math.pi, math.pi))
def test_fits_are_translation_and_rotation_equivariant(c, tx, ty, rot) -> None:
    d, bearing, r = c
    rng = np.random.default_rng(0)
    p = visible_arc((d * math.cos(bearing), d * math.sin(bearing)), r, sigma=0.005, rng=rng)
    if p.shape[0] < 3:
        return
    R = np.array([[math.cos(rot), -math.sin(rot)], [math.sin(rot), math.cos(rot)]])
    t = np.array([tx, ty])
    q = p @ R.T + t
    for m in ALL:
        a = fit_circle(p, m, origin=(0.0, 0.0), sigma=0.005, angle_increment=DTH)
        b = fit_circle(q, m, origin=t, sigma=0.005, angle_increment=DTH)
        assert bool(a) == bool(b), m
        if not a:
            continue
        # tolerance: round-off of coordinates up to 1e4 m (~1e-12 relative) amplified by the
        # conditioning of a short arc; 1e-6 m is far below any physical effect
        np.testing.assert_allclose(b.center, R @ a.center + t, atol=1e-6, err_msg=m)
        assert b.radius == pytest.approx(a.radius, abs=1e-6), m


@settings(max_examples=40, deadline=None)
@given(circles)
def test_noise_free_recovery_and_nonnegative_radius(c) -> None:
    d, bearing, r = c
    p = visible_arc((d * math.cos(bearing), d * math.sin(bearing)), r)
    if p.shape[0] < 3:
        return
    truth = np.array([d * math.cos(bearing), d * math.sin(bearing)])
    for m in ALL:
        fit = fit_circle(p, m, angle_increment=DTH)
        if fit:
            assert fit.radius > 0, m
            assert np.all(np.isfinite(fit.center)), m
    for m in EXACT:
        fit = fit_circle(p, m)
        # exact in exact arithmetic; a 3-point 1.5 deg arc at 20 m amplifies round-off ~1e6x
        np.testing.assert_allclose(fit.center, truth, atol=1e-6, err_msg=m)
        assert fit.radius == pytest.approx(r, abs=1e-6), m
    ours = fit_circle_ours(p, edges=(False, False))
    np.testing.assert_allclose(ours.center, truth, atol=1e-6)
    assert ours.radius == pytest.approx(r, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=0, max_size=12).map(
        lambda v: np.array(v, dtype=float).reshape(-1, 2)
    )
)
def test_any_finite_input_gives_a_valid_fit_or_a_reason(p) -> None:
    for m in ALL:
        fit = fit_circle(p, m)
        if fit:
            assert fit.radius > 0 and np.all(np.isfinite(fit.center)), m
        else:
            assert fit.reason and math.isnan(fit.radius), m


# ------------------------------------------------------------------------------------------
# degenerate and bad inputs
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ALL)
def test_degenerate_inputs_fail_with_a_reason(method: str) -> None:
    few = np.array([[1.0, 0.0]])
    assert not fit_circle(few, method)
    assert "point" in fit_circle(few, method).reason
    same = np.full((5, 2), 3.0)
    fit = fit_circle(same, method)
    assert not fit and fit.reason
    line = np.column_stack((np.linspace(2, 3, 6), np.linspace(2, 2.5, 6)))
    fit = fit_circle(line, method, edges=(False, False))
    if method == "chord_width":  # a width needs no curvature
        assert fit
    else:
        assert not fit and fit.reason, method
    # returns all on one beam (a line through the sensor): no bearing spread, no silhouette
    ray = np.column_stack((np.linspace(2, 3, 6), np.linspace(1, 1.5, 6)))
    fit = fit_circle(ray, method)
    assert not fit and fit.reason, method


@pytest.mark.parametrize("method", ALL)
def test_huge_offsets_and_duplicate_points(method: str) -> None:
    p = visible_arc((5.0, 0.0), 0.2)
    off = np.array([6.5e5, 4.3e6])  # UTM-size coordinates
    a = fit_circle(p, method, angle_increment=DTH)
    b = fit_circle(p + off, method, origin=off, angle_increment=DTH)
    # ~1e-9 relative round-off of 4e6 m coordinates, amplified by the short arc
    np.testing.assert_allclose(b.center - off, a.center, atol=2e-4)
    assert b.radius == pytest.approx(a.radius, abs=2e-4)
    dup = np.vstack((p, p[:3]))
    assert fit_circle(dup, method, angle_increment=DTH)


def test_bad_inputs_raise_input_or_config_errors() -> None:
    p = visible_arc((5.0, 0.0), 0.2)
    with pytest.raises(InputError, match=r"\(N, 2\)"):
        fit_circle_ours(np.zeros(6))
    bad = p.copy()
    bad[2, 0] = np.nan
    for m in ALL:
        with pytest.raises(InputError, match="NaN"):
            fit_circle(bad, m)
    with pytest.raises(InputError, match="origin"):
        fit_circle_ours(p, origin=(0.0, np.inf))
    with pytest.raises(InputError, match="sigma"):
        fit_circle_ours(p, sigma=-0.01)
    with pytest.raises(InputError, match="angle_increment"):
        fit_circle_ours(p, angle_increment=0.0)
    with pytest.raises(InputError, match="edges"):
        fit_circle_ours(p, edges=(True, True, False))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="unknown circle fit"):
        fit_circles_batch(p, np.zeros(len(p), dtype=int), "ransac")
    with pytest.raises(InputError, match="segment_ids"):
        fit_circles_batch(p, np.zeros(len(p) - 1, dtype=int))
    with pytest.raises(InputError, match="segment_ids"):
        fit_circles_batch(p, np.zeros(len(p)))  # float ids
    with pytest.raises(InputError, match="sigma"):
        fit_circles_batch(p, np.zeros(len(p), dtype=int), sigma=[0.01, 0.02])
    with pytest.raises(InputError, match="edges"):
        fit_circles_batch(p, np.zeros(len(p), dtype=int), edges=np.ones((3, 2), bool))


# ------------------------------------------------------------------------------------------
# batch API
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ALL)
def test_batch_matches_single_fits_and_accepts_unsorted_ids(method: str) -> None:
    rng = np.random.default_rng(5)
    pts, ids, _ = arc_batch(6.0, 6, 0.01, rng)
    perm = rng.permutation(len(ids))
    # ids shuffled: a stable sort regroups them, keeping each segment's point order
    fits = fit_circles_batch(pts[perm], ids[perm] * 10, method, sigma=0.01, angle_increment=DTH)
    assert fits.segment_ids.tolist() == [0, 10, 20, 30, 40, 50]
    for k in range(6):
        p = pts[perm][ids[perm] == k]
        single = fit_circle(p, method, sigma=0.01, angle_increment=DTH)
        assert bool(fits.ok[k]) == bool(single)
        np.testing.assert_allclose(fits.centers[k], single.center, atol=1e-9)
        assert fits[k].radius == pytest.approx(single.radius, abs=1e-9)
        assert fits.n_points[k] == p.shape[0]


def test_batch_reports_failed_segments_without_zeros() -> None:
    p = np.vstack((visible_arc((5.0, 0.0), 0.2), [[1.0, 1.0], [1.0, 1.0]]))
    ids = np.r_[np.zeros(len(p) - 2, dtype=int), [1, 1]]
    fits = fit_circles_batch(p, ids, "ours")
    assert fits.ok.tolist() == [True, False]
    assert np.isnan(fits.radii[1]) and "at least 3" in fits.reasons[1]
    assert not fits[1]


# ------------------------------------------------------------------------------------------
# simulated one-sided noisy arcs: ours is unbiased where the algebraic fits are not
# ------------------------------------------------------------------------------------------


def test_ours_is_unbiased_on_short_noisy_arcs_where_kasa_is_not() -> None:
    # 2 m, 0.5 deg beams, 1 cm range noise, trunks 10-60 cm: 15-60 returns on the front half.
    rng = np.random.default_rng(11)
    pts, ids, radii = arc_batch(2.0, 300, 0.01, rng)
    kw = {"sigma": 0.01, "angle_increment": DTH}
    ka = (fit_circles_batch(pts, ids, "kasa").diameters - 2 * radii) * 100
    ours = (fit_circles_batch(pts, ids, "ours", **kw).diameters - 2 * radii) * 100
    # measured (seed 11): kasa bias -1.58 cm, RMSE 1.91 cm; ours bias -0.08 cm, RMSE 0.70 cm
    # with orthogonal residuals (when this bound was set), -0.18 / 0.58 cm with the range
    # residuals that are the default since the edge model (thin beams: a little more bias for
    # less RMSE, scan-fits.md "Known weakness").
    # Standard error of the mean of ours = 0.70 / sqrt(300) = 0.04 cm, so |bias| < 0.2 cm is
    # measured + 3 standard errors, while kasa's shrinkage is ~15 of its standard errors.
    assert np.mean(ka) < -1.0
    assert abs(np.mean(ours)) < 0.2
    assert np.sqrt(np.mean(ours**2)) < 0.5 * np.sqrt(np.mean(ka**2))  # measured ratio 0.37


@pytest.mark.parametrize(("dist", "max_bias", "max_rmse"), [(5.0, 0.65, 1.8), (10.0, 1.1, 3.2)])
def test_ours_accuracy_at_range(dist: float, max_bias: float, max_rmse: float) -> None:
    # 0.5 deg beams, 1 cm noise, radius 5-30 cm: 3-12 returns per arc. Measured (seed 12):
    # 5 m: bias -0.41, RMSE 1.48 cm (kasa RMSE 18 cm); 10 m: bias -0.71, RMSE 2.74 cm (kasa 22)
    # with orthogonal residuals; with the default range residuals 5 m: -0.52 / 1.36 cm, 10 m:
    # -0.94 / 2.71 cm.
    # Bounds: measured + 3 standard errors of the mean (RMSE / sqrt(400)) for the bias, +20 %
    # for the RMSE. The negative bias is the known weakness documented in scan-fits.md.
    rng = np.random.default_rng(12)
    pts, ids, radii = arc_batch(dist, 400, 0.01, rng)
    fits = fit_circles_batch(pts, ids, "ours", sigma=0.01, angle_increment=DTH)
    assert fits.ok.all()
    err = (fits.diameters - 2 * radii) * 100
    assert abs(np.mean(err)) < max_bias
    assert np.sqrt(np.mean(err**2)) < max_rmse
    kasa = (fit_circles_batch(pts, ids, "kasa").diameters - 2 * radii) * 100
    assert np.sqrt(np.mean(err**2)) < 0.5 * np.sqrt(np.mean(kasa**2))


def test_ours_covariance_is_calibrated() -> None:
    # predicted radius std from the Gauss-Newton covariance vs the empirical spread over
    # repeated noisy scans of one trunk: 200 repeats give the empirical std to +-10 %.
    rng = np.random.default_rng(13)
    errs, stds = [], []
    for _ in range(200):
        p = visible_arc((4.0, 0.5), 0.15, sigma=0.01, rng=rng)
        fit = fit_circle_ours(p, sigma=0.01, angle_increment=DTH)
        errs.append(fit.radius - 0.15)
        stds.append(math.sqrt(fit.cov[2, 2]))
    ratio = float(np.std(errs) / np.sqrt(np.mean(np.square(stds))))
    assert 0.6 < ratio < 1.5
    cov = fit.cov
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_ours_is_robust_to_a_mixed_pixel() -> None:
    # a mixed pixel at the edge: range halfway to a wall 1 m behind the trunk
    rng = np.random.default_rng(14)
    errs_ours, errs_kasa = [], []
    for _ in range(50):
        p = visible_arc((4.0, 0.0), 0.2, sigma=0.005, rng=rng)
        u = p[-1] / np.hypot(*p[-1])
        p[-1] = p[-1] + 0.5 * u
        errs_ours.append(fit_circle_ours(p, sigma=0.005, angle_increment=DTH).radius - 0.2)
        errs_kasa.append(fit_circle_kasa(p).radius - 0.2)
    # Huber (1.5 sigma) bounds the outlier's pull; kasa follows it by tens of cm.
    assert np.sqrt(np.mean(np.square(errs_ours))) < 0.01
    assert np.sqrt(np.mean(np.square(errs_kasa))) > 0.05


def test_ours_occluded_edge_is_dropped() -> None:
    # the last 30 % of the arc hidden behind a nearer trunk: the hidden side is no silhouette
    p = visible_arc((6.0, 0.0), 0.25)
    keep = p[: int(0.7 * len(p))]
    right = fit_circle_ours(keep, sigma=0.002, angle_increment=DTH, edges=(True, False))
    wrong = fit_circle_ours(keep, sigma=0.002, angle_increment=DTH, edges=(True, True))
    assert abs(right.radius - 0.25) < 0.01
    assert abs(wrong.radius - 0.25) > abs(right.radius - 0.25)


segments = st.lists(
    st.one_of(
        # a noisy visible arc
        st.tuples(st.floats(1.0, 15.0), st.floats(-3.0, 3.0), st.floats(0.05, 0.5)).map(
            lambda c: visible_arc(
                (c[0] * math.cos(c[1]), c[0] * math.sin(c[1])),
                c[2],
                sigma=0.01,
                rng=np.random.default_rng(int(c[0] * 1000)),
            )
        ),
        # arbitrary small point sets: 0-5 points, possibly duplicated or collinear
        st.lists(st.tuples(st.integers(-3, 3), st.integers(-3, 3)), max_size=5).map(
            lambda v: np.array(v, dtype=float).reshape(-1, 2)
        ),
    ),
    min_size=1,
    max_size=6,
)


@settings(max_examples=40, deadline=None)
@given(segments)
def test_vectorised_batch_equals_single_fits(segs) -> None:
    segs = [s for s in segs if s.shape[0]]
    if not segs:
        return
    pts = np.vstack(segs)
    ids = np.repeat(np.arange(len(segs)), [s.shape[0] for s in segs])
    for m in ALL:
        fits = fit_circles_batch(pts, ids, m, sigma=0.01, angle_increment=DTH)
        for k, s in enumerate(segs):
            single = fit_circle(s, m, sigma=0.01, angle_increment=DTH)
            assert bool(fits.ok[k]) == bool(single), (m, k, fits.reasons[k], single.reason)
            assert fits.reasons[k] == single.reason, m
            if single:
                # same algebra, summed in a different order: round-off only
                np.testing.assert_allclose(fits.centers[k], single.center, rtol=1e-7, atol=1e-7)
                assert fits.radii[k] == pytest.approx(single.radius, rel=1e-7, abs=1e-7), m
                assert fits.rms[k] == pytest.approx(single.rms, rel=1e-6, abs=1e-9), m


def test_chord_width_front_is_the_nearest_return_on_a_shared_bearing() -> None:
    """Two returns on the bisecting bearing (1.41 and 2.83 m at 45 deg): the front surface is
    the nearer one whether the segment is fitted alone or second in a batch (hypothesis found
    the batch taking the farther one: its bearing key lost the tie's order)."""
    seg = np.array([[0.0, 1.0], [1.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    other = visible_arc((1.0, 0.0), 0.5, sigma=0.01, rng=np.random.default_rng(1000))
    pts = np.vstack((other, seg))
    ids = np.repeat([0, 1], [other.shape[0], seg.shape[0]])
    fits = fit_circles_batch(pts, ids, "chord_width")
    single = fit_circle(seg, "chord_width")
    # radius = half the 1.414 m chord; centre at the nearer return's range + r along 45 deg
    want = (math.sqrt(2.0) + math.sqrt(0.5)) * np.array([math.cos(math.pi / 4)] * 2)
    np.testing.assert_allclose(single.center, want, atol=1e-12)
    np.testing.assert_allclose(fits.centers[1], want, atol=1e-12)
