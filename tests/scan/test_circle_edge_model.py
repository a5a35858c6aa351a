"""Tests of the edge model of the "ours" fit: range residuals, footprint-averaged edge returns,
per-side silhouette priors, and the detector's mixed-pixel classification of segment ends."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from stemmap import ConfigError, InputError
from stemmap.scan._fit_geometric import _footprint_range
from stemmap.scan._fit_lm import _footprint_range_share
from stemmap.scan.circle import fit_circle_ours, fit_circles_batch
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.features import MIXED_FRACTION_STD, edge_silhouette, mixed_fraction
from stemmap.scan.segment import build_segments, euclidean_breaks, extract_points
from stemmap.types import LaserScan

DTH = math.radians(0.5)
FOOT = math.radians(0.25)


def ray_range(c: np.ndarray, r: float, ang: np.ndarray) -> np.ndarray:
    """Exact first hit of rays from the origin at angles ``ang`` (NaN where they miss)."""
    u0, u1 = np.cos(ang), np.sin(ang)
    b = u0 * c[0] + u1 * c[1]
    disc = b * b - (c @ c - r * r)
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0, b - np.sqrt(disc), np.nan)


def footprint_arc(
    center: tuple[float, float],
    radius: float,
    *,
    foot: float = FOOT,
    sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    phase: float = 0.5,
    n_sub: int = 401,
) -> np.ndarray:
    """Returns of an averaging scanner (uniform footprint ``foot``, sampled by ``n_sub`` rays):
    a beam returns if at least half its footprint hits; range = mean of the hitting rays."""
    c = np.asarray(center, dtype=float)
    d = float(np.hypot(*c))
    half = math.asin(radius / d)
    b0 = math.atan2(c[1], c[0])
    ang = np.arange(b0 - half - DTH + phase * DTH, b0 + half + DTH, DTH)
    off = foot * ((np.arange(n_sub) + 0.5) / n_sub - 0.5)
    rr = ray_range(c, radius, ang[:, None] + off[None, :])
    hit = np.isfinite(rr)
    keep = hit.mean(axis=1) >= 0.5
    rho = np.nanmean(np.where(hit, rr, np.nan)[keep], axis=1)
    if sigma > 0:
        assert rng is not None
        rho = rho + rng.normal(0.0, sigma, rho.shape)
    a = ang[keep]
    return np.column_stack((np.cos(a), np.sin(a))) * rho[:, None]


# ------------------------------------------------------------------------------------------
# the footprint-averaged range (closed form) and its derivatives
# ------------------------------------------------------------------------------------------


@settings(max_examples=80, deadline=None)
@given(
    st.floats(1.0, 15.0),
    st.floats(0.04, 0.4),
    st.floats(-0.45, 3.0),
    st.sampled_from([-1.0, 1.0]),
)
@example(15.0, 0.04296875, 0.23828125, -1.0)  # found by hypothesis: round-off of the old FD
def test_footprint_range_matches_ray_casting_and_finite_differences(d, r, u, side) -> None:
    # beam centre u beam spacings inside the tangent (negative: outside, at most 0.45 beams,
    # so at least part of the footprint hits); the closed form linearises the rays' rotation
    # across the footprint: error O(r foot^2), < 0.05 mm here (measured <= 0.03 mm). The
    # prediction has kinks where the tangent crosses the centre ray (u = 0: the beam stops
    # returning) or a footprint edge (|u| = 1/4 beam); finite differences there are one-sided.
    assume(abs(u) > 0.01 and abs(abs(u) - 0.25) > 0.01)
    c = np.array([d, 0.0])
    alpha = math.asin(r / d)
    # a thin far trunk spans < 1 beam: its far tangent, 2 alpha / DTH - u beams beyond the
    # centre ray, makes the same kinks (hypothesis found d = 14.2, r = 0.04, u = 0.396: the far
    # tangent 0.2500 beams out, the h = 1e-5 stencil straddling it, while h = 1e-6 agrees)
    far = 2.0 * alpha / DTH - u
    assume(abs(far) > 0.01 and abs(abs(far) - 0.25) > 0.01)
    th = side * (alpha - u * DTH)
    ux, uy = math.cos(th), math.sin(th)
    b, s0 = ux * c[0] + uy * c[1], ux * c[1] - uy * c[0]
    out = np.zeros(4)
    assert _footprint_range(b, s0, r, FOOT, out)
    off = FOOT * ((np.arange(4001) + 0.5) / 4001 - 0.5)
    rays = ray_range(c, r, th + off)
    if np.mean(np.isfinite(rays)) >= 0.5:  # the beam would return: the physical prediction
        assert out[0] == pytest.approx(np.nanmean(rays), abs=5e-5)
    # five-point central differences, h = 1e-5 m: truncation O(h^4) is negligible and the
    # stencil (2h) stays inside the kink guard above (>= 8.7e-5 m at 1 m); a two-point stencil
    # at h = 1e-7 lost ~3e-4 to round-off (the prediction ~15 m carries S / (b wd) with wd ~
    # 4e-3 rad; hypothesis found d = 15, r = 0.043, u = 0.238).
    h = 1e-5

    def pred_at(k: int, step: float) -> float:
        args = [b, s0, r]
        args[k] += step
        o = np.zeros(4)
        assert _footprint_range(*args, FOOT, o)
        return float(o[0])

    for k in range(3):
        num = (-pred_at(k, 2 * h) + 8 * pred_at(k, h) - 8 * pred_at(k, -h) + pred_at(k, -2 * h)) / (
            12 * h
        )
        assert out[1 + k] == pytest.approx(num, rel=1e-4, abs=1e-5)


@settings(max_examples=80, deadline=None)
@given(
    st.floats(1.0, 15.0),
    st.floats(0.04, 0.4),
    st.floats(-0.45, 3.0),
    st.sampled_from([-1.0, 1.0]),
    st.sampled_from([0.04, 0.25]),
)
def test_footprint_range_share_is_the_mean_of_a_sliver(d, r, u, side, share) -> None:
    # edge_hit_window (Dec 5): the range window keeps at least `share` of the footprint, so a
    # beam whose footprint the circle covers by at least that share (a scanner with a return
    # threshold that low returned it) reads the mean range of the rays that hit, to the
    # closed form's linearisation error (< 0.05 mm, as above); kinks where the tangent
    # crosses the centre ray, a footprint edge or the window's edge (share - 1/2 footprints
    # past the centre: (1/2 - share) / 2 beams of 0.5 deg for a 0.25-degree footprint)
    kinks = (0.0, 0.25, (0.5 - share) * FOOT / DTH)
    c = np.array([d, 0.0])
    alpha = math.asin(r / d)
    far = 2.0 * alpha / DTH - u
    for x in (u, far):
        assume(all(abs(abs(x) - k) > 0.01 for k in kinks))
    th = side * (alpha - u * DTH)
    ux, uy = math.cos(th), math.sin(th)
    b, s0 = ux * c[0] + uy * c[1], ux * c[1] - uy * c[0]
    out = np.zeros(4)
    assert _footprint_range_share(b, s0, r, FOOT, share, out)
    # 40 001 rays: with 4 001 a 4 % sliver holds ~160 of them, and the reference's own
    # sampling error (3e-5 m at d 10, r 0.375, u -0.175, share 0.04) reaches the tolerance
    off = FOOT * ((np.arange(40001) + 0.5) / 40001 - 0.5)
    rays = ray_range(c, r, th + off)
    if np.mean(np.isfinite(rays)) >= share:
        assert out[0] == pytest.approx(np.nanmean(rays), abs=5e-5)
    h = 1e-5

    def pred_at(k: int, step: float) -> float:
        args = [b, s0, r]
        args[k] += step
        o = np.zeros(4)
        assert _footprint_range_share(*args, FOOT, share, o)
        return float(o[0])

    for k in range(3):
        num = (-pred_at(k, 2 * h) + 8 * pred_at(k, h) - 8 * pred_at(k, -h) + pred_at(k, -2 * h)) / (
            12 * h
        )
        assert out[1 + k] == pytest.approx(num, rel=1e-4, abs=1e-5)
    # the half-footprint share is the default model to the bit
    half = np.zeros(4)
    _footprint_range(b, s0, r, FOOT, out)
    assert _footprint_range_share(b, s0, r, FOOT, 0.5, half)
    np.testing.assert_array_equal(half, out)


def test_footprint_range_beam_behind_sensor_is_rejected() -> None:
    assert not _footprint_range(-1.0, 0.0, 0.1, FOOT, np.zeros(4))


# ------------------------------------------------------------------------------------------
# the fit with the edge model
# ------------------------------------------------------------------------------------------


def test_noise_free_footprint_arc_is_recovered_by_the_edge_model() -> None:
    # Noise-free averaging-scanner returns: the edge model (range residuals, footprint-averaged
    # edges) explains them to < 0.4 mm (the second beams' footprints are modelled as thin
    # rays), so with sigma = 1 mm only the silhouette prior (interval middle) pulls: measured
    # radius errors 0.12 / 0.05 / 0.03 mm at phases 0.1 / 0.5 / 0.9; the thin-beam range model
    # is off by 3.9 / 0.7 / 0.7 mm on the same returns. ``rms`` is orthogonal: an edge return
    # averaged over a partly-missing footprint lies off the circle (here by ~1 mm).
    for phase in (0.1, 0.5, 0.9):
        p = footprint_arc((4.0, 1.0), 0.2, phase=phase)
        fit = fit_circle_ours(p, sigma=1e-3, angle_increment=DTH, beam_divergence=FOOT)
        assert fit.radius == pytest.approx(0.2, abs=5e-4)
        np.testing.assert_allclose(fit.center, [4.0, 1.0], atol=5e-4)
        assert fit.rms < 2e-3


def test_edge_model_removes_the_footprint_bias_of_the_thin_beam_model() -> None:
    # 5 m, radius 8-20 cm, 1 cm noise, random beam phase, 300 footprint-averaged arcs (6.3
    # returns on average). Measured (seed 21): diameter bias orthogonal -0.26 cm, range thin
    # -0.44 cm, edge model -0.21 cm; RMSE 1.66 / 1.60 / 1.54 cm; standard error of each mean
    # 0.09 cm. Bounds: the edge model's |bias| < 0.5 cm (measured + 3 s.e.); on the same arcs
    # (paired) it has a smaller bias than the thin-beam range model and the smallest RMSE.
    rng = np.random.default_rng(21)
    pts, ids, radii = [], [], []
    while len(radii) < 300:
        r = rng.uniform(0.08, 0.2)
        b = rng.uniform(-1.0, 1.0)
        p = footprint_arc(
            (5.0 * math.cos(b), 5.0 * math.sin(b)), r, sigma=0.01, rng=rng, phase=rng.uniform()
        )
        if p.shape[0] < 4:
            continue
        pts.append(p)
        ids.append(np.full(p.shape[0], len(radii)))
        radii.append(r)
    x, i, rad = np.vstack(pts), np.concatenate(ids), np.asarray(radii)
    kw = {"sigma": 0.01, "angle_increment": DTH}
    err = {
        name: 100 * (fit_circles_batch(x, i, "ours", **kw, **opt).diameters - 2 * rad)
        for name, opt in (
            ("orth", {"residuals": "orthogonal"}),
            ("thin", {}),
            ("edge", {"beam_divergence": FOOT}),
        )
    }
    bias = {k: float(np.mean(v)) for k, v in err.items()}
    rmse = {k: float(np.sqrt(np.mean(v**2))) for k, v in err.items()}
    assert abs(bias["edge"]) < 0.5
    assert abs(bias["edge"]) < abs(bias["thin"])
    assert rmse["edge"] < min(rmse["orth"], rmse["thin"])


def test_silhouette_prior_moves_the_tangent() -> None:
    # Noise-free arc, points weighted at sigma = 5 cm so that the silhouette dominates: a prior
    # that puts each tangent one beam farther out than the default (1.5 instead of 0.5 beams)
    # widens the silhouette by 2 beams: the radius grows by about D * dtheta = 3.5 cm.
    p = footprint_arc((4.0, 0.0), 0.15)
    base = fit_circle_ours(p, sigma=0.05, angle_increment=DTH, beam_divergence=FOOT)
    wide = fit_circle_ours(
        p,
        sigma=0.05,
        angle_increment=DTH,
        beam_divergence=FOOT,
        silhouette=[[1.5, 0.05], [1.5, 0.05]],
    )
    assert wide.radius - base.radius == pytest.approx(4.0 * DTH, rel=0.35)
    # NaN entries keep the default exactly
    same = fit_circle_ours(
        p,
        sigma=0.05,
        angle_increment=DTH,
        beam_divergence=FOOT,
        silhouette=[[np.nan, np.nan], [np.nan, np.nan]],
    )
    assert same.radius == base.radius
    np.testing.assert_array_equal(same.center, base.center)


def test_residual_models_agree_on_noise_free_thin_beam_arcs() -> None:
    # on exact thin-beam returns both noise models have the truth as a zero-residual solution;
    # with sigma = 10 um the points outweigh the silhouette prior (interval middle) entirely
    c = np.array([3.0, 1.0])
    a = np.arange(math.atan2(1, 3) - 0.045, math.atan2(1, 3) + 0.045, DTH)
    rho = ray_range(c, 0.1, a)
    p = np.column_stack((np.cos(a), np.sin(a)))[np.isfinite(rho)] * rho[np.isfinite(rho), None]
    for res in ("range", "orthogonal"):
        fit = fit_circle_ours(p, sigma=1e-5, angle_increment=DTH, residuals=res)
        assert fit.radius == pytest.approx(0.1, abs=1e-5)
        np.testing.assert_allclose(fit.center, c, atol=1e-5)


def test_edge_model_arguments_are_validated() -> None:
    p = footprint_arc((4.0, 0.0), 0.15)
    with pytest.raises(InputError):
        fit_circle_ours(p, beam_divergence=-0.1)
    with pytest.raises(InputError):
        fit_circle_ours(p, beam_divergence=math.inf)
    with pytest.raises(InputError):
        fit_circle_ours(p, silhouette=[0.5, 0.3])
    with pytest.raises(InputError):
        fit_circle_ours(p, silhouette=[[0.5, 0.0], [0.5, 0.3]])
    with pytest.raises(ConfigError):
        fit_circle_ours(p, residuals="algebraic")
    ids = np.zeros(p.shape[0], dtype=int)
    with pytest.raises(InputError):
        fit_circles_batch(p, ids, "ours", silhouette=np.full((2, 2, 2), 0.5))


# ------------------------------------------------------------------------------------------
# mixed pixels and the per-side silhouette from the neighbouring beams
# ------------------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(st.floats(0.5, 20.0), st.floats(0.05, 20.0), st.floats(0.0, 1.0))
def test_mixed_fraction_inverts_the_energy_weighted_blend(near, gap, f) -> None:
    far = near + gap
    w_n, w_f = f / near**2, (1 - f) / far**2
    m = (w_n * near + w_f * far) / (w_n + w_f)
    got = mixed_fraction(m, near, far)
    if near < m < far:
        assert float(got) == pytest.approx(f, abs=1e-6)
    else:  # f = 0 or 1 (or round-off): not a mixed pixel
        assert np.isnan(got) or float(got) == pytest.approx(f, abs=1e-6)


def scan_segments(ranges: np.ndarray) -> tuple:
    grid = ranges[None, :]
    ang = DTH * np.arange(ranges.shape[0])
    pts = extract_points(grid, ang, DTH)
    brk = euclidean_breaks(pts, 0.1, range_factor=3.0)
    return build_segments(pts, brk, ranges=grid), grid


def test_edge_silhouette_classifies_the_beams_beyond_each_end() -> None:
    h = FOOT / (2 * DTH)
    near, far = 4.0, 12.0
    f = 0.3
    w_n, w_f = f / near**2, (1 - f) / far**2
    mixed = (w_n * near + w_f * far) / (w_n + w_f)
    # beams: nothing, nothing | trunk x 5 | mixed pixel, background, background
    r = np.array([np.inf, np.inf, 4.02, 4.0, 3.99, 4.0, 4.02, mixed, far, far])
    segs, grid = scan_segments(r)
    k = int(np.flatnonzero(segs.counts == 5)[0])
    sil = edge_silhouette(segs, grid, FOOT)
    assert np.all(np.isnan(sil[k, 0]))  # nothing beyond the start: default
    assert sil[k, 1, 0] == pytest.approx(1 - h + 2 * h * mixed_fraction(mixed, 4.02, far))
    assert sil[k, 1, 1] == pytest.approx(2 * h * MIXED_FRACTION_STD)
    # a clean background beyond the end: the tangent is in the gap between two footprints
    r2 = np.array([np.inf, np.inf, 4.02, 4.0, 3.99, 4.0, 4.02, far, far, far])
    segs2, grid2 = scan_segments(r2)
    k2 = int(np.flatnonzero(segs2.counts == 5)[0])
    sil2 = edge_silhouette(segs2, grid2, FOOT)
    assert sil2[k2, 1, 0] == pytest.approx(0.5)
    assert sil2[k2, 1, 1] == pytest.approx((1 - 2 * h) / math.sqrt(12))
    # no footprint (thin beams) or a footprint as wide as the beam spacing: no information
    assert np.all(np.isnan(edge_silhouette(segs2, grid2, 0.0)))
    assert np.all(np.isnan(edge_silhouette(segs2, grid2, DTH)))


def test_detector_with_negative_angle_increment_matches_the_mirrored_scan() -> None:
    # the fit takes segment ends in bearing order: a scan listed from its last beam with a
    # negative increment must give the same trunks. The scene is asymmetric: trunk B's lower
    # side is hidden behind trunk A (occluded), a wall 10 m away stands behind the other edges
    # (background priors), so swapped flags or priors would change the fits.
    a = np.radians(np.arange(-20, 20.25, 0.5))
    r = np.full(a.shape, np.inf)
    for cx, cy, rad in ((4.0, -0.4, 0.15), (6.0, -0.25, 0.2)):
        rr = ray_range(np.array([cx, cy]), rad, a)
        r = np.fmin(r, np.where(np.isfinite(rr), rr, np.inf))
    r[~np.isfinite(r) & (a > math.radians(-10))] = 10.0
    det = ScanTrunkDetector("stemmap")
    fwd = det.detect(LaserScan(r, a[0], np.radians(0.5)))
    rev = det.detect(LaserScan(r[::-1].copy(), a[-1], -np.radians(0.5)))
    assert len(fwd) == len(rev) == 2
    assert np.any(fwd.quality < 0.6)  # B is partial (quality halved)
    o1, o2 = np.argsort(fwd.centers[:, 0]), np.argsort(rev.centers[:, 0])
    np.testing.assert_allclose(fwd.centers[o1], rev.centers[o2], atol=1e-6)
    np.testing.assert_allclose(fwd.radii[o1], rev.radii[o2], atol=1e-6)
    # noise-free ranges but sigma = 1 cm and beam-quantised priors: about the benchmark's
    # error at 4-6 m (measured 0.141 / 0.220 m; B is a partial arc)
    np.testing.assert_allclose(fwd.radii[o1], [0.15, 0.2], atol=0.03)


def test_detector_config_validates_the_edge_model_fields() -> None:
    with pytest.raises(ConfigError):
        DetectorConfig.preset("stemmap", beam_divergence_deg=-1.0)
    with pytest.raises(ConfigError):
        DetectorConfig.preset("stemmap", fit_residuals="algebraic")
    cfg = DetectorConfig.preset("stemmap")
    assert cfg.beam_divergence_deg == 0.25 and cfg.fit_residuals == "range"
