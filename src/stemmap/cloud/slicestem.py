"""One stem from its slice fits (ours, docs/algorithms/cloud.md "Ours" step 8): the slices
that agree on a radius and a centre line, a buttress below breast height, and the Theil-Sen
line (Theil 1950, Sen 1968) through the slices that gives DBH, centre, taper and lean at the
measurement height."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.band import _Band
from stemmap.cloud.bhradius import near_median_radius
from stemmap.cloud.config import StemConfig
from stemmap.cloud.dbhsd import dbh_variance
from stemmap.cloud.result import RULE_BH
from stemmap.cloud.slicefit import (
    _fit_segments,
    _segment_arcs,
    _segment_covariances,
    _theil_sen,
)
from stemmap.cloud.uncertainty import _line_uncertainty, _mean_uncertainty
from stemmap.types import FloatArray

BUTTRESS_CLEARANCE = 0.3  # m above the top of a buttress where the diameter is taken
BUTTRESS_OUTSIDE = 0.1  # fraction of a slice's points on fins outside the fitted circle
#: lean allowance (m per m of height, tan 10 deg: the pooled fit's bound) of the search for
#: returns above a stem's agreeing slices (:func:`_ends_in_band`)
CONTINUE_LEAN = math.tan(math.radians(10.0))


@dataclass(frozen=True)
class _SliceFits:
    """The circle fits of the candidate clusters, one row per cluster, one column per slice.

    ``passed``: the fit passed the per-slice quality tests (step 7); ``fitted``: a fit with a
    positive radius exists; ``centers`` (K, S, 2), ``radii``, ``rms``, ``arcs`` (degrees),
    ``n_in`` (inliers), ``weights`` (inliers / rms^2), ``cov`` (K, S, 3, 3) over (cx, cy, r);
    ``present`` (K,): slices with at least ``min_slice_points`` points."""

    passed: NDArray[np.bool_]
    fitted: NDArray[np.bool_]
    centers: FloatArray
    radii: FloatArray
    rms: FloatArray
    arcs: FloatArray
    n_in: NDArray[np.int64]
    weights: FloatArray
    cov: FloatArray
    present: NDArray[np.int64]


@dataclass(frozen=True)
class _BandContext:
    """What the per-stem tests read besides the fits: the band before the vertical filter
    (a cKDTree of its xy, or None, and each point's slice), the slice centres' heights, the
    noise floor, and whether the cloud is a pre-cut slice."""

    band: _Band
    tree: Any
    band_sl: NDArray[np.int64]
    centers_h: FloatArray
    noise_floor: float
    slice_cloud: bool
    rms_max: float = math.inf  # the per-slice residual test (step 7)
    # the noise floor is one candidate's own slice RMS, not pooled over stems (_annulus_noise)
    own_floor: bool = False
    # a plot's sparse band thickened to few slices (pooled noise floor): DBH from the slice
    # holding the measurement height, not from the line through them (_stem_at,
    # StemConfig.thick_dbh_slice)
    few_thick: bool = False
    # inliers an annulus refit about an established stem must hold (:func:`_annulus_fit`;
    # None: ``cfg.min_slice_points``). Set for the default thin slices of a plot's thickened
    # band (StemConfig.thin_refit_points)
    annulus_points: int | None = None


def _weighted_median(x: FloatArray, w: FloatArray) -> float:
    """The weighted median of ``x`` (weights ``w`` > 0): the smallest value whose cumulative
    weight reaches half the total; the mean of the two middle values at an exact tie (the
    plain median with equal weights)."""
    o = np.argsort(x)
    xs, cw = x[o], np.cumsum(w[o])
    half = 0.5 * cw[-1]
    k = int(np.searchsorted(cw, half * (1 - 1e-12)))
    if abs(cw[k] - half) <= 1e-12 * cw[-1] and k + 1 < xs.size:
        return float(0.5 * (xs[k] + xs[k + 1]))
    return float(xs[k])


def _short_arc_sigma(fits: _SliceFits, c: int) -> FloatArray:
    """The approximate radius noise (S,) of cluster ``c``'s slice fits: 2 rms / sqrt(n) on a
    half arc, growing like max(1, 180 deg / arc)^2 on shorter arcs (partly occluded trunks)."""
    short = np.maximum(1.0, 180.0 / np.maximum(fits.arcs[c], 1.0)) ** 2
    return np.asarray(2.0 * fits.rms[c] / np.sqrt(np.maximum(fits.n_in[c], 1)) * short)


def _radius_se(fits: _SliceFits, c: int, floor: float = 0.0) -> FloatArray:
    """Each slice fit's radius standard error (S,) from its covariance (sqrt of the (r, r)
    entry, :func:`~stemmap.cloud.slicefit._segment_covariances`); where it is missing (no
    covariance), the short-arc approximation 2 rms / sqrt(n) x max(1, 180 deg / arc)^2.

    The covariance is RMS^2 (J^T J)^-1: with a ``floor`` > 0 (a plot's pooled noise floor)
    a fit whose RMS is below it has its standard error scaled by floor / RMS, for the reason
    of :func:`_consensus_weights`: a few clutter points that happen to lie on a circle are
    not a smoother surface than the cloud's stems have."""
    rms = np.maximum(fits.rms[c], 1e-4)
    scale = np.maximum(1.0, floor / rms) if floor > 0 else np.ones_like(rms)
    approx = _short_arc_sigma(fits, c)
    var = fits.cov[c, :, 2, 2]
    ok = np.isfinite(var) & (var > 0)
    return np.where(ok, np.sqrt(np.where(ok, var, 1.0)), approx) * scale


def _radius_consensus(
    r: FloatArray,
    m: NDArray[np.bool_],
    tol: float,
    sig_r: float,
    w: FloatArray,
    se: FloatArray | None = None,
) -> tuple[float, NDArray[np.bool_]]:
    """Radius most slices agree on, and the slices that agree.

    The median of all passing slices is right when most slices see the stem. In a spruce
    whose whorls hide the stem in some slices, those slices fit large circles through the
    branches and the median lands between stem and clutter, rejecting both. The consensus is
    the slice radius with the most support within its tolerance (15 % of it, or 5 sigma of
    a slice radius); when every slice agrees with the median, the median is kept (the common
    case, unchanged). Support is the slices' fit weights ``w`` (inliers / RMS^2), not their
    count: around a spruce's whorls the circles through the branches agree with each other
    too (a crown is round), but they fit their points with several times the RMS of the
    bark, so three of them do not outvote one clean stem slice.

    ``se`` (S,; ``StemConfig.consensus_radius_se``): each slice's radius standard error from
    its fit. The consensus radius is then the median weighted by 1 / se^2 (the radius's own
    inverse variance), and the support of a radius is that weight too: a one-sided arc of
    9 points fixes its radius to several cm, a 145 deg arc of 10 to a few mm, and the
    points' RMS alone (``w``) does not tell them apart.
    """
    idx = np.flatnonzero(m)
    if se is not None:
        w = 1.0 / np.maximum(se, 1e-4) ** 2
    r_med = _middle(r[idx], None if se is None else w[idx])
    if np.all(np.abs(r[idx] - r_med) <= tol):
        return r_med, m
    tols = np.maximum(0.15 * r[idx], 5.0 * sig_r)
    near = np.abs(r[idx][None, :] - r[idx][:, None]) <= tols[:, None]
    support = near @ w[idx]
    best = support >= support.max() * (1 - 1e-12)
    # among equally supported radii, the smallest: clutter makes circles larger, not smaller
    j = idx[best][int(np.argmin(r[idx][best]))]
    agree = m & (np.abs(r - r[j]) <= max(0.15 * r[j], 5.0 * sig_r))
    return _middle(r[agree], None if se is None else w[agree]), agree


def _middle(x: FloatArray, w: FloatArray | None) -> float:
    """The median of ``x``, weighted by ``w`` when given (:func:`_weighted_median`)."""
    return float(np.median(x)) if w is None else _weighted_median(x, w)


@dataclass(frozen=True)
class _Agreement:
    """The slices of one cluster that agree on a stem: ``kept`` (S,), the ``radius`` they
    agree on, its tolerance ``tol``, and the centre ``pred`` (S, 2) the stem's line predicts
    at every slice height."""

    kept: NDArray[np.bool_]
    radius: float
    tol: float
    pred: FloatArray


def _centre_line(h: FloatArray, centers: FloatArray, at: FloatArray) -> FloatArray:
    """Centres (len(at), 2) on the Theil-Sen lines through ``centers`` (K, 2) at heights
    ``h``, evaluated at the heights ``at``."""
    lx, ly = _theil_sen(h, centers[:, 0]), _theil_sen(h, centers[:, 1])
    return np.column_stack((lx[0] + lx[1] * at, ly[0] + ly[1] * at))


def _consensus_weights(fits: _SliceFits, c: int, floor: float) -> FloatArray:
    """Cluster ``c``'s slice fit weights for the radius consensus: inliers / RMS^2, or with a
    ``floor`` > 0 inliers / max(RMS, floor)^2.

    A fit's weight stands for the inverse variance of its points about the circle. Where the
    noise floor is pooled over a plot's stems it measures the scatter a stem's surface has in
    this cloud (range noise, bark); a fit whose RMS is below it has not found a surface that
    much smoother -- its RANSAC tolerance and trimming kept the few points that happen to lie
    on a circle (treels pine_plot at 20 %, seed 0: a 10.1 cm circle through its neighbours'
    clutter, 8 inliers at RMS 1.7 mm against a 7.0 mm floor, outweighed two slices of an
    8.6 cm stem at 4-6 mm 16-fold; docs/algorithms/cloud.md "Sparse plots: the consensus
    weight floored at the noise"). ``StemConfig.consensus_floor``; only with a pooled floor
    (a single tree's floor is its own median RMS, on a sparse spruce its branch whorls')."""
    if floor <= 0:
        return fits.weights[c]
    return np.asarray(fits.n_in[c] / np.maximum(fits.rms[c], floor) ** 2, dtype=np.float64)


def _consistent_slices(
    fits: _SliceFits,
    c: int,
    centers_h: FloatArray,
    floor: float = 0.0,
    se_floor: float | None = None,
) -> _Agreement:
    """The passing slices of cluster ``c`` that agree on the radius and the centre line.

    Radii within max(15 % of r, 5 sigma_r) of the median -- or of the consensus radius
    (:func:`_radius_consensus`) when not all slices agree with the median -- where
    sigma_r = 2 rms / sqrt(n) x max(1, 180 deg / arc)^2 approximates a slice fit's radius
    noise; centres within max(that, 0.3 r) of a Theil-Sen line through them (>= 3 slices) or
    of their median. ``floor``: the consensus weights' RMS floor (:func:`_consensus_weights`).

    ``se_floor`` (not None: ``StemConfig.consensus_radius_se``): the consensus weighs slices
    by their radius's own inverse variance (:func:`_radius_se` with that RMS floor,
    :func:`_radius_consensus`); the tolerances stay as above.
    """
    radii, cen = fits.radii[c], fits.centers[c]
    m = fits.passed[c]
    # consistency: drop slices whose radius or centre is far from the median
    r_med = float(np.median(radii[m]))
    # tolerance: 15 % of the radius, or 5 sigma of a slice radius, whichever is larger.
    # sigma_r is the fit's parameter noise, not the points': ~2 rms / sqrt(n) on a half
    # arc, growing like (180 deg / arc)^2 on shorter arcs (partly occluded trunks)
    sig_r = float(np.median(_short_arc_sigma(fits, c)[m]))
    tol = max(0.15 * r_med, 5.0 * sig_r)
    se = None if se_floor is None else _radius_se(fits, c, se_floor)
    r_med, m = _radius_consensus(radii, m, tol, sig_r, _consensus_weights(fits, c, floor), se)
    tol = max(0.15 * r_med, 5.0 * sig_r)
    c_med = np.median(cen[m], axis=0)
    # centres are compared with a robust line through them (a leaning stem's centre
    # moves with height), radii with their median
    if m.sum() >= 3:
        pred = _centre_line(centers_h[m], cen[m], centers_h)
    else:
        pred = np.broadcast_to(c_med, cen.shape)
    m = m & (np.abs(radii - r_med) <= tol) & (np.hypot(*(cen - pred).T) <= max(tol, 0.3 * r_med))
    return _Agreement(m, r_med, tol, pred)


def _row(fits: _SliceFits, c: int) -> _SliceFits:
    """Cluster ``c``'s fits alone (as cluster 0), as copies."""
    return _SliceFits(*(np.array(getattr(fits, f)[c : c + 1]) for f in fits.__dataclass_fields__))


def _annulus_noise(
    fits: _SliceFits, c: int, kept: NDArray[np.bool_], ctx: _BandContext, cfg: StemConfig
) -> float | None:
    """The residual scale of the annulus about cluster ``c``'s stem (:func:`_annulus_fit`):
    None (the cloud's noise floor), or the mean RMS of the stem's agreeing slices ``kept``
    when the floor is not a measure of this stem's scatter.

    The annulus half width (3 noise floors) and its RANSAC tolerance (half a floor) stand
    for the scatter of a stem's surface: range noise and bark. Pooled over a plot's stems,
    the median slice RMS measures that. A cloud with a single candidate cluster
    (``ctx.own_floor``) has the median over that candidate's own slices, and on a sparse
    spruce most of those fit its branch whorls: treels spruce.laz at 20 / 10 % has floors
    of 71 / 124 mm against 3-9 mm on its stem slices, so the annulus about its 12 cm stem
    reached 21-37 cm out and its refits fit the whorls (docs/algorithms/cloud.md "Single
    trees: the annulus about a found stem"). The stem's own scale replaces the floor when
    the floor exceeds it by more than ``cfg.residual_factor`` -- the ratio at which the
    residual test calls a slice fit too rough for the floor, here read the other way: a
    floor that far above the stem's slices is not their noise (archi Tree_1's rough bark,
    floor 20 mm against 10 mm: kept). It needs two agreeing slices: the RMS of one fit is
    that fit's, and a stem seen in one slice only is not yet established (one flared slice
    would set both the annulus and its scale). In a plot the pooled floor stays: a shrub's
    two slices fit with less RMS than the scan's noise (the simulated mobile scan, 3 cm
    range noise: with its own 10 mm a clump of spheres became a 5.7 cm stem)."""
    if not ctx.own_floor or kept.sum() < 2:
        return None
    own = float(np.mean(fits.rms[c, kept]))
    return own if ctx.noise_floor > cfg.residual_factor * own else None


def _guided_refits(
    fits: _SliceFits, c: int, agree: _Agreement, ctx: _BandContext, cfg: StemConfig
) -> tuple[_SliceFits, NDArray[np.bool_]] | None:
    """Refit the slices of cluster ``c`` that disagree with its stem, from the circle the
    agreeing slices (``agree``) predict there; the cluster's fits (as cluster 0) with the refits
    that pass and the slices refitted, or None when none passes.

    In a slice full of branches (a spruce's whorls) the robust fit may lock onto a circle
    through the clutter although the stem is there too; which slices do so changes with the
    smallest perturbation of the cloud (a 1 mm resampling, a rotation about z, a coarser
    spacing). The band's points of such a slice (before the vertical filter) within an
    annulus around the predicted circle -- half width max(0.3 r, 3 noise floors; the stem's
    own scale where the floor is not its noise, :func:`_annulus_noise`) plus the largest
    taper over the height difference to the agreeing slices -- are fitted again
    (:func:`_annulus_fit`); the refit replaces the slice's fit when
    it passes the per-slice tests (inliers, arc, residual) and agrees with the stem (radius
    within the tolerance, centre within max(tolerance, 0.3 r) of the prediction, both plus that
    taper allowance). The predicted centre is the consistency test's line, or with two
    agreeing slices the line through them, or one slice's centre. Only for a cluster that
    would otherwise fail the slice count: stems found without it are unchanged.
    """
    m, r_med, tol, pred = agree.kept, agree.radius, agree.tol, agree.pred
    if ctx.tree is None or not m.any():
        return None
    ch = ctx.centers_h
    h_ref = float(np.mean(ch[m]))
    if m.sum() == 2:  # a line through the two (3 or more: already the Theil-Sen line)
        pred = _centre_line(ch[m], fits.centers[c, m], ch)
    noise = _annulus_noise(fits, c, m, ctx, cfg)
    out = _row(fits, c)
    changed = np.zeros(m.shape[0], dtype=bool)
    found: dict[int, _AnnulusFit] = {}
    for s in map(int, np.flatnonzero(~m)):
        slack = cfg.max_taper * abs(float(ch[s]) - h_ref)
        fit = _annulus_fit(ctx, s, pred[s], r_med, tol, slack, cfg, noise)
        if fit is not None:
            found[s] = fit
    if cfg.guided_taper:
        found = _taper_checked(found, ch, m, fits.radii[c], h_ref, cfg)
    for s, fit in found.items():
        _set_slice(out, s, fit)
        changed[s] = True
    return (out, changed) if changed.any() else None


def _taper_checked(
    found: dict[int, _AnnulusFit],
    ch: FloatArray,
    m: NDArray[np.bool_],
    radii: FloatArray,
    h_ref: float,
    cfg: StemConfig,
) -> dict[int, _AnnulusFit]:
    """The guided refits ``found`` (slice -> fit) that keep the stem's taper: taken from the
    nearest to the agreeing slices' mean height ``h_ref`` outwards, a refit is kept when the
    Theil-Sen line through the agreeing slices' radii (``radii[m]``) and the refits kept so
    far and its own has |d r / d h| <= ``cfg.max_taper`` (``StemConfig.guided_taper``).

    An annulus refit may pass its radius test within the consensus tolerance plus the largest
    taper over its height difference, and that tolerance grows with the short arcs' radius
    noise (5 sigma_r, :func:`_consistent_slices`): on treels pine_plot at 10 % (seed 3) the
    0.8-1.2 m slice of a stem with slices r = 8.02 / 9.32 cm at 1.4 / 1.8 m refitted at
    14.22 cm on the root flare and clutter, within 4.8 + 3.0 cm of 8.67 cm; the line through
    the three radii then tapers by 6.1 cm/m and :func:`_stem_at` rejects the stem, the
    refit with it. A refit that breaks the taper test is a swelling or clutter, not the
    stem's radius at that height: it is left out instead, and the stem stands or falls by
    the others (docs/algorithms/cloud.md "Short arcs in the radius consensus")."""
    keep: dict[int, _AnnulusFit] = {}
    h0, r0 = ch[m], radii[m]
    for s in sorted(found, key=lambda k: (abs(float(ch[k]) - h_ref), k)):
        ks = sorted(keep)
        h = np.concatenate((h0, ch[ks], [ch[s]]))
        r = np.concatenate((r0, [keep[k].radius for k in ks], [found[s].radius]))
        if h.size >= 3 and np.ptp(h) >= 0.3 and abs(_theil_sen(h, r)[1]) > cfg.max_taper:
            continue
        keep[s] = found[s]
    return keep


@dataclass(frozen=True)
class _AnnulusFit:
    """One slice's circle refitted from the points about a predicted circle."""

    center: FloatArray
    radius: float
    rms: float
    arc: float
    n_in: int
    cov: FloatArray


def _annulus_fit(
    ctx: _BandContext,
    s: int,
    center: FloatArray,
    radius: float,
    tol: float,
    slack: float,
    cfg: StemConfig,
    noise: float | None = None,
) -> _AnnulusFit | None:
    """The circle of slice ``s`` (of ``ctx.band_sl``) fitted to the band's points (before the
    vertical filter) within an annulus about the predicted circle (``center``, ``radius``),
    or None when it fails the per-slice tests or disagrees with the prediction.

    Half width of the annulus max(0.3 r, 3 noise floors) + ``slack`` (the largest taper over
    the height difference to the slices the prediction comes from); RANSAC tolerance half a
    noise floor (>= 5 mm). The fit must have ``cfg.min_slice_points`` inliers, an arc of
    ``cfg.min_arc_deg``, RMS within the per-slice residual test (``ctx.rms_max``, or 2 % of
    r), a radius within ``tol`` + slack of the prediction and a centre within max(tol, 0.3 r)
    + slack of it. ``noise`` replaces the noise floor in the width and the tolerance
    (:func:`_annulus_noise`; None: the floor). The inlier count is ``ctx.annulus_points``
    where set (a plot's thin slices in a thickened band, :func:`thin_slice_points`).
    """
    need = cfg.min_slice_points if ctx.annulus_points is None else ctx.annulus_points
    nf = ctx.noise_floor if noise is None else noise
    width = max(0.3 * radius, 3.0 * nf) + slack
    idx = np.asarray(ctx.tree.query_ball_point(center, radius + width), dtype=np.int64)
    idx = idx[ctx.band_sl[idx] == s]
    q = ctx.band.xy[idx]
    q = q[np.abs(np.hypot(*(q - center).T) - radius) <= width]
    if q.shape[0] < need:
        return None
    ids = np.zeros(q.shape[0], dtype=np.int64)
    cen, rad, rms, ok, nin = _fit_segments(
        q,
        ids,
        1,
        cfg.fit_method,
        ransac_tol=max(0.5 * nf, 0.005),
        radius_window=(cfg.min_diameter / 2, cfg.max_diameter / 2),
        ransac_lo=cfg.ransac_lo,
        ransac_seed=cfg.ransac_seed,
        window=cfg.slice_fit_window,
        stub_trim=cfg.slice_stub_trim,
        stub_surface=cfg.slice_stub_surface,
    )
    if not ok[0] or nin[0] < need:
        return None
    arc = float(_segment_arcs(q, ids, 1, cen)[0])
    good = (
        arc >= cfg.min_arc_deg
        and rms[0] <= max(ctx.rms_max, 0.02 * rad[0])
        and abs(rad[0] - radius) <= tol + slack
        and math.hypot(*(cen[0] - center)) <= max(tol, 0.3 * radius) + slack
    )
    if not good:
        return None
    cov = _segment_covariances(q, ids, 1, cen, rad, rms)[0]
    return _AnnulusFit(cen[0], float(rad[0]), float(rms[0]), arc, int(nin[0]), cov)


#: the fewest inliers of a circle refit about a known stem: three parameters and two degrees
#: of freedom left to test the residual
MIN_ANNULUS_POINTS = 5


def thin_slice_points(min_points: int, thin: float, thick: float) -> int:
    """Inliers a default (``thin``) slice must hold in a band thickened to ``thick`` slices:
    ``min_points`` x thin / thick, at least :data:`MIN_ANNULUS_POINTS`.

    :func:`~stemmap.cloud.band._adapt_slices` thickens the slices of a sparse cloud until each
    is ``slices_per_spacing`` spacings thick, so that a stem's side in one holds the
    ``min_points`` a circle fit must find among clutter; a thin slice of the same cloud holds
    thin / thick of that on the same stem. An annulus refit about the circle two agreeing thin
    slices predict (:func:`_guided_refits` in the tighter refits' thin ladder) does not search
    the clutter for a circle -- its centre and radius must agree with the prediction -- so it
    is held to the count the density gives, not to the dense cloud's (never above
    ``min_points``)."""
    scaled = math.ceil(min_points * thin / thick - 1e-9)
    return min(min_points, max(MIN_ANNULUS_POINTS, scaled))


def _set_slice(out: _SliceFits, s: int, fit: _AnnulusFit) -> None:
    """Slice ``s`` of the one-cluster fits ``out`` (cluster 0) becomes the passing ``fit``."""
    out.passed[0, s] = out.fitted[0, s] = True
    out.centers[0, s], out.radii[0, s], out.rms[0, s] = fit.center, fit.radius, fit.rms
    out.arcs[0, s], out.n_in[0, s] = fit.arc, fit.n_in
    out.weights[0, s] = fit.n_in / max(fit.rms, 1e-4) ** 2
    out.cov[0, s] = fit.cov


def _outside_fraction(
    band: _Band,
    tree: Any,
    sl: NDArray[np.int64],
    c: FloatArray,
    r: FloatArray,
    rms: FloatArray,
) -> FloatArray:
    """Per slice of one stem: the fraction of the band's points within two radii of the
    slice circle's centre that lie outside it by more than max(3 RMS, 2 cm) and less than one
    radius -- buttress fins and root flare, which the robust fit trims as outliers (it
    measures the round core between the fins). All band points, before the vertical filter
    (a fin shrinks with height, so the filter removes much of it)."""
    ns = r.shape[0]
    out = np.zeros(ns)
    if tree is None or not np.isfinite(r).any():
        return out
    k = int(np.nanargmax(r))
    idx = np.asarray(tree.query_ball_point(c[k], 2.0 * float(np.nanmax(r))), dtype=np.int64)
    if idx.size == 0:
        return out
    for s in range(ns):
        if not np.isfinite(r[s]):
            continue
        q = idx[sl[idx] == s]
        d = np.hypot(*(band.xy[q] - c[s]).T)
        q_in = d <= 2 * r[s]
        if q_in.sum() < 8:
            continue
        res = d[q_in] - r[s]
        thr = max(3 * float(rms[s]) if np.isfinite(rms[s]) else 0.0, 0.02)
        out[s] = float(np.mean((res > thr) & (res < r[s])))
    return out


def _measurement_height(
    fits: _SliceFits, c: int, agree: _Agreement, ctx: _BandContext, cfg: StemConfig
) -> tuple[float, str]:
    """Where the DBH of cluster ``c`` is measured, and why: breast height, or
    :data:`BUTTRESS_CLEARANCE` (0.3 m) above the top of a buttress that reaches above
    ``breast_height - 0.3`` (forestry convention: the diameter is taken 0.3 m above the top of
    the swelling when it reaches above 1.0 m).

    A buttress or root flare is the run of slices from the lowest up, below breast height,
    centred on the stem, whose fit is too large for the stem's tolerance or whose band points
    lie outside the circle (:func:`_outside_fraction` > :data:`BUTTRESS_OUTSIDE`), with a
    clean stem above it (outside fraction < half of that: a spruce's whorls put branch points
    around the stem at every height, which is not a buttress). Never for a pre-cut slice.
    """
    m, r_med, tol, pred = agree.kept, agree.radius, agree.tol, agree.pred
    centers_h = ctx.centers_h
    radii, cen, fitted = fits.radii[c], fits.centers[c], fits.fitted[c]
    out_f = _outside_fraction(ctx.band, ctx.tree, ctx.band_sl, cen, radii, fits.rms[c])
    flare = (
        fitted
        & (centers_h < cfg.breast_height)
        & (np.hypot(*(cen - pred).T) <= r_med + radii)
        & ((~m & (radii > r_med + tol)) | (out_f > BUTTRESS_OUTSIDE))
    )
    # a buttress starts at the ground: only the run of flared slices from the lowest up;
    # and above it the stem is clean (a spruce's whorls put branch points around the
    # stem at every height, which is not a buttress)
    flare &= np.cumprod(flare | (centers_h < centers_h[fitted].min())).astype(bool)
    above = fitted & ~flare & (centers_h > centers_h[flare].max() if flare.any() else False)
    if flare.any() and (not above.any() or out_f[above].max() > BUTTRESS_OUTSIDE / 2):
        flare[:] = False
    h_meas = cfg.breast_height
    rule = RULE_BH
    if flare.any() and not ctx.slice_cloud:
        top = float(centers_h[flare].max() + cfg.slice_thickness / 2)
        if top + BUTTRESS_CLEARANCE > cfg.breast_height:
            h_meas = top + BUTTRESS_CLEARANCE
            rule = f"above buttress (swelling to {top:.2f} m)"
    return h_meas, rule


def _stem_at(
    fits: _SliceFits,
    c: int,
    m: NDArray[np.bool_],
    hh: FloatArray,
    cfg: StemConfig,
    at_slice: bool = False,
) -> tuple[float, FloatArray, float, float, FloatArray] | None:
    """Radius, centre (2,), taper (dr/dh, NaN when not estimated), radius variance and
    centre covariance (2, 2) of cluster ``c`` at ``hh = 0`` (``hh``: the kept slices'
    heights relative to the measurement height); None when the taper is too steep for a stem.

    With >= 3 slices spanning >= 0.3 m: robust Theil-Sen lines (Theil 1950, Sen 1968) through
    the slices' radii and centres (taper, lean), rejected if |dr/dh| > ``cfg.max_taper`` (a
    sphere or a bush changes radius fast with height), uncertainty by
    :func:`~stemmap.cloud.uncertainty._line_uncertainty`; the radius is corrected for lean
    (the horizontal section of a stem leaning by theta is an ellipse with axes d / cos(theta)
    and d; a circle fit returns about their mean, so the diameter across the axis is
    2 cos(theta) / (1 + cos(theta)) of it, first order). Otherwise the slices' weighted mean
    (weights inliers / rms^2), uncertainty by
    :func:`~stemmap.cloud.uncertainty._mean_uncertainty`.

    ``at_slice`` (a plot's band thickened to a few slices, ``StemConfig.thick_dbh_slice``):
    the radius (and its variance) is the kept slice's that holds the measurement height
    (within half a slice thickness), lean-corrected; the line still gives the centre, the
    lean and the taper test. Three 0.4 m slices put the line's outer points at 0.8-1.2 m
    (root flare) and 1.6-2.0 m (crown base, branch whorls): one flared or cluttered slice
    tilts a Theil-Sen line through three radii, and the 1.2-1.6 m slice measures the stem
    where the DBH is defined (treels pine_plot at 20 %, seed 0: a stem whose slices fit
    r = 8.64 / 6.55 / 8.06 cm came out 16.8 cm from the line against a 13.3 cm ring;
    docs/algorithms/cloud.md "Sparse plots: DBH from the slice at breast height").
    """
    radii, cen = fits.radii[c, m], fits.centers[c, m]
    cov_i = fits.cov[c, m]
    if m.sum() >= 3 and np.ptp(hh) >= 0.3:
        # robust (Theil-Sen) line through the slices (taper, lean), at breast height: one
        # slice spoilt by a branch or a shrub does not tilt it
        coef_r = _theil_sen(hh, radii)
        coef_x = _theil_sen(hh, cen[:, 0])
        coef_y = _theil_sen(hh, cen[:, 1])
        taper = float(coef_r[1])
        if abs(taper) > cfg.max_taper:
            return None  # radius changes too fast with height for a stem (bush, boulder)
        r_bh = float(coef_r[0])
        cxy = np.array([coef_x[0], coef_y[0]])
        var_r, cov_xy = _line_uncertainty(hh, radii, cen, (coef_r, coef_x, coef_y), cov_i)
        # lean: the horizontal slice of a stem leaning by theta is an ellipse with axes
        # d / cos(theta) and d; a circle fit returns about their mean, so the diameter
        # across the axis is 2 cos(theta) / (1 + cos(theta)) of it (first order)
        cos_t = 1.0 / math.sqrt(1.0 + coef_x[1] ** 2 + coef_y[1] ** 2)
        on = np.flatnonzero(np.abs(hh) <= cfg.slice_thickness / 2 + 1e-9)
        if at_slice and on.size:
            # the kept slice that holds the measurement height: its own radius
            k = int(on[np.argmin(np.abs(hh[on]))])
            r_bh, var_r = float(radii[k]), float(cov_i[k, 2, 2])
        r_bh *= 2 * cos_t / (1 + cos_t)
    else:
        w = fits.weights[c, m]
        r_bh = float(np.average(radii, weights=w))
        cxy = np.average(cen, axis=0, weights=w)
        taper = math.nan
        var_r, cov_xy = _mean_uncertainty(cov_i)
    return r_bh, cxy, taper, var_r, cov_xy


def _ends_in_band(agree: _Agreement, ctx: _BandContext, cfg: StemConfig) -> bool:
    """True when the agreeing slices of a candidate end below the band's top slice and the
    band holds no return about its circle above them: the object ends inside the band.

    A trunk goes on above the 0.8-2.0 m band; a shrub, a sapling's clump of twigs or a stack
    of debris ends. The pooled band fit asks for inliers in the top slice
    (:func:`~stemmap.cloud.pooled._pooled_row`); the per-slice path asked for nothing above
    its agreeing slices, so three slices of a 1.6 m object passed (treels pine_plot with
    1 cm noise or tilted 10 degrees: a 23-25 cm "stem" at (6.2, 3.0) m fitted at 1.1-1.5 m,
    no return within its radius + 5 cm at 1.6-2.0 m; as shipped, a 6.3 cm one at
    (1.09, 9.68) m fitted at 1.1-1.7 m, none within 50 cm at 1.71-2.88 m;
    docs/algorithms/cloud.md "Plots at lower density: the lost stems, stage by stage").
    The test is weaker than the pooled one, so that occlusion or a sparse cloud does not
    reject a real trunk: one band return (before the vertical filter) more than a quarter
    slice above the top agreeing slice's upper edge (the ground model's and the points' own
    height scatter: an object cut flat at the edge has returns a few mm above it) within
    2 r of the centre the stem's line predicts at a higher slice, plus
    :data:`CONTINUE_LEAN` x the height above the top agreeing slice (an extrapolated centre
    is off by the lean the line did not see; the pooled fit's 10 degree bound), is enough.
    Only an absence counts: on treels pine_plot at 20 % (seed 0) a 14.9 cm stem's thin
    re-measure has its nearest return above 1.85 m 9.5 cm from the predicted centre (r
    6.7 cm), while the two objects above have none within 1.6 / 0.55 m. *Limit:* a snag
    broken off inside the band (1.3-1.9 m tall) is rejected with the shrubs."""
    top = int(np.flatnonzero(agree.kept).max())
    ch = ctx.centers_h
    if ctx.tree is None or top == ch.shape[0] - 1:
        return False
    above = float(ch[top]) + 0.75 * cfg.slice_thickness
    for s in range(top + 1, ch.shape[0]):
        reach = 2.0 * agree.radius + CONTINUE_LEAN * float(ch[s] - ch[top])
        idx = np.asarray(ctx.tree.query_ball_point(agree.pred[s], reach), dtype=np.int64)
        if np.any(ctx.band.h[idx] > above):
            return False
    return True


def _consensus_floor(ctx: _BandContext, cfg: StemConfig) -> float:
    """The RMS floor of the radius consensus weights: the pooled noise floor where
    ``cfg.consensus_floor`` is on and the floor is pooled over stems, else 0 (none)."""
    return ctx.noise_floor if cfg.consensus_floor and not ctx.own_floor else 0.0


def _se_floor(ctx: _BandContext, cfg: StemConfig) -> float | None:
    """None (the consensus by fit weights) unless ``cfg.consensus_radius_se``; then the RMS
    floor of the slices' radius standard errors (:func:`_radius_se`): the pooled noise floor
    in a plot, 0 (none) where the floor is one candidate's own."""
    if not cfg.consensus_radius_se:
        return None
    return 0.0 if ctx.own_floor else ctx.noise_floor


def _slice_stem(
    fits: _SliceFits, c: int, ctx: _BandContext, cfg: StemConfig
) -> tuple[tuple[float, ...], str] | None:
    """Step 8 for cluster ``c``: its row ``(x, y, dbh, n_points, quality, arc, rms,
    n_slices, taper, dbh_std, cov_xx, cov_xy, cov_yy, dbh_height)`` and DBH rule, or None
    when it is no stem.

    Tests, in order: >= ``cfg.min_slices`` consistent slices (:func:`_consistent_slices`;
    with fewer, the others refitted from the stem's predicted circle, :func:`_guided_refits`)
    spanning >= ``cfg.min_vertical_extent`` (not a bush, a boulder or a branch stub; not
    for a pre-cut slice), returns above them when they end inside the band
    (:func:`_ends_in_band`, ``cfg.continues_above``), the taper (:func:`_stem_at`).
    Quality = fraction of the present slices kept x min(1, arc / 120 deg) x min(1, noise
    floor / RMS).
    """
    centers_h = ctx.centers_h
    agree = _consistent_slices(fits, c, centers_h, _consensus_floor(ctx, cfg), _se_floor(ctx, cfg))
    if agree.kept.sum() < cfg.min_slices:
        refit = _guided_refits(fits, c, agree, ctx, cfg)
        if refit is None:
            return None
        # the refits passed the agreement tests against this stem: no second vote
        fits, c, m = refit[0], 0, agree.kept | refit[1]
        if m.sum() < cfg.min_slices:
            return None
        r_new = float(np.median(fits.radii[0, m]))
        pred = _centre_line(centers_h[m], fits.centers[0, m], centers_h)
        agree = _Agreement(m, r_new, agree.tol, pred)
    m = agree.kept
    if not ctx.slice_cloud and np.ptp(centers_h[m]) < cfg.min_vertical_extent - 1e-9:
        return None  # not a vertical structure (a bush, a boulder, a branch stub)
    if cfg.continues_above and not ctx.slice_cloud and _ends_in_band(agree, ctx, cfg):
        return None  # a shrub, a sapling's clump or stacked debris: a stem goes on above
    h_meas, rule = _measurement_height(fits, c, agree, ctx, cfg)
    at_slice = (ctx.few_thick and cfg.thick_dbh_slice) or cfg.dbh_from == "slice"
    at = _stem_at(fits, c, m, centers_h[m] - h_meas, cfg, at_slice)
    if at is None:
        return None
    r_bh, cxy, taper, var_r, cov_xy = at
    path = ""
    if cfg.dbh_from == "median" and not at_slice and math.isfinite(taper):
        # the slices about the measurement height, not the line through a flared profile
        near = near_median_radius(
            fits.radii[c, m],
            fits.centers[c, m],
            fits.cov[c, m, 2, 2],
            centers_h[m] - h_meas,
            cfg.slice_thickness,
        )
        if near is not None:
            r_bh, var_r, path = near[0], near[1], "median"
    # the variance from its parts: fit noise, the section's change (cfg.dbh_sd_scatter)
    hh = centers_h[m] - h_meas
    if not math.isfinite(taper):
        path = "mean"
    elif path != "median":
        on = at_slice and bool(np.any(np.abs(hh) <= cfg.slice_thickness / 2 + 1e-9))
        path = "slice" if on else "line"
    var_r = dbh_variance(
        var_r,
        fits.radii[c, m],
        fits.cov[c, m, 2, 2],
        hh,
        path,
        cfg.slice_thickness,
        cfg.dbh_sd_scatter,
        fits.weights[c, m],
    )
    frac = float(m.sum()) / max(int(fits.present[c]), 1)
    arc = float(np.mean(fits.arcs[c, m]))
    rr = float(np.mean(fits.rms[c, m]))
    q = frac * min(1.0, arc / 120.0) * min(1.0, ctx.noise_floor / max(rr, 1e-6))
    row = (
        cxy[0],
        cxy[1],
        2 * r_bh,
        int(fits.n_in[c, m].sum()),
        q,
        arc,
        rr,
        int(m.sum()),
        taper,
        2 * math.sqrt(var_r),
        cov_xy[0, 0],
        cov_xy[0, 1],
        cov_xy[1, 1],
        h_meas,
    )
    return row, rule


def _thin_slice_stem(
    fits: _SliceFits,
    c: int,
    ctx: _BandContext,
    ctx_thin: _BandContext,
    cfg_thin: StemConfig,
) -> tuple[tuple[float, ...], str] | None:
    """Cluster ``c``'s stem, found on the thick slices of a sparse cloud (``fits``, ``ctx``),
    measured again on the default thin slices (``ctx_thin``, ``cfg_thin``); None when fewer
    than ``cfg_thin.min_slices`` thin slices give a fit, and the thick measurement stands.

    A sparse band is cut into fewer, thicker slices so that a slice holds enough points to
    *find* a stem among the clutter (:func:`~stemmap.cloud.band._adapt_slices`; from a
    spacing of 75 mm on, 3 slices of 0.4 m). Its DBH then comes from a line through three
    radii, the lowest of which (0.8-1.2 m) takes in the root flare: on treels pine_plot at
    20 % the ten full-ring stems came out 1.0 cm too large on average (0.35 cm on the cloud
    as shipped). Once the stem is known, clutter no longer competes: each thin slice is fitted
    to the band's points about the circle the thick slices predict there
    (:func:`_annulus_fit`, the guided refit's test, with its scale: :func:`_annulus_noise`),
    and the stem is measured from the thin
    slices that pass as on a dense cloud (:func:`_slice_stem`: consistency, buttress,
    Theil-Sen line, lean). Only the measurement changes, not which stems are found.
    """
    agree = _consistent_slices(
        fits, c, ctx.centers_h, _consensus_floor(ctx, cfg_thin), _se_floor(ctx, cfg_thin)
    )
    m = agree.kept
    if ctx_thin.tree is None or m.sum() < 2:
        return None
    ch, ch_thin = ctx.centers_h, ctx_thin.centers_h
    pred = _centre_line(ch[m], fits.centers[c, m], ch_thin)
    h_ref = float(np.mean(ch[m]))
    noise = _annulus_noise(fits, c, m, ctx, cfg_thin)
    ns = ch_thin.shape[0]
    out = _SliceFits(
        passed=np.zeros((1, ns), dtype=bool),
        fitted=np.zeros((1, ns), dtype=bool),
        centers=np.full((1, ns, 2), np.nan),
        radii=np.full((1, ns), np.nan),
        rms=np.full((1, ns), np.nan),
        arcs=np.zeros((1, ns)),
        n_in=np.zeros((1, ns), dtype=np.int64),
        weights=np.zeros((1, ns)),
        cov=np.full((1, ns, 3, 3), np.nan),
        present=np.zeros(1, dtype=np.int64),
    )
    for s in range(ns):
        slack = cfg_thin.max_taper * abs(float(ch_thin[s]) - h_ref)
        fit = _annulus_fit(ctx_thin, s, pred[s], agree.radius, agree.tol, slack, cfg_thin, noise)
        if fit is not None:
            _set_slice(out, s, fit)
    out.present[0] = int(out.passed[0].sum())
    if out.present[0] < cfg_thin.min_slices:
        return None
    return _slice_stem(out, 0, ctx_thin, cfg_thin)
