"""Why a trunk candidate is dropped: the segment filters and fit plausibility tests of
:class:`~stemmap.scan.detect.ScanTrunkDetector` as reason codes.

Each test returns, per candidate segment, the code of the *first* test it fails (0 = kept), in
the order the detector applies them. The detector keeps exactly the candidates with code 0 (the
same boolean logic as before the codes existed: ``tests/scan/test_detect_fast.py`` checks the
numpy path against the compiled one), and :func:`rejected_candidates` lists the others with
their reason (``stemmap detect --rejected FILE``).

Segments with fewer than ``min_points`` returns right after segmentation (single stray returns,
leaves, grass) are not candidates and are never listed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.scan.features import SegmentFeatures, is_straight, line_bulge_gain
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted
    from stemmap.types import ScanBatch

__all__ = [
    "PIECE_REASONS",
    "REASONS",
    "biweight_scale",
    "fit_reasons",
    "fitted_reasons",
    "interior_triples",
    "own_noise",
    "range_roughness",
    "rejected_candidates",
    "residual_smoothness",
    "rms_limit",
    "robust_residual_scale",
    "scan_noise",
    "scan_noise_estimates",
    "segment_reasons",
    "segment_sigma",
]

#: ``straight_curvature``: the bend of :func:`~stemmap.scan.features.line_bulge_gain` is
#: significant towards the sensor at the chi-square straightness test's 1 %: one-sided, the
#: curvature's z-score above z_0.99 = 2.326, i.e. the gain above 2.326^2 sigma^2
STRAIGHT_BEND_CHI2 = 5.411894431054339

#: 1.4826 MAD -> sigma of a Gaussian, / sqrt(6): std of a second difference of iid noise
_ROUGH = 1.4826 / math.sqrt(6.0)


def range_roughness(segs: Segments) -> FloatArray:
    """Robust scale of range noise plus bark roughness of every segment, metres.

    ``1.4826 median_i |r_{i-1} - 2 r_i + r_{i+1}| / sqrt(6)`` over the consecutive returns of
    the segment: for i.i.d. range errors of std s the second difference has std sqrt(6) s, and
    the median ignores the few large differences a trunk's curvature gives near its edges
    (0 for segments of < 3 returns). Ours (issue 11): the detector's sigma per segment is
    ``max(sigma, roughness)``, so rough bark widens the fit's Huber scale and the RMS test
    instead of failing them. Same arithmetic as the compiled path (``_range_roughness``).
    """
    r = segs.points.r
    out = np.zeros(len(segs))
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        m = int(b - a) - 2
        if m < 1:
            continue
        seg = r[a:b]
        d = np.sort(np.abs(seg[:-2] - 2.0 * seg[1:-1] + seg[2:]))
        h = m // 2
        med = d[h] if m % 2 == 1 else 0.5 * (d[h - 1] + d[h])
        out[j] = _ROUGH * med
    return out


#: Fewest continuous beam triples a scan needs for its own noise estimate (fewer: 0, i.e. the
#: configured sigma stands).
SCAN_NOISE_MIN_TRIPLES = 16


def scan_noise(
    ranges: ArrayLike,
    jump: float,
    surface: float = 0.0,
    missing: float = 0.0,
    pool: bool = False,
    batch_min: float = math.inf,
    batch_scale: str = "mad",
    triples: tuple[list[FloatArray], list[int]] | None = None,
) -> FloatArray:
    """Range-noise scale of every scan from all its returns, metres (ours, issue 11).

    ``1.4826 MAD(d) / sqrt(6)``, ``MAD(d) = median |d_k - median d|``, of the second
    differences ``d_k = r_{k-1} - 2 r_k + r_{k+1}`` over every interior triple of a
    continuous run: a triple of adjacent beams is continuous when all three returned and its
    two range steps are both at most ``jump`` (walls, ground, bushes, every trunk of the scan
    together), and interior when the triples on both sides are continuous too. A run's end
    triples hold its silhouette beam (grazing incidence, and on a footprint-averaging scanner
    a mixed return); in a scene of many short runs they are a large share and raised the
    estimate above the sensor's noise (the simulated demo: 1.6 cm read for 1 cm, 1.1 cm
    without them; scan-detection-history.md, seventh round). For i.i.d. Gaussian range errors
    of std s the second difference has std sqrt(6) s (coefficients 1, -2, 1) and 1.4826 x its
    MAD estimates that std. The surfaces' own shape adds a positive part: a wall or trunk seen
    from outside is convex in range, ``d ~ r (1 + 2 tan^2 psi) dtheta^2`` (psi: incidence
    angle; 0.8 mm at 10 m, 0.5 deg, square on), steep near a trunk's silhouette; centring the
    MAD on the median removes its common part (on the real slices without noise: 0.3-1.0 cm
    against 0.3-1.5 cm about 0, scan-detection-history.md, sixth round), and the median ignores the
    edges, twigs and one rough trunk that a single segment's estimate
    (:func:`range_roughness`) cannot tell from noise. 0 (the configured sigma stands) where
    fewer than :data:`SCAN_NOISE_MIN_TRIPLES` interior triples exist or where one run of
    them (one surface) holds more than half of them: the median's breakdown point, so no
    single object decides the estimate (a single-tree scan of a rough trunk would measure
    its bark, as a segment's own estimate does). Last, the share ``surface`` of the surfaces'
    own shape and roughness is taken out in quadrature, ``sqrt(max(e^2 - surface^2, 0))``.
    ``missing`` is returned where there is no estimate (NaN tells "no estimate" from "less
    than ``surface``"; ``rms_noise_from_fit``).

    ``pool`` (issue 11, sixteenth round): the scans of the batch with too few interior
    triples for an estimate of their own share one, the same statistic over the union of
    their triples, under the same two rules (at least :data:`SCAN_NOISE_MIN_TRIPLES` triples,
    no single run holding more than half). The range noise is the sensor's, not the scan's: a
    breast-height scan of a few trunks in the open at 0.5-1 degree steps holds 0-15 interior
    triples, many such scans together enough. A scan refused for one surface holding most
    of its triples is not pooled: that surface (one tree seen from many sides) would decide
    the union too. Scans with their own estimate keep it (bit for bit).

    ``batch_min`` (issue 11, Dec 4, "Range noise on sparse scans"; ``scan_noise_batch``):
    every scan still without an estimate (too few triples, one run holding more than half,
    or refused by the pool) takes the batch's, the same statistic over the interior triples
    of *every* scan of the batch together (at least :data:`SCAN_NOISE_MIN_TRIPLES`, no run
    holding more than half of them), when that estimate is at least ``batch_min`` metres. The
    union is dominated by the scans with many triples (walls, large trunks, long runs), whose
    second differences hold the least surface curvature, unlike the union of the sparse
    scans alone (``pool``: the TreeLS plot without noise at 0.5 deg reads 2.1 cm raw there,
    0.7 cm over every scan). The floor keeps bark from passing as noise: over a single tree
    seen from every side the union reads the bark (aRchi, no noise: up to 1.3 cm raw) as the
    sparse scans do, so the batch only speaks when it reads a scanner clearly noisier than
    configured (the detector passes ``scan_noise_batch x sigma``). ``inf``: off.

    ``batch_scale`` (Dec 5, "The batch's noise from few triples"; ``batch_noise_scale``): the
    scale statistic of that batch estimate, ``"mad"`` (the statistic above) or ``"biweight"``
    (:func:`biweight_scale`: as robust to a few surface tails, about three quarters of the MAD's
    sampling spread on the 20-60 triples a batch of sparse slice scans holds at 1 deg). The scans'
    own estimates and the pool keep the MAD.

    Parameters
    ----------
    ranges : array_like of shape (S, N), metres, gated (NaN / inf = no return), beam order
    jump : float, metres, > 0 -- largest range step inside a continuous triple
    surface : float, metres, >= 0 -- the surfaces' own share of the estimate
    batch_min : float, metres -- smallest batch estimate shared (``inf``: off)
    batch_scale : "mad" or "biweight" -- the batch estimate's scale statistic
    triples : :func:`interior_triples` of ``ranges`` and ``jump``, if already found (the
        detector estimates up to three scales from one batch)
    """
    r = np.atleast_2d(np.asarray(ranges, dtype=np.float64))
    out = np.full(r.shape[0], missing)
    if r.shape[1] < 5:
        return out
    lacking: list[int] = []
    pooled: list[FloatArray] = []
    pool_longest = 0
    unset = np.ones(r.shape[0], dtype=bool)
    every: list[FloatArray] = []
    every_longest = 0
    if triples is None:
        triples = interior_triples(r, jump)
    for s, (v, longest) in enumerate(zip(*triples, strict=True)):
        every.append(v)
        every_longest = max(every_longest, longest)
        if v.shape[0] >= SCAN_NOISE_MIN_TRIPLES and 2 * longest <= v.shape[0]:
            out[s] = _noise_estimate(v, surface)
            unset[s] = False
        elif pool and v.shape[0] < SCAN_NOISE_MIN_TRIPLES:
            lacking.append(s)
            pooled.append(v)
            pool_longest = max(pool_longest, longest)
    if lacking:
        v = np.concatenate(pooled)
        if v.shape[0] >= SCAN_NOISE_MIN_TRIPLES and 2 * pool_longest <= v.shape[0]:
            out[lacking] = _noise_estimate(v, surface)
            unset[lacking] = False
    if batch_min < math.inf and unset.any():
        v = np.concatenate(every)
        if v.shape[0] >= SCAN_NOISE_MIN_TRIPLES and 2 * every_longest <= v.shape[0]:
            e = _noise_estimate(v, surface, batch_scale)
            if e >= batch_min:
                out[unset] = e
    return out


def scan_noise_estimates(
    raw: FloatArray, cfg: DetectorConfig
) -> Callable[[float, bool, float], FloatArray]:
    """:func:`scan_noise` of the gated ranges ``raw`` (S, N) with
    ``cfg``'s jump, surface and batch scale, as a function of its ``(missing, pool,
    batch_min)``: the detector asks for up to three estimates of one batch (the tests' sigma,
    the step threshold's, the fits' weights), so the interior triples are found once and an
    estimate asked for twice (with ``step_noise_pool="batch"`` and ``fit_noise_floor``) is
    computed once. The same arrays as separate calls, bit for bit."""
    r = np.atleast_2d(np.asarray(raw, dtype=np.float64))
    triples: tuple[list[FloatArray], list[int]] | None = None
    memo: dict[tuple[bool, float, bool, float], FloatArray] = {}

    def estimate(missing: float, pool: bool, batch_min: float) -> FloatArray:
        nonlocal triples
        key = (math.isnan(missing), 0.0 if math.isnan(missing) else missing, pool, batch_min)
        if key not in memo:
            if triples is None and r.shape[1] >= 5:
                triples = interior_triples(r, cfg.scan_noise_jump)
            memo[key] = scan_noise(
                r,
                cfg.scan_noise_jump,
                cfg.scan_noise_surface,
                missing,
                pool=pool,
                batch_min=batch_min,
                batch_scale=cfg.batch_noise_scale,
                triples=triples,
            )
        return memo[key]

    return estimate


def interior_triples(ranges: FloatArray, jump: float) -> tuple[list[FloatArray], list[int]]:
    """Per scan of ``ranges`` (S, N >= 5), the second differences of its interior continuous
    beam triples in beam order and the longest run of consecutive ones: the sample
    :func:`scan_noise` estimates from (a triple is continuous when its three returns are
    finite and its two range steps at most ``jump``; interior when the triples on both sides
    are continuous too)."""
    r = ranges
    a, b, c = r[:, :-2], r[:, 1:-1], r[:, 2:]
    with np.errstate(invalid="ignore"):
        cont = np.isfinite(a) & np.isfinite(b) & np.isfinite(c)
        cont &= (np.abs(b - a) <= jump) & (np.abs(c - b) <= jump)
        d = (a - 2.0 * b + c)[:, 1:-1]
    # interior triples: both neighbouring triples continuous too (no silhouette beam)
    ok = cont[:, :-2] & cont[:, 1:-1] & cont[:, 2:]
    values: list[FloatArray] = []
    runs: list[int] = []
    for s in range(r.shape[0]):
        values.append(d[s][ok[s]])
        # longest run of consecutive qualifying triples
        edges = np.flatnonzero(np.diff(np.concatenate(([0], ok[s].astype(np.int8), [0]))))
        runs.append(int(np.max(edges[1::2] - edges[::2])) if edges.size else 0)
    return values, runs


def _noise_estimate(v: FloatArray, surface: float, scale: str = "mad") -> float:
    """:func:`scan_noise`'s statistic of the second differences ``v`` (``scale`` "biweight":
    :func:`biweight_scale`)."""
    if scale == "biweight":
        e = biweight_scale(v) / math.sqrt(6.0)
    else:
        e = _ROUGH * float(np.median(np.abs(v - np.median(v))))
    return math.sqrt(max(e * e - surface * surface, 0.0))


#: Tuning constant of :func:`biweight_scale`, in MADs: Mosteller & Tukey's (1977) c = 6 of the
#: biweight; values beyond 6 MAD (4 sigma) from the median weigh nothing.
BIWEIGHT_C = 6.0

#: :func:`biweight_scale`'s raw statistic for Gaussian data is 1.0462 sigma at c = 6
#: (2 x 10^6 draws, three runs 1.0460-1.0473): divided out, so it estimates sigma.
BIWEIGHT_GAUSS = 1.0462


def biweight_scale(v: FloatArray) -> float:
    """Biweight midvariance scale of ``v`` (Mosteller & Tukey 1977, *Data Analysis and
    Regression*, ch. 10; Lax 1985, JASA 80, eq. for s_bi; the form of Beers, Flynn & Gebhardt
    1990, AJ 100, eq. 9), made consistent for Gaussian data (:data:`BIWEIGHT_GAUSS`):

    ``u_i = (v_i - M) / (c MAD)``, ``s = sqrt(n sum_{|u|<1} (v_i - M)^2 (1 - u_i^2)^4) /
    |sum_{|u|<1} (1 - u_i^2)(1 - 5 u_i^2)|``, M the median, c = :data:`BIWEIGHT_C`.

    Its breakdown point is the MAD's (a value beyond c MAD weighs nothing; a surface's
    curvature tails and a few bark flakes do not move it), its Gaussian efficiency higher:
    over the second differences of i.i.d. noise (4 000 draws), 21 values, the estimate's
    spread is 0.234 sigma against the MAD's 0.308 (5-95 %: 0.62-1.40 against 0.57-1.57), 50
    values 0.150 against 0.197. 0 when the MAD is 0 (more than half the values equal). The
    sums run in the order of ``v`` (``np.cumsum``), as the compiled twin's loop
    (``_fast_robust._biweight_scale``) does: the same value bit for bit."""
    m = float(np.median(v))
    s = float(np.median(np.abs(v - m)))
    if not s > 0.0:
        return 0.0
    u = (v - m) / (BIWEIGHT_C * s)
    w = np.abs(u) < 1.0
    d = v[w] - m
    uu = u[w] * u[w]
    t = 1.0 - uu
    t2 = t * t
    num = math.sqrt(v.shape[0] * float(np.cumsum(d * d * (t2 * t2))[-1]))
    den = abs(float(np.cumsum(t * (1.0 - 5.0 * uu))[-1]))
    return num / den / BIWEIGHT_GAUSS if den > 0.0 else 0.0


def segment_sigma(cfg: DetectorConfig, segs: Segments, mean_r: FloatArray) -> FloatArray:
    """Range-noise sigma of every segment: ``sigma + sigma_rel x mean range``, with
    ``sigma_from_scan`` at least its scan's own estimate (:func:`scan_noise`, carried in
    ``segs.points.noise``; only where a sigma is configured: sigma 0 lets the fit estimate its
    scale). ``outline_floor_points``: each scan's floor (``segs.points.floor``,
    :mod:`stemmap.scan._outline_floor`) in place of ``sigma``. Same arithmetic as the compiled
    path."""
    floor = segs.points.floor  # outline_floor_points: each scan's floor in place of sigma
    base: float | FloatArray = cfg.sigma if floor is None else floor[segs.scan]
    sigma: FloatArray = base + cfg.sigma_rel * mean_r
    noise = segs.points.noise
    if cfg.sigma_from_scan and noise is not None and (cfg.sigma > 0 or cfg.sigma_rel > 0):
        sigma = np.fmax(sigma, noise[segs.scan])  # (NaN: no estimate, rms_noise_from_fit)
    return sigma


#: Reason codes (index = code). Segment filters first, then the fit tests.
REASONS: tuple[str, ...] = (
    "kept",
    "min_points",  # fewer returns than min_points
    "min_points_partial",  # occluded / truncated end and fewer than min_points_partial
    "max_points",
    "width",  # edge-beam chord outside [min_width, max_width]
    "depth",  # sagitta towards the sensor below min_depth
    "curvature",  # cluster curvature outside [min_curvature, max_curvature]
    "straight",  # line residual is pure noise (is_straight)
    "partial",  # drop_partial
    "fit_failed",  # the circle fit did not converge / degenerate
    "radius",  # fitted radius outside [min_radius, max_radius]
    "radius_width_ratio",  # radius > max_radius_width_ratio x silhouette width
    "centre_in_front",  # fitted centre nearer than the returns
    "rms",  # RMS (or robust residual scale) > max_rms_sigma x sigma
    "precision",  # the fit's diameter std 2 sqrt(C_rr) > max_dbh_sd (first echo, numpy path)
)
_CODE = {name: i for i, name in enumerate(REASONS)}


def robust_residual_scale(segs: Segments, centers: FloatArray, radii: FloatArray) -> FloatArray:
    """``1.4826 median_i | |p_i - c| - r |`` per segment: the residual scale of a circle fit that
    a few returns off the circle (a branch stub, a mixed pixel, a bark ridge) do not inflate,
    unlike the RMS (ours, issue 11: the RMS test rejected real bark). Same arithmetic as the
    compiled path (``_robust_residual_scale``)."""
    p = segs.points
    out = np.full(len(segs), np.nan)
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        d = np.sort(np.abs(np.hypot(p.x[a:b] - centers[j, 0], p.y[a:b] - centers[j, 1]) - radii[j]))
        m = d.shape[0]
        h = m // 2
        out[j] = 1.4826 * (d[h] if m % 2 == 1 else 0.5 * (d[h - 1] + d[h]))
    return out


#: Fewest returns of a candidate whose residual smoothness is measured (three second
#: differences; fewer: NaN, and the lobe allowance of the RMS test does not apply).
SMOOTH_MIN_POINTS = 8


def residual_smoothness(segs: Segments, centers: FloatArray, radii: FloatArray) -> FloatArray:
    """High-frequency scale of a circle fit's residuals along the arc, metres (ours, issue 11).

    ``1.4826 median_i |e_{i-1} - 2 e_i + e_{i+1}| / sqrt(6)`` of the orthogonal residuals
    ``e_i = |p_i - c| - r`` in beam order, the statistic of :func:`range_roughness` on the
    residuals instead of the ranges: for i.i.d. noise of std s it estimates s, while a smooth
    deviation from the circle (a lobe, an ellipse, a buttress flank) that changes little from
    one return to the next adds almost nothing to it (a sinusoid of amplitude A and k returns
    per period adds ``2 (1 - cos(2 pi / k)) A``, 0.38 A at k = 10). Scattered returns (a bush,
    twigs, a clump of stems) raise it as much as their RMS. NaN for fewer than
    :data:`SMOOTH_MIN_POINTS` returns or a failed fit."""
    p = segs.points
    out = np.full(len(segs), np.nan)
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        m = int(b - a) - 2
        if m + 2 < SMOOTH_MIN_POINTS or not np.isfinite(radii[j]):
            continue
        e = np.hypot(p.x[a:b] - centers[j, 0], p.y[a:b] - centers[j, 1]) - radii[j]
        d = np.sort(np.abs(e[:-2] - 2.0 * e[1:-1] + e[2:]))
        h = m // 2
        out[j] = _ROUGH * (d[h] if m % 2 == 1 else 0.5 * (d[h - 1] + d[h]))
    return out


def own_noise(
    cfg: DetectorConfig, segs: Segments, sigma: FloatArray, smooth: FloatArray
) -> FloatArray:
    """The candidate's own range noise with ``rms_noise_from_fit`` (ours, issue 11, twelfth
    round): ``smooth`` (:func:`residual_smoothness`) where it lies in ``(sigma,
    rms_noise_from_fit x sigma]`` on a scan without its own noise estimate (:func:`scan_noise`
    NaN, or ``sigma_from_scan`` off), ``sigma`` elsewhere. Where the scan measured its noise
    on its walls, ground and trunks, a candidate rougher than that is rough itself (a rock, a
    bush), not a trunk in a noisy scan; and one rougher than the cap is no noisy trunk either
    (the simulated demo's rocks read 2-13 cm, the real slices' trunks at 3 cm of range noise
    1.7-4.8 cm, one 7.1; scan-detection-history.md, twelfth round)."""
    noise = segs.points.noise
    unknown = np.ones(len(segs), dtype=bool)
    if cfg.sigma_from_scan and noise is not None:
        unknown = ~np.isfinite(noise[segs.scan])
    with np.errstate(invalid="ignore"):
        use = unknown & (smooth > sigma) & (smooth <= cfg.rms_noise_from_fit * sigma)
    out: FloatArray = np.where(use, smooth, sigma)
    return out


def _first_failure(codes: NDArray[np.int8], fails: NDArray[np.bool_], name: str) -> None:
    codes[(codes == 0) & fails] = _CODE[name]


def segment_reasons(
    segs: Segments,
    f: SegmentFeatures,
    cfg: DetectorConfig,
    least: NDArray[np.int64] | None = None,
) -> NDArray[np.int8]:
    """Reason code per segment of the segment filters (Zheng et al. 2012 §3.2 criteria 1, 3, 4;
    Xue et al. 2018 eq. 12 width window; ours: partial-segment minimum, straightness).
    ``least`` (K,): the returns each segment needs in place of ``min_points``
    (``mixed_end_min_points``, :func:`~stemmap.scan._mixed_end.least_points`)."""
    codes = np.zeros(len(segs), dtype=np.int8)
    need = cfg.min_points if least is None else least
    _first_failure(codes, f.n_points < need, "min_points")
    _first_failure(
        codes, segs.partial & (f.n_points < cfg.min_points_partial), "min_points_partial"
    )
    if cfg.max_points is not None:
        _first_failure(codes, f.n_points > cfg.max_points, "max_points")
    _first_failure(codes, ~((f.width >= cfg.min_width) & (f.width <= cfg.max_width)), "width")
    _first_failure(codes, ~(f.depth >= cfg.min_depth), "depth")
    _first_failure(
        codes,
        ~((f.curvature >= cfg.min_curvature) & (f.curvature <= cfg.max_curvature)),
        "curvature",
    )
    if cfg.reject_straight:
        sigma = segment_sigma(cfg, segs, f.mean_range)
        straight = is_straight(
            f.line_rms,
            f.width,
            sigma,
            ratio=cfg.straight_ratio,
            n_points=f.n_points if cfg.straight_test == "chi2" else None,
        )
        # ours (issue 11): a sagitta of many sigmas is an arc, whatever the line's RMS says
        straight &= ~(f.depth > cfg.straight_depth_sigmas * sigma)
        if cfg.straight_curvature:  # ours (Dec 5): a significant bend towards the sensor
            straight &= ~(line_bulge_gain(segs) > STRAIGHT_BEND_CHI2 * sigma * sigma)
        _first_failure(codes, straight & (f.n_points >= cfg.straight_min_points), "straight")
    if cfg.drop_partial:
        _first_failure(codes, segs.partial, "partial")
    return codes


def fit_reasons(
    cfg: DetectorConfig,
    centers: FloatArray,
    radii: FloatArray,
    fit_ok: NDArray[np.bool_],
    sil_width: FloatArray,
    mean_r: FloatArray,
    rms: FloatArray,
    sigma: FloatArray,
    smooth: FloatArray | None = None,
    own: FloatArray | None = None,
) -> NDArray[np.int8]:
    """Reason code per fitted segment of the fit plausibility tests (ours): radius bounds, not
    near-flat (radius <= ratio x silhouette width), centre behind the visible surface, outline a
    circle within the noise (RMS <= max_rms_sigma x sigma; with ``rms_noise_from_fit`` the
    candidate's own noise ``own``, :func:`own_noise`), or with ``lobe_roughness`` a
    smooth lobed outline (the residuals' high-frequency scale ``smooth``,
    :func:`residual_smoothness`, within ``lobe_smooth_sigmas`` sigma and the RMS within the
    lobe allowance). Failed fits carry NaN."""
    codes = np.zeros(centers.shape[0], dtype=np.int8)
    with np.errstate(invalid="ignore"):
        _first_failure(codes, ~fit_ok, "fit_failed")
        _first_failure(codes, ~((radii >= cfg.min_radius) & (radii <= cfg.max_radius)), "radius")
        _first_failure(
            codes,
            ~(radii <= cfg.max_radius_width_ratio * np.maximum(sil_width, 1e-9)),
            "radius_width_ratio",
        )
        _first_failure(codes, ~(np.hypot(centers[:, 0], centers[:, 1]) > mean_r), "centre_in_front")
        if math.isfinite(cfg.max_rms_sigma):
            fails = ~(rms <= rms_limit(cfg, sigma, radii))
            if smooth is not None or own is not None:
                fails &= ~_relaxed_rms(cfg, radii, sil_width, rms, sigma, smooth, own)
            _first_failure(codes, fails, "rms")
    return codes


def _relaxed_rms(
    cfg: DetectorConfig,
    radii: FloatArray,
    sil_width: FloatArray,
    rms: FloatArray,
    sigma: FloatArray,
    smooth: FloatArray | None,
    own: FloatArray | None,
) -> NDArray[np.bool_]:
    """Candidates that fail the RMS test but pass it as a noisy or lobed trunk
    (``rms_noise_from_fit``, ``lobe_roughness``): residuals that are the white noise the
    candidate's own noise ``own`` (:func:`own_noise`) measures, ``RMS <= rms_own_sigmas x
    sqrt(own^2 + (bark_roughness r)^2)`` where ``own`` exceeds ``sigma`` (white noise of scale s
    has RMS ~ s, a lobe or a rock's face adds to the RMS more than to ``own``), or a smooth
    outline (``smooth <= lobe_smooth_sigmas x sigma``) within the lobe allowance; and in both
    cases a silhouette no wider than the circle, ``sil_width <= 2 r + 2 max_rms_sigma x own``
    (a circle's outline cannot be wider than its diameter: a bark ridge or a flat face fitted
    as a small circle is)."""
    s = sigma if own is None else own
    ok = np.zeros(rms.shape[0], dtype=bool)
    if own is not None:
        br = cfg.bark_roughness * radii
        ok |= (own > sigma) & (rms <= cfg.rms_own_sigmas * np.sqrt(own * own + br * br))
    if cfg.lobe_roughness > 0.0 and smooth is not None:
        lobed = rms <= rms_limit(cfg, sigma, radii, cfg.lobe_roughness)
        ok |= lobed & (smooth <= cfg.lobe_smooth_sigmas * sigma)
    out: NDArray[np.bool_] = ok & (sil_width <= 2.0 * radii + 2.0 * cfg.max_rms_sigma * s)
    return out


def fitted_reasons(cfg: DetectorConfig, fitted: _Fitted) -> NDArray[np.int8]:
    """:func:`fit_reasons` of the candidates of a detector's fit (``_fit_candidates``)."""
    codes = fit_reasons(
        cfg,
        fitted.centers,
        fitted.radii,
        fitted.ok,
        fitted.sil_width,
        fitted.mean_r,
        fitted.test_rms,
        fitted.sigma,
        fitted.smooth,
        fitted.own_noise,
    )
    if fitted.dbh_sd is not None:
        # max_dbh_sd: a diameter the returns did not measure (NaN covariance: not estimated)
        with np.errstate(invalid="ignore"):
            _first_failure(codes, fitted.dbh_sd > cfg.max_dbh_sd, "precision")
    return codes


def rms_limit(
    cfg: DetectorConfig, sigma: FloatArray, radii: FloatArray, roughness: float | None = None
) -> FloatArray:
    """Largest residual scale the RMS test accepts: ``max_rms_sigma x sigma`` or, with
    ``bark_roughness`` b > 0, ``max_rms_sigma x sqrt(sigma^2 + (b r)^2)`` (ours, issue 11): a
    real trunk's outline deviates from its best circle by a roughly constant fraction of its
    radius (bark ridges, ellipticity; the ring references of the real slices: 2.5-8 %), so a
    large trunk may be rougher than the sensor noise. ``roughness`` replaces b (the lobe
    allowance, ``lobe_roughness``). Same arithmetic as the compiled path."""
    k = cfg.max_rms_sigma
    b = cfg.bark_roughness if roughness is None else roughness
    if b > 0.0:
        br = b * radii
        out: FloatArray = k * np.sqrt(sigma * sigma + br * br)
        return out
    return k * sigma


def rejected_candidates(
    detector: ScanTrunkDetector, batch: ScanBatch, fate: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Every candidate segment of ``batch`` that fails the detector's tests, with the test it
    failed and what became of it.

    Runs the numpy reference pipeline once (no tilt compensation) and reads every
    candidate's fate from it; ``fate``: the record of a run that already happened
    (:meth:`~stemmap.scan.detect.ScanTrunkDetector._run_numpy` ``fate=``, on ``batch``),
    which is then not repeated. Returns columns (one entry per
    rejected candidate): ``scan_index``, ``reason``, ``n_points``, ``bearing_deg`` and
    ``range`` of the segment's mean return, ``width`` (edge-beam chord, m), ``partial`` (an end
    occluded or truncated), for fitted candidates ``x``, ``y``, ``radius``, ``rms`` and
    ``sigma`` (NaN when the candidate failed a segment filter), ``failed_test`` (the name of
    :data:`REASONS` of the first test the whole candidate failed), ``pieces`` (how many pieces
    the detector re-fitted from it: a corner, search or gap split, or its largest consistent
    arc; 0 when none) and ``pieces_accepted`` (how many of them it kept as trunks).
    ``reason`` is ``failed_test`` unless a piece was kept: then :data:`PIECE_REASONS`
    ``split`` (the candidate was a merged segment, its pieces are in the output in its place)
    or ``arc`` (its largest arc is); the candidate was then not dropped.
    """
    from stemmap.scan.features import segment_sum

    if fate is None:
        fate = {}
        detector._run_numpy(
            batch.ranges, batch.times, batch.angle_min, batch.angle_increment,
            batch.range_min, batch.range_max, batch.frame, None, None, fate=fate,
        )  # fmt: skip
    segs: Segments = fate["every"]
    k = len(segs)
    nan = np.full(k, np.nan)
    cols: dict[str, Any] = {"x": nan.copy(), "y": nan.copy(), "radius": nan.copy()}
    cols["rms"], cols["sigma"] = nan.copy(), nan.copy()
    codes = np.array(fate["seg_codes"], dtype=np.int8)  # a copy: the fit codes go in
    seg_passed = np.flatnonzero(codes == 0)  # candidates that passed the segment filters
    fitted = fate["fitted"]
    if seg_passed.size and fitted is not None:
        codes[seg_passed] = fate["fit_codes"]
        cols["x"][seg_passed], cols["y"][seg_passed] = fitted.centers[:, 0], fitted.centers[:, 1]
        cols["radius"][seg_passed], cols["rms"][seg_passed] = fitted.radii, fitted.rms
        cols["sigma"][seg_passed] = fitted.sigma
    rej = codes != 0
    tried, took, rescued = _piece_fates(fate, k, seg_passed)
    failed = [REASONS[c] for c in codes[rej]]
    p = segs.points
    n = np.maximum(segs.counts, 1)
    mx = segment_sum(p.x, segs) / n if k else nan
    my = segment_sum(p.y, segs) / n if k else nan
    width = fate["features"].width if k else nan
    return {
        "scan_index": segs.scan[rej],
        "reason": [r or f for r, f in zip(rescued[rej].tolist(), failed, strict=True)],
        "n_points": segs.counts[rej],
        "bearing_deg": np.degrees(np.arctan2(my, mx))[rej],
        "range": np.hypot(mx, my)[rej],
        "width": width[rej],
        "partial": segs.partial[rej],
        **{name: v[rej] for name, v in cols.items()},
        "failed_test": failed,
        "pieces": tried[rej],
        "pieces_accepted": took[rej],
    }


#: ``reason`` of a rejected candidate whose re-fitted pieces were kept
#: (:func:`rejected_candidates`): ``split`` (pieces of a split), ``arc`` (its largest arc).
PIECE_REASONS: tuple[str, ...] = ("split", "arc")


def _piece_fates(
    fate: dict[str, Any], n: int, seg_passed: np.ndarray
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.str_]]:
    """Per candidate (``n``, before the segment filters; ``seg_passed``: those that passed
    them): the pieces the detector re-fitted from it, how many it kept, and ``split`` /
    ``arc`` / '' by which re-fit they were kept (the numpy pipeline's record,
    :meth:`~stemmap.scan.detect.ScanTrunkDetector._run_numpy` ``fate``)."""
    tried = np.zeros(n, dtype=np.int64)
    took = np.zeros(n, dtype=np.int64)
    how = np.full(n, "", dtype="<U5")
    for name in PIECE_REASONS:
        for parent, ok in fate.get(name, ()):
            par = np.asarray(seg_passed, dtype=np.int64)[parent] if fate["filtered"] else parent
            np.add.at(tried, par, 1)
            np.add.at(took, par[ok], 1)
            how[par[ok]] = name
    return tried, took, how
