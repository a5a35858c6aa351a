"""Properties of the circle fits that the first tests left open (found by mutation testing of
``scan/circle.py``, docs/reliability.md "Mutation testing"): what a failed fit carries, the
textbook 3-step convergence of Fletcher-Reeves, noisy full rings, the chord width's ordering
and origin, point-order and mirror invariance, and the batch paths (vectorised, compiled and
one call per segment) against the single fits, field by field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.scan import circle
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

INC = math.radians(0.5)


def _arc(cx, cy, r, n, origin=(0.0, 0.0), noise=0.0, seed=0):
    """Returns of a thin-beam scanner at ``origin`` on the visible side of a circle, in bearing
    order (ray casting, so the arc ends are where the beams graze the trunk)."""
    o = np.asarray(origin, float)
    c = np.array([cx, cy]) - o
    d = math.hypot(*c)
    beta = math.atan2(c[1], c[0])
    half = math.asin(r / d)
    a = beta + np.linspace(-half * 0.95, half * 0.95, n)
    u = np.column_stack((np.cos(a), np.sin(a)))
    b = u @ c
    rng_ = b - np.sqrt(b * b - (d * d - r * r))
    rng_ = rng_ + np.random.default_rng(seed).normal(0.0, noise, n) if noise else rng_
    return o + u * rng_[:, None]


def _fields(f):
    return (f.ok, f.reason, f.method, f.n_points)


@pytest.mark.parametrize(
    ("method", "points", "reason"),
    [
        ("kasa", np.zeros((2, 2)), "need at least 3 points, got 2"),
        ("kasa", np.ones((4, 2)), "all points coincide"),
        ("kasa", [[0, 0], [1, 1], [2, 2], [3, 3]], "points are collinear"),
        ("fletcher_reeves", np.zeros((2, 2)), "need at least 3 points, got 2"),
        ("fletcher_reeves", np.ones((4, 2)), "all points coincide"),
        ("fletcher_reeves", [[0, 0], [1, 1], [2, 2], [3, 3]], "points are collinear"),
        ("ours", np.zeros((2, 2)), "need at least 3 points for a circle fit"),
    ],
)
def test_a_failed_fit_names_its_method_count_and_reason(method, points, reason):
    f = fit_circle(points, method)
    n = np.asarray(points).shape[0]
    assert _fields(f) == (False, reason, method, n)
    assert not f
    assert f.center.shape == (2,) and np.all(np.isnan(f.center)) and math.isnan(f.radius)
    assert math.isnan(f.diameter) and f.cov.shape == (3, 3) and np.all(np.isnan(f.cov))


@pytest.mark.parametrize("method", ["three_point", "chord_width"])
def test_failed_single_from_batch_fits_carry_method_and_count(method):
    f = fit_circle([[1.0, 1.0], [1.0, 1.0]], method)
    assert not f and f.method == method and f.n_points == 2 and f.reason


def test_fit_fields_on_success():
    p = _arc(4.0, 1.0, 0.25, 21)
    for m in ("kasa", "fletcher_reeves", "three_point", "chord_width"):
        f = fit_circle(p, m)
        assert f.ok and f.reason == "" and f.method == m and f.n_points == 21
        assert f.cov.shape == (3, 3) and np.all(np.isnan(f.cov))  # no covariance estimated
        assert f.rms == pytest.approx(math.sqrt(np.mean(f.residuals(p) ** 2)), abs=1e-12)
    f = fit_circle_ours(p, angle_increment=INC, sigma=0.001)
    assert f.ok and f.method == "ours" and f.n_points == 21 and np.all(np.isfinite(f.cov))


def test_residuals_accept_any_numeric_nested_input():
    f = fit_circle_kasa([[1, 0], [0, 1], [-1, 0], [0, -1]])
    np.testing.assert_allclose(f.residuals([[2, 0], [0, 0]]), [1.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(f.residuals([3, 0]), [2.0], atol=1e-12)


def test_fletcher_reeves_converges_in_the_textbook_three_steps():
    # CG on the 3x3 normal equations: 3 updates, and the 4th iteration sees ||d|| < tol
    p = _arc(5.0, 1.0, 0.3, 15, noise=0.003, seed=4)
    kasa = fit_circle_kasa(p)
    f4 = fit_circle_fletcher_reeves(p, k_max=4)
    assert f4 and f4.radius == pytest.approx(kasa.radius, rel=1e-9)
    np.testing.assert_allclose(f4.center, kasa.center, rtol=0, atol=1e-9)
    f3 = fit_circle_fletcher_reeves(p, k_max=3)
    assert _fields(f3) == (False, "no convergence within k_max=3 iterations", "fletcher_reeves", 15)
    with pytest.raises(ConfigError, match=r"^k_max must be >= 1 and tol > 0, got k_max=5, tol=0"):
        fit_circle_fletcher_reeves(p, k_max=5, tol=0.0)


@pytest.mark.parametrize("method", ["kasa", "fletcher_reeves"])
def test_noisy_full_ring_is_fitted(method):
    # the points' RMS distance to their mean exceeds the fitted radius here (noise), so the
    # scaled algebraic r^2 is below 1: it must still be accepted
    rng = np.random.default_rng(0)
    a = np.linspace(0.0, 2 * math.pi, 50, endpoint=False)
    p = np.column_stack((np.cos(a), np.sin(a))) * 0.4 + [3.0, -2.0]
    p = p + rng.normal(0.0, 0.02, p.shape)
    f = fit_circle(p, method)
    assert f and f.radius == pytest.approx(0.4, abs=0.01)
    assert np.hypot(*(f.center - [3.0, -2.0])) < 0.01


def test_chord_width_uses_the_outermost_beams_seen_from_the_origin():
    origin = np.array([10.0, -4.0])
    p = _arc(13.0, -1.0, 0.3, 9, origin=origin)
    rng = np.random.default_rng(1)
    shuffled = p[rng.permutation(9)]
    w, bis, theta = chord_width(shuffled, origin=origin)
    # first and last returns by bearing are p[0] and p[-1]
    assert w == pytest.approx(math.hypot(*(p[-1] - p[0])), rel=1e-12)
    b0 = math.atan2(*(p[0] - origin)[::-1])
    b1 = math.atan2(*(p[-1] - origin)[::-1])
    assert theta == pytest.approx(b1 - b0, abs=1e-12)
    assert bis == pytest.approx(0.5 * (b0 + b1), abs=1e-12)
    assert w < 1.0  # a trunk, not a clamp
    # the same in a frame where the sensor is at the origin
    w2, _, th2 = chord_width(shuffled - origin)
    assert (w2, th2) == pytest.approx((w, theta), rel=1e-12)
    f = fit_circle_chord_width(shuffled, origin=origin)
    assert f.method == "chord_width" and f.diameter == pytest.approx(w, rel=1e-12)


def test_chord_width_orders_by_bearing_not_by_range():
    # nearest return in the middle, far returns at the ends: range order is not bearing order
    p = np.array([[5.0, 0.0], [5.5, 0.3], [5.5, -0.3], [5.2, 0.15], [5.2, -0.15]])
    w, _, theta = chord_width(p)
    assert w == pytest.approx(0.6, rel=1e-12)
    assert theta == pytest.approx(2 * math.atan2(0.3, 5.5), rel=1e-12)


@pytest.mark.parametrize("method", sorted(FIT_METHODS))
def test_every_fit_is_invariant_to_the_order_of_the_points(method):
    p = _arc(6.0, 2.0, 0.25, 25, noise=0.002, seed=7)
    kw = {"angle_increment": INC} if method == "ours" else {}
    a = fit_circle(p, method, **kw)
    b = fit_circle(p[np.random.default_rng(3).permutation(25)], method, **kw)
    assert a and b
    np.testing.assert_allclose(b.center, a.center, rtol=0, atol=1e-9)
    assert b.radius == pytest.approx(a.radius, abs=1e-9)


def test_ours_partial_arc_is_mirror_equivariant():
    # the first return occluded; mirrored in y, the same side is the last return
    p = _arc(5.0, 0.5, 0.3, 30, noise=0.002, seed=2)[8:]
    a = fit_circle_ours(p, angle_increment=INC, sigma=0.002, edges=(False, True))
    m = fit_circle_ours(p * [1, -1], angle_increment=INC, sigma=0.002, edges=(True, False))
    both = fit_circle_ours(p, angle_increment=INC, sigma=0.002, edges=(True, True))
    assert a and m and both
    np.testing.assert_allclose(m.center, a.center * [1, -1], atol=1e-7)
    assert m.radius == pytest.approx(a.radius, abs=1e-7)
    assert abs(both.radius - a.radius) > 1e-4  # the edge term matters here


def test_ours_rms_is_the_rms_of_the_residuals():
    p = _arc(4.0, 0.0, 0.2, 31, noise=0.003, seed=9)
    f = fit_circle_ours(p, angle_increment=INC)
    orth = math.sqrt(np.mean(f.residuals(p) ** 2))
    assert f.rms == pytest.approx(orth, rel=0.2)


# --- batches ---------------------------------------------------------------------------------


def _batch_scene():
    segs = [
        _arc(4.0, 1.0, 0.2, 15, origin=(0.5, -1.0), noise=0.002, seed=1),
        _arc(-3.0, 5.0, 0.3, 21, origin=(0.5, -1.0), noise=0.002, seed=2),
        np.array([[1.0, 1.0], [1.0, 1.0]]),  # fails
        _arc(2.0, -6.0, 0.15, 12, origin=(0.5, -1.0), noise=0.002, seed=3),
    ]
    pts = np.vstack(segs)
    ids = np.repeat([3, 7, 8, 12], [len(s) for s in segs])
    return segs, pts, ids


def _same(fits, singles, method):
    assert len(fits) == len(singles) and fits.method == method
    assert fits.covs.shape == (len(singles), 3, 3)
    for j, s in enumerate(singles):
        g = fits[j]
        assert _fields(g) == _fields(s), j
        assert bool(fits.ok[j]) == s.ok and fits.reasons[j] == s.reason
        if s.ok:
            np.testing.assert_allclose(g.center, s.center, rtol=0, atol=1e-9)
            assert g.radius == pytest.approx(s.radius, abs=1e-9)
            assert g.rms == pytest.approx(s.rms, abs=1e-9)
            np.testing.assert_allclose(g.cov, s.cov, rtol=1e-6, atol=1e-15, equal_nan=True)
        else:
            assert np.all(np.isnan(g.center)) and math.isnan(fits.radii[j])


@pytest.mark.parametrize("method", sorted(FIT_METHODS))
def test_batch_fields_equal_the_single_fits_with_an_origin(method):
    segs, pts, ids = _batch_scene()
    o = (0.5, -1.0)
    kw = {"angle_increment": INC} if method == "ours" else {}
    fits = fit_circles_batch(pts, ids, method, origin=o, **kw)
    singles = [fit_circle(s, method, origin=o, **kw) for s in segs]
    _same(fits, singles, method)
    assert fits.segment_ids.tolist() == [3, 7, 8, 12]
    assert fits.n_points.tolist() == [15, 21, 2, 12]
    np.testing.assert_allclose(fits.diameters, 2 * fits.radii)


def test_batch_ours_passes_every_option_per_segment():
    segs, pts, ids = _batch_scene()
    origins = np.array([[0.5, -1.0], [0.5, -1.0], [0.0, 0.0], [0.5, -1.0]])
    edges = np.array([[False, True], [True, False], [True, True], [True, True]])
    sil = np.array([[0.3, 0.2], [0.6, 0.25]])
    for residuals in ("range", "orthogonal"):
        fits = fit_circles_batch(
            pts,
            ids,
            "ours",
            origin=origins,
            sigma=[0.002, np.nan, 0.002, 0.003],
            angle_increment=INC,
            edges=edges,
            beam_divergence=0.002,
            silhouette=sil,
            residuals=residuals,
        )
        singles = [
            fit_circle_ours(
                s,
                origin=origins[j],
                sigma=[0.002, None, 0.002, 0.003][j],
                angle_increment=INC,
                edges=tuple(edges[j]),
                beam_divergence=0.002,
                silhouette=sil,
                residuals=residuals,
            )
            for j, s in enumerate(segs)
        ]
        _same(fits, singles, "ours")


def test_batch_broadcasts_a_shared_edge_pair_and_estimates_sigma_by_default():
    segs, pts, ids = _batch_scene()
    o = (0.5, -1.0)
    fits = fit_circles_batch(pts, ids, "ours", origin=o, angle_increment=INC, edges=(True, False))
    singles = [fit_circle_ours(s, origin=o, angle_increment=INC, edges=(True, False)) for s in segs]
    _same(fits, singles, "ours")


def test_batch_groups_ids_that_are_out_of_order_after_the_first():
    segs, pts, ids = _batch_scene()
    order = np.r_[0:15, 36:38, 15:36, 38:50]  # segment 8 (the failing pair) moved up
    fits = fit_circles_batch(pts[order], ids[order], "kasa")
    _same(fits, [fit_circle_kasa(s) for s in segs], "kasa")


def test_empty_batch():
    for m in ("kasa", "ours", "three_point"):
        fits = fit_circles_batch(np.zeros((0, 2)), np.zeros(0, dtype=np.int64), m)
        assert len(fits) == 0 and fits.centers.shape == (0, 2) and fits.reasons == ()


def test_batch_input_checks_name_the_argument():
    _, pts, ids = _batch_scene()
    with pytest.raises(InputError, match=r"^origin must be a finite \(2,\) pair or \(4, 2\)"):
        fit_circles_batch(pts, ids, "kasa", origin=np.zeros((3, 2)))
    with pytest.raises(InputError, match=r"^sigma must be a scalar or have shape \(4,\)"):
        fit_circles_batch(pts, ids, "ours", sigma=[0.1, 0.1])
    for bad in (-0.01, math.inf):
        with pytest.raises(InputError, match=r"^sigma \(range noise std, metres\) must be finite"):
            fit_circles_batch(pts, ids, "ours", sigma=bad)
    with pytest.raises(InputError, match=r"^edges must have shape \(2,\) or \(4, 2\)"):
        fit_circles_batch(pts, ids, "ours", edges=np.ones((3, 2), dtype=bool))
    with pytest.raises(InputError, match=r"^segment_ids must be an integer array of shape \(50,\)"):
        fit_circles_batch(pts, ids[:-1], "kasa")


def test_vectorised_methods_do_not_call_the_single_fit(monkeypatch):
    _, pts, ids = _batch_scene()

    def boom(*a, **k):
        raise AssertionError("the single fit was called")

    for m in ("kasa", "fletcher_reeves", "three_point", "chord_width"):
        monkeypatch.setitem(FIT_METHODS, m, boom)
        fits = fit_circles_batch(pts, ids, m)
        assert fits.ok.tolist() == [True, True, False, True]


def test_other_registered_methods_are_called_segment_by_segment(monkeypatch):
    segs, pts, ids = _batch_scene()
    calls = []

    def spy(points, **kw):
        calls.append(kw)
        return fit_circle_kasa(points, **kw)

    monkeypatch.setitem(FIT_METHODS, "spy", spy)
    origins = np.array([[0.5, -1.0], [1.0, 2.0], [0.0, 0.0], [0.5, -1.0]])
    edges = np.array([[False, True], [True, False], [True, True], [False, False]])
    fits = fit_circles_batch(
        pts,
        ids,
        "spy",
        origin=origins,
        sigma=[0.0, 0.01, np.nan, 0.02],
        edges=edges,
        angle_increment=INC,
    )
    singles = [fit_circle_kasa(s) for s in segs]
    for s in singles:
        object.__setattr__(s, "method", "spy")
    _same(fits, singles, "spy")
    assert len(calls) == 4
    np.testing.assert_array_equal([c["origin"] for c in calls], origins)
    assert [c["sigma"] for c in calls] == [None, 0.01, None, 0.02]
    assert [c["angle_increment"] for c in calls] == [INC] * 4
    assert [c["edges"] for c in calls] == [tuple(map(bool, e)) for e in edges]
    fits0 = fit_circles_batch(pts, ids, "spy")
    assert calls[-1]["angle_increment"] is None and calls[-1]["edges"] == (True, True)
    assert fits0.ok.tolist() == [True, True, False, True]


def test_unknown_method_message_lists_the_methods():
    with pytest.raises(ConfigError, match=r"unknown circle fit method 'nope'; choose one of \["):
        fit_circle(np.zeros((3, 2)), "nope")
    with pytest.raises(ConfigError, match="unknown circle fit method"):
        fit_circles_batch(np.zeros((3, 2)), np.zeros(3, dtype=int), "nope")
    assert circle.fit_circle_three_point is FIT_METHODS["three_point"]
    assert fit_circle_three_point([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]).radius == pytest.approx(1)


def test_ours_compiled_failure_names_method_and_count():
    p = _arc(5.0, 0.0, 0.3, 3)
    f = fit_circle_ours(p, angle_increment=INC, edges=(False, True))
    assert not f and f.method == "ours" and f.n_points == 3
    assert f.reason.startswith("a partial arc (one edge occluded) needs at least 4 returns")


def test_ours_option_limits():
    p = _arc(5.0, 0.0, 0.3, 15)
    # sigma 0 means "estimate it", like None
    a = fit_circle_ours(p, angle_increment=INC, sigma=0.0)
    b = fit_circle_ours(p, angle_increment=INC)
    assert a and a.radius == b.radius and np.array_equal(a.cov, b.cov)
    # beam divergence: 0 (thin beam) allowed, 0.5 rad and beyond refused
    assert fit_circle_ours(p, angle_increment=INC, beam_divergence=0.0)
    for bad in (0.5, 0.7, -0.01):
        with pytest.raises(InputError, match=r"^beam_divergence \(full angular width"):
            fit_circle_ours(p, angle_increment=INC, beam_divergence=bad)
    with pytest.raises(ConfigError, match=r"^residuals must be one of \('range', 'orthogonal'\)"):
        fit_circle_ours(p, residuals="normal")
    msg = r"^silhouette offsets must be finite \(NaN = default\) and stds finite and > 0 \(beam"
    for sil in (
        [[-2000.0, 0.3], [0.5, 0.3]],  # first side's offset
        [[0.5, 0.3], [-2000.0, 0.3]],  # last side's offset
        [[0.5, 0.3], [np.inf, 0.3]],
        [[0.5, 0.0], [0.5, 0.3]],
    ):
        with pytest.raises(InputError, match=msg):
            fit_circle_ours(p, angle_increment=INC, silhouette=sil)


@pytest.mark.parametrize("seed", range(4))
def test_fletcher_reeves_three_steps_on_other_arcs_and_a_symmetric_ring(seed):
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.05, 0.5)
    p = _arc(rng.uniform(2, 15), rng.uniform(-3, 3), r, int(rng.integers(6, 40)), noise=1e-3)
    f = fit_circle_fletcher_reeves(p, k_max=4)
    assert f and f.radius == pytest.approx(fit_circle_kasa(p).radius, rel=1e-8)
    a = np.arange(8) * math.pi / 4
    ring = np.column_stack((np.cos(a), np.sin(a))) * r
    g = fit_circle_fletcher_reeves(ring, k_max=4)
    assert g and g.radius == pytest.approx(r, rel=1e-12)


def test_batch_columns_have_the_documented_types():
    _, pts, ids = _batch_scene()
    for m in ("kasa", "ours", "spy"):
        with pytest.MonkeyPatch.context() as mp:
            mp.setitem(FIT_METHODS, "spy", fit_circle_kasa)
            fits = fit_circles_batch(pts, ids, m)
        assert fits.segment_ids.dtype == np.int64 and fits.n_points.dtype == np.int64
        assert fits.ok.dtype == bool and fits.ok.tolist() == [True, True, False, True]
        assert fits.rms.dtype == np.float64 and np.isnan(fits.rms[2])
        assert fits.radii.dtype == np.float64 and fits.centers.dtype == np.float64


def test_defaults_and_shape_messages():
    p = _arc(4.0, 1.0, 0.25, 9)
    assert fit_circle(p).method == "kasa"  # the default method
    assert circle.CircleFit.failed("why", "kasa").n_points == 0
    with pytest.raises(InputError, match=r"^points must have shape \(N, 2\), got \(3, 3\)\.$"):
        circle.as_points(np.zeros((3, 3)))
    with pytest.raises(InputError, match=r"^silhouette must have shape \(2, 2\) or \(1, 2, 2\)"):
        fit_circle_ours(p, angle_increment=INC, silhouette=np.zeros((3, 2)))
