"""Per-segment features and filters for trunk candidates in 2D scans.

Everything is computed for *all segments of a batch at once* from the flattened returns of a
:class:`~stemmap.scan.segment.Segments` table (``np.add.reduceat`` over segment starts); no
per-segment Python loop.

Paper methods
-------------
* :func:`point_curvature` -- curvature of a single point, Zheng et al. 2012 eq. 3 (corrected).
* :func:`cluster_curvature` -- curvature of the whole cluster, Zheng §3.2 criterion (1).
* :func:`chord_width` -- trunk width by the law of cosines from the edge beams, Xue et al. 2018
  eq. 12; also Zheng §3.2 criterion (3), the greatest acceptable width, and the visual-lidar
  paper's 0.55 m width threshold (§2.2).
* :func:`sagitta_depth` -- depth of the cluster, Zheng §3.2 criterion (4).
* :func:`radius_median_filter` -- keep returns within 0.5 m of the cluster's median point
  (visual-lidar paper §2.3), which separates overlapping trunks.
* :func:`line_fit_rms` -- residual of the best straight line; :func:`is_straight` rejects walls
  and fences (ours: the papers only reject them implicitly through depth and width);
  :func:`line_bulge_gain` -- the share of it a bend towards the sensor explains (ours).
* :func:`edge_silhouette` -- where each trunk edge's tangent lies, from the beams next to the
  segment: background behind them narrows the interval, a mixed pixel pins it (ours).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import chdtri

from stemmap.errors import ConfigError
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

__all__ = [
    "SegmentFeatures",
    "chord_width",
    "cluster_curvature",
    "edge_default_prior",
    "edge_silhouette",
    "first_echo_edge_prior",
    "footprint_correct",
    "is_straight",
    "line_bulge_gain",
    "line_fit_rms",
    "point_curvature",
    "radius_median_filter",
    "sagitta_depth",
    "segment_features",
    "segment_sum",
    "segment_widths",
]

BoolArray = NDArray[np.bool_]


def segment_sum(values: ArrayLike, segs: Segments) -> FloatArray:
    """Sum of a per-return quantity (M,) over every segment, shape (K,)."""
    v = np.asarray(values, dtype=np.float64)
    if len(segs) == 0:
        return np.zeros(0)
    out: FloatArray = np.add.reduceat(v, segs.start)
    return out


def chord_width(r0: ArrayLike, r1: ArrayLike, theta: ArrayLike) -> FloatArray:
    """Trunk width from the two edge beams by the law of cosines (Xue et al. 2018, eq. 12).

    ``AB^2 = O_R A^2 + O_R B^2 - 2 O_R A O_R B cos(theta)``.

    Parameters
    ----------
    r0, r1 : array_like, metres -- ranges of the first and last return of the segment
    theta : array_like, radians -- angle between the two edge beams

    Returns
    -------
    ndarray, metres

    Notes
    -----
    The chord between the outermost returns is shorter than the diameter: the edge beams hit
    the trunk inside its tangent lines (Xue et al. report 6-16.7 % under-estimation). It is a
    width *feature*, not a diameter estimate.

    Examples
    --------
    >>> round(float(chord_width(1.0, 1.0, np.pi / 3)), 12)
    1.0
    """
    a = np.asarray(r0, dtype=np.float64)
    b = np.asarray(r1, dtype=np.float64)
    h = np.sin(np.asarray(theta, dtype=np.float64) / 2.0)
    # eq. 12 with cos(theta) = 1 - 2 sin^2(theta / 2): identical, without the cancellation of
    # a^2 + b^2 - 2ab cos(theta) for the small angles a far trunk subtends
    out: FloatArray = np.sqrt((a - b) ** 2 + 4.0 * a * b * h * h)
    return out


def point_curvature(r: ArrayLike, segs: Segments | None = None) -> FloatArray:
    """Curvature of single returns (Zheng et al. 2012, eq. 3, corrected).

    ``cur_i = (l_{i+1} - l_i) - (l_i - l_{i-1}) = l_{i+1} - 2 l_i + l_{i-1}``.

    Parameters
    ----------
    r : array_like of shape (M,), metres, ranges in beam order
    segs : Segments, optional
        When given, the first and last return of every segment (no neighbour inside the
        segment) get NaN; otherwise only the two ends of ``r``.

    Returns
    -------
    ndarray of shape (M,)

    Notes
    -----
    The paper prints ``l_{i+1} - 2 l_{i-1} + l_i``, which contradicts its own first
    expression; we implement the second difference (decision in
    docs/algorithms/scan-detection.md). A trunk facing the scanner is convex in range
    (``cur > 0`` near its middle); a one-beam spike outward has a large negative curvature.

    Examples
    --------
    >>> point_curvature([2.0, 1.0, 2.0, 3.0]).tolist()
    [nan, 2.0, 0.0, nan]
    """
    v = np.asarray(r, dtype=np.float64)
    out = np.full(v.shape, np.nan)
    if v.shape[0] >= 3:
        out[1:-1] = v[2:] - 2.0 * v[1:-1] + v[:-2]
    if segs is not None and len(segs):
        out[segs.start] = np.nan
        out[segs.stop - 1] = np.nan
    return out


def _edge_angle(segs: Segments) -> FloatArray:
    """Angle at the sensor between the first and last return of every segment, radians."""
    p = segs.points
    i0, i1 = segs.start, segs.stop - 1
    cross = p.x[i0] * p.y[i1] - p.y[i0] * p.x[i1]
    dot = p.x[i0] * p.x[i1] + p.y[i0] * p.y[i1]
    out: FloatArray = np.abs(np.arctan2(cross, dot))
    return out


def segment_widths(segs: Segments) -> FloatArray:
    """Edge-beam chord width of every segment (Xue et al. 2018, eq. 12), metres, shape (K,)."""
    if len(segs) == 0:
        return np.zeros(0)
    p = segs.points
    return chord_width(p.r[segs.start], p.r[segs.stop - 1], _edge_angle(segs))


def sagitta_depth(segs: Segments) -> FloatArray:
    """Depth of every segment: largest distance of a return from the chord between its ends,
    measured towards the sensor (Zheng et al. 2012, §3.2 criterion 4).

    Returns
    -------
    ndarray of shape (K,), metres; negative when the segment bulges away from the sensor
    (a concave shape, never a trunk seen from outside); 0 for segments of 1-2 returns.

    Notes
    -----
    Zheng et al. name the criterion ("smallest acceptable depth of the cluster") without
    defining depth; we take the sagitta, which is 0 for flat objects (ground, walls) and close
    to the radius for a trunk (decision in docs/algorithms/scan-detection.md).
    """
    k = len(segs)
    if k == 0:
        return np.zeros(0)
    p = segs.points
    lab = segs.labels
    i0, i1 = segs.start, segs.stop - 1
    x0, y0 = p.x[i0], p.y[i0]
    dx, dy = p.x[i1] - x0, p.y[i1] - y0
    length = np.hypot(dx, dy)
    safe = np.where(length > 0, length, 1.0)
    nx, ny = -dy / safe, dx / safe
    # orient the normal towards the sensor (origin)
    flip = (nx * -x0 + ny * -y0) < 0
    nx = np.where(flip, -nx, nx)
    ny = np.where(flip, -ny, ny)
    d = (p.x - x0[lab]) * nx[lab] + (p.y - y0[lab]) * ny[lab]
    dmax: FloatArray = np.maximum.reduceat(d, segs.start)
    dmin: FloatArray = np.minimum.reduceat(d, segs.start)
    out = np.where(dmax >= -dmin, dmax, dmin)
    out = np.where(length > 0, out, 0.0)
    res: FloatArray = out
    return res


def cluster_curvature(width: ArrayLike, depth: ArrayLike) -> FloatArray:
    """Curvature of a whole cluster (Zheng et al. 2012, §3.2 criterion 1), 1/m.

    The circle through the two ends of a chord of length ``w`` and the point at sagitta ``h``
    has radius ``(w^2/4 + h^2) / (2 h)``; its inverse is the cluster curvature, so the paper's
    minimum and maximum curvature "prescribe the acceptable value of the trunk radius".

    Returns
    -------
    ndarray; 0 for a straight cluster (``h = 0``), negative for a concave one.

    Examples
    --------
    >>> round(float(cluster_curvature(0.4, 0.2)), 9)  # half circle of radius 0.2
    5.0
    """
    w = np.asarray(width, dtype=np.float64)
    h = np.asarray(depth, dtype=np.float64)
    den = w * w / 4.0 + h * h
    out: FloatArray = np.where(den > 0, 2.0 * h / np.where(den > 0, den, 1.0), 0.0)
    return out


def _centred_moments(
    segs: Segments,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Every segment's mean return (mx, my), its returns about it (qx, qy, per return) and
    their second moments summed per segment (sxx, syy, sxy); centred first, which is
    numerically safe far from the sensor."""
    p = segs.points
    n = segs.counts.astype(np.float64)
    lab = segs.labels
    mx = segment_sum(p.x, segs) / n
    my = segment_sum(p.y, segs) / n
    qx = p.x - mx[lab]
    qy = p.y - my[lab]
    sxx = segment_sum(qx * qx, segs)
    syy = segment_sum(qy * qy, segs)
    sxy = segment_sum(qx * qy, segs)
    return mx, my, qx, qy, sxx, syy, sxy


def line_fit_rms(segs: Segments) -> FloatArray:
    """RMS orthogonal distance of every segment's returns to its best straight line (PCA).

    Returns
    -------
    ndarray of shape (K,), metres (0 for segments of 1-2 returns).
    """
    if len(segs) == 0:
        return np.zeros(0)
    n = segs.counts.astype(np.float64)
    _, _, _, _, sxx, syy, sxy = _centred_moments(segs)
    sxx, syy, sxy = sxx / n, syy / n, sxy / n
    tr = sxx + syy
    det = sxx * syy - sxy * sxy
    lam_min = tr / 2.0 - np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))
    out: FloatArray = np.sqrt(np.maximum(lam_min, 0.0))
    return out


def line_bulge_gain(segs: Segments) -> FloatArray:
    """How much a bend explains of every segment's residual from its best line, m^2 (ours,
    issue 11, Dec 5; ``straight_curvature``).

    In the frame of the segment's best line (PCA: ``s`` along it, ``t`` across it, ``t``
    pointing to the sensor), the returns are regressed on ``s^2`` after ``1`` and ``s``: the
    least-squares parabola ``t = a + b s + c s^2``, whose ``c`` is half the curvature. Its
    gain is the drop of the residual sum of squares over the line's, ``(sum t z)^2 / sum
    z^2`` with ``z`` = ``s^2`` made orthogonal to ``1`` and ``s`` (``t`` is already orthogonal
    to both, the PCA line being the least-squares one). Under a straight surface with
    independent errors of std ``sigma`` across it, the gain is ``sigma^2 chi^2_1``: one degree
    of freedom, the curvature, against the ``n - 2`` of the line's whole residual that
    :func:`is_straight` tests. An arc of sagitta ``h`` over ``n`` returns puts ``4 n h^2 / 45``
    (returns even along the chord) into that one degree, so the bend of a small trunk under
    noise is read from all its returns at once, where the line's residual spreads it over
    ``n - 2`` degrees and :func:`sagitta_depth` reads it from the deepest return alone. The
    sign: positive where the middle bulges towards the sensor (``c < 0``; a trunk seen from
    outside), negative where it recedes (a wall's inside corner, a hollow).

    Returns
    -------
    ndarray of shape (K,), m^2, signed (0 for segments of fewer than 4 returns).
    """
    if len(segs) == 0:
        return np.zeros(0)
    n = segs.counts.astype(np.float64)
    lab = segs.labels
    mx, my, qx, qy, sxx, syy, sxy = _centred_moments(segs)
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of the best line
    ux, uy = np.cos(phi), np.sin(phi)
    # the normal, pointed at the sensor (the frame's origin)
    flip = np.where(-(mx * -uy + my * ux) >= 0.0, 1.0, -1.0)
    vx, vy = -uy * flip, ux * flip
    s_along = qx * ux[lab] + qy * uy[lab]
    t_across = qx * vx[lab] + qy * vy[lab]
    s2 = s_along * s_along
    m2 = segment_sum(s2, segs) / n
    ss = segment_sum(s2, segs)
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.where(ss > 0, segment_sum(s2 * s_along, segs) / ss, 0.0)
        z = s2 - m2[lab] - beta[lab] * s_along
        tz = segment_sum(t_across * z, segs)
        zz = segment_sum(z * z, segs)
        gain = np.where(zz > 0, tz * tz / zz, 0.0)
    out: FloatArray = np.where(segs.counts >= 4, np.where(tz < 0, gain, -gain), 0.0)
    return out


@functools.lru_cache(maxsize=8)
def _chi2_upper(alpha: float) -> FloatArray:
    """Upper ``alpha`` quantiles of chi-square with 0..1023 degrees of freedom (index = dof)."""
    dof = np.arange(1024, dtype=np.float64)
    out: FloatArray = np.concatenate(([0.0], chdtri(dof[1:], alpha)))
    out.setflags(write=False)
    return out


def is_straight(
    line_rms: ArrayLike,
    width: ArrayLike,
    sigma: float | ArrayLike,
    *,
    ratio: float = 0.05,
    n_points: ArrayLike | None = None,
    alpha: float = 0.01,
) -> BoolArray:
    """Straight-segment test for walls, fences and ground (ours).

    Without ``n_points``: the line residual left after removing the range noise is below
    ``ratio`` times the width, ``sqrt(max(rms^2 - sigma^2, 0)) < ratio * width``.

    With ``n_points`` (the default of the detector): a chi-square test -- the segment is
    straight when a straight line explains its returns within the noise,
    ``n rms^2 / sigma^2 <= chi2_{n-2}(1 - alpha)``. A half-visible trunk has a line residual of
    about ``0.31 r`` (r = radius), far above a 1 cm noise for any trunk worth measuring; a wall's
    residual is the noise itself.

    Parameters
    ----------
    line_rms : array_like of shape (K,), metres (:func:`line_fit_rms`)
    width : array_like of shape (K,), metres
    sigma : float or array_like of shape (K,), metres, > 0 for the chi-square test
    ratio : float, > 0
    n_points : array_like of shape (K,), int, optional
    alpha : float in (0, 1) -- false-straight rate for a true line

    Examples
    --------
    >>> is_straight([0.01, 0.05], [1.0, 0.3], 0.01, n_points=[20, 8]).tolist()
    [True, False]
    """
    sig = np.asarray(sigma, dtype=np.float64)
    if np.any(sig < 0) or ratio <= 0 or not 0 < alpha < 1:
        raise ConfigError(
            f"need sigma >= 0, ratio > 0, 0 < alpha < 1; got {sigma!r}, {ratio}, {alpha}."
        )
    rms = np.asarray(line_rms, dtype=np.float64)
    if n_points is not None and np.all(sig > 0):
        n = np.asarray(n_points, dtype=np.float64)
        dof = np.maximum(n - 2.0, 1.0)
        stat = n * rms * rms / (sig * sig)
        table = _chi2_upper(alpha)
        d = dof.astype(np.int64)
        small = d < table.shape[0]
        limit = np.where(small, table[np.minimum(d, table.shape[0] - 1)], 0.0)
        if not np.all(small):
            limit[~small] = chdtri(dof[~small], alpha)
        chi: BoolArray = stat <= limit
        return chi
    excess = np.sqrt(np.maximum(rms * rms - sig * sig, 0.0))
    out: BoolArray = excess < ratio * np.asarray(width, dtype=np.float64)
    return out


def _segment_median(values: FloatArray, segs: Segments) -> FloatArray:
    """Median of ``values`` within every segment (lower middle for even counts... averaged)."""
    lab = segs.labels
    order = np.lexsort((values, lab))
    sv = values[order]
    c = segs.counts
    lo = segs.start + (c - 1) // 2
    hi = segs.start + c // 2
    out: FloatArray = 0.5 * (sv[lo] + sv[hi])
    return out


def radius_median_filter(segs: Segments, radius: float = 0.5) -> BoolArray:
    """Keep returns within ``radius`` of their segment's median point (visual-lidar paper §2.3).

    The median point is the coordinate-wise median of the segment's returns. Returns farther
    away belong to another trunk merged into the same cluster (or to noise).

    Parameters
    ----------
    segs : Segments
    radius : float, metres, > 0 (paper: 0.5 m)

    Returns
    -------
    ndarray of shape (M,), bool -- True for returns to keep.
    """
    if not radius > 0:
        raise ConfigError(f"radius median filter radius must be > 0 m, got {radius}.")
    p = segs.points
    if len(segs) == 0:
        return np.zeros(len(p), dtype=bool)
    # a segment whose bounding box fits in the radius keeps every return (the median point lies
    # inside the box): only the others need the (sorting) median
    dx = np.maximum.reduceat(p.x, segs.start) - np.minimum.reduceat(p.x, segs.start)
    dy = np.maximum.reduceat(p.y, segs.start) - np.minimum.reduceat(p.y, segs.start)
    big = np.hypot(dx, dy) > radius
    out: BoolArray = np.ones(len(p), dtype=bool)
    if not np.any(big):
        return out
    sub = segs.select(big)
    lab = sub.labels
    mx = _segment_median(sub.points.x, sub)
    my = _segment_median(sub.points.y, sub)
    in_big = np.repeat(big, segs.counts)
    out[in_big] = np.hypot(sub.points.x - mx[lab], sub.points.y - my[lab]) <= radius
    return out


def footprint_correct(segs: Segments, footprint: float) -> Segments:
    """Move every return to the bearing it most likely came from, for nearest-return sensors
    with a beam footprint (divergence) of ``footprint`` radians (ours).

    A first-echo scanner reports, at the beam's nominal bearing, the range of the nearest
    surface anywhere inside its footprint ``[theta - f/2, theta + f/2]``. On a trunk (a convex
    object whose range has one minimum, at the apex bearing ``theta_a``) that nearest point lies
    at the footprint side closest to the apex, ``theta' = theta - clip(theta - theta_a, -f/2,
    f/2)``. Without the correction the trunk looks wider by up to one footprint (half on each
    side) and every fit over-estimates the diameter.

    Parameters
    ----------
    segs : Segments
    footprint : float, radians, >= 0 (0 returns ``segs`` unchanged)

    Returns
    -------
    Segments
        Same segments and flags, returns at the corrected bearings (ranges unchanged).

    Notes
    -----
    The apex bearing is that of the segment's nearest return. Sensors that average the
    footprint (or the simulator's energy-weighted mixed-pixel model) need ``footprint = 0``.
    """
    if footprint < 0 or not np.isfinite(footprint):
        raise ConfigError(f"beam footprint must be finite and >= 0 rad, got {footprint}.")
    if footprint == 0 or len(segs) == 0:
        return segs
    p = segs.points
    lab = segs.labels
    theta = np.arctan2(p.y, p.x)
    rmin = np.minimum.reduceat(p.r, segs.start)
    is_min = p.r == rmin[lab]
    first_min = np.full(len(segs), -1, dtype=np.int64)
    idx = np.flatnonzero(is_min)
    # the first nearest return of every segment (reverse assignment keeps the first)
    first_min[lab[idx[::-1]]] = idx[::-1]
    apex = theta[first_min]
    d = np.arctan2(np.sin(theta - apex[lab]), np.cos(theta - apex[lab]))
    new_t = theta - np.clip(d, -footprint / 2.0, footprint / 2.0)
    pts = replace(p, x=p.r * np.cos(new_t), y=p.r * np.sin(new_t))
    return replace(segs, points=pts)


#: Standard deviation of the trunk's share of a mixed pixel's footprint as recovered from its
#: range (fraction of the footprint): the energy-weighted blend below is a model of the sensor,
#: whose beam profile is not exactly uniform (the simulator samples it with 5 sub-beams).
MIXED_FRACTION_STD = 0.2


def mixed_fraction(rho_mixed: ArrayLike, rho_near: ArrayLike, rho_far: ArrayLike) -> FloatArray:
    """Share ``f`` of a beam footprint on the near surface, from the range of a mixed pixel.

    An averaging scanner whose footprint covers two surfaces reports the energy-weighted mean
    range; with the diffuse-target energy ``~ 1 / rho^2`` per unit footprint,
    ``rho_m = (f / rho_n + (1 - f) / rho_f) / (f / rho_n^2 + (1 - f) / rho_f^2)``, solved for
    ``f`` (clipped to [0, 1]; NaN where the ranges are not ordered ``rho_n < rho_m < rho_f``)."""
    m = np.asarray(rho_mixed, dtype=np.float64)
    a = 1.0 / np.asarray(rho_near, dtype=np.float64)
    b = 1.0 / np.asarray(rho_far, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = b * (1.0 - m * b) / ((a - b) * (m * (a + b) - 1.0))
    ok = (np.asarray(rho_near) < m) & (m < np.asarray(rho_far))
    out: FloatArray = np.where(ok, np.clip(f, 0.0, 1.0), np.nan)
    return out


def edge_default_prior(h: float, hit_min: float, hit_max: float) -> tuple[float, float]:
    """The tangent prior of a segment end whose beams beyond tell nothing, for an averaging
    scanner whose return threshold lies in ``[hit_min, hit_max]`` (ours, Dec 4).

    A beam whose footprint (full width ``w = 2 h`` beam spacings) is centred at bearing
    ``theta`` returns from a trunk whose silhouette ends at bearing ``T`` when at least a share
    ``q`` of the footprint hits: ``T > theta - w/2 + q w``. The edge beam returned and the next
    beam (``theta + 1``) did not, so ``T`` lies in ``(theta + (q - 1/2) w, theta + 1 +
    (q - 1/2) w]``; over ``q`` in ``[hit_min, hit_max]`` the union is an interval of width
    ``1 + 2 h (hit_max - hit_min)`` centred at ``1/2 + h (hit_min + hit_max - 1)`` beams beyond
    the edge beam. Returns (offset, std) in beam spacings, std that of a uniform interval.
    ``(0.5, 0.5)`` is the fit's own default ``(1/2, 1/sqrt(12))``; ``(0, 0)`` a scanner that
    returns when any part of the footprint hits (the tangent ``h`` beams nearer)."""
    return (
        0.5 + h * (hit_min + hit_max - 1.0),
        (1.0 + 2.0 * h * (hit_max - hit_min)) / math.sqrt(12.0),
    )


def first_echo_edge_prior(segs: Segments, protrusion: float) -> FloatArray:
    """Tangent prior of each segment end of a first-echo scan on a stem whose outline carries
    protrusions up to ``protrusion`` metres high (ours, issue 11, Dec 4).

    After :func:`footprint_correct` a first-echo edge return sits at the side of its footprint
    nearest the apex, and the fit's default prior puts the silhouette tangent uniformly in the
    rest of that footprint (offset 1/2, width 1 beam spacing beyond the return): the tangent
    of the *outline*. A real stem's outline is its mean circle plus bark flakes, twigs, needles
    and stubs (on the real slices of docs/algorithms/scan-detection.md, points 1.7-3.3 cm
    outside the reference ring), and a first-echo beam returns from whatever is nearest in its
    footprint, so the last beam that returns may have caught a protrusion only. The mean
    circle's tangent then lies up to ``protrusion / rho`` radians (``rho`` the edge return's
    range) inside the outline's: uniform over ``[edge - s, edge + 1]`` beam spacings with
    ``s = protrusion / (rho * spacing)``, i.e. offset ``(1 - s) / 2`` and standard deviation
    ``(1 + s) / sqrt(12)`` (a uniform interval's, as the fit's default).

    Parameters
    ----------
    segs : Segments
        Segments of one batch (their ends are the edge returns).
    protrusion : float, metres, >= 0

    Returns
    -------
    ndarray of shape (K, 2, 2)
        Per segment, rows (start, end) in beam order: (offset, std) in beam spacings (the
        layout of :func:`edge_silhouette`); NaN (the fit's default) everywhere for 0.
    """
    if protrusion < 0 or not np.isfinite(protrusion):
        raise ConfigError(f"protrusion must be finite and >= 0 m, got {protrusion}.")
    k = len(segs)
    out = np.full((k, 2, 2), np.nan)
    p = segs.points
    inc = abs(p.angle_increment)
    if k == 0 or protrusion == 0 or not inc > 0:
        return out
    for side, idx in enumerate((segs.start, segs.stop - 1)):
        s = protrusion / (np.maximum(p.r[idx], 1e-9) * inc)
        out[:, side, 0] = 0.5 * (1.0 - s)
        out[:, side, 1] = (1.0 + s) / math.sqrt(12.0)
    return out


def edge_silhouette(
    segs: Segments,
    ranges: ArrayLike,
    divergence: float,
    *,
    margin: float = 0.2,
    wrap: bool = False,
    hit_range: tuple[float, float] = (0.5, 0.5),
) -> FloatArray:
    """Prior on each segment end's tangent bearing from the beams beyond it (ours).

    For an averaging scanner with beam spacing ``d`` and a footprint of full width
    ``divergence`` (``h = divergence / (2 d)`` beams each side of a beam centre), look at the
    two beams beyond each end (``n1`` next to the edge return, then ``n2``):

    * ``n1`` returned nothing or is within ``margin`` of the edge range: no information; the
      default (tangent uniform between the edge beam and ``n1``, offset 1/2, std 1/sqrt(12)).
    * ``n1`` is background (more than ``margin`` farther than the edge return) and ``n2`` is
      the same background (within ``margin`` of ``n1``): neither footprint is mixed, so the
      tangent lies in the gap between them: offset 1/2, std ``(1 - 2 h) / sqrt(12)``.
    * ``n2`` is farther than ``n1`` by more than ``margin``: ``n1`` is a mixed pixel of the
      trunk (range of the edge return) and the background (range of ``n2``); its range gives the
      trunk's share ``f`` of its footprint (:func:`mixed_fraction`), so the tangent lies at
      ``1 - h + 2 h f`` beams beyond the edge return (std ``2 h`` x
      :data:`MIXED_FRACTION_STD`).

    Occluded ends (``n1`` nearer) are left at the default (the fit drops them anyway).
    ``hit_range`` (the scanner's return threshold, a share of the footprint, assumed in that
    interval; ``DetectorConfig.edge_hit_min`` / ``edge_hit_max``) other than (0.5, 0.5) writes
    :func:`edge_default_prior` at the ends where ``n1`` returned nothing, for any footprint >
    0 (also one of >= a beam spacing, where the neighbours are not read otherwise): only
    there did the threshold decide where the returns stop (a footprint whose rest hits a
    surface behind returns a mixed pixel whatever the threshold).

    Parameters
    ----------
    segs : Segments
    ranges : array_like of shape (S, N), metres
        The gated range grid the segment returns came from (inf/NaN = no return).
    divergence : float, radians, >= 0 (0 or >= one beam spacing: all defaults)
    margin : float, metres
    wrap : bool
        Beams wrap around (360-degree scan): beam -1 is beam N - 1.

    Returns
    -------
    ndarray of shape (K, 2, 2)
        Per segment, rows (start, end) in beam order: (offset, std) in beam spacings; NaN where
        the default applies.
    """
    k = len(segs)
    out = np.full((k, 2, 2), np.nan)
    p = segs.points
    inc = abs(p.angle_increment)
    h = divergence / (2.0 * inc) if inc > 0 else 0.0
    if k == 0 or not h > 0.0:
        return out
    grid = np.asarray(ranges, dtype=np.float64).reshape(p.n_scans, p.n_beams)
    n = p.n_beams

    def at(beams: NDArray[np.int64]) -> FloatArray:
        if wrap:
            b = np.mod(beams, n)
            val: FloatArray = grid[segs.scan, b]
        else:
            b = np.clip(beams, 0, n - 1)
            val = np.where((beams >= 0) & (beams < n), grid[segs.scan, b], np.inf)
        return np.where(np.isfinite(val), val, np.inf)

    ends = ((segs.start, -1), (segs.stop - 1, 1))
    threshold = tuple(hit_range) != (0.5, 0.5)
    for side, (idx, step) in enumerate(ends):
        edge_r = p.r[idx]
        b_edge = p.beam[idx]
        r1 = at(b_edge + step)
        if threshold:  # nothing returned beyond the end: the return threshold set the edge
            nothing = ~np.isfinite(r1)
            out[nothing, side, 0], out[nothing, side, 1] = edge_default_prior(h, *hit_range)
        if not h < 0.5:
            continue
        r2 = at(b_edge + 2 * step)
        with np.errstate(invalid="ignore"):
            bg = np.isfinite(r1) & (r1 > edge_r + margin)
            clean = bg & np.isfinite(r2) & (np.abs(r2 - r1) <= margin)
            mixed = bg & np.isfinite(r2) & (r2 > r1 + margin)
        f = mixed_fraction(r1, edge_r, r2)
        mixed &= np.isfinite(f)
        out[clean, side, 0] = 0.5
        out[clean, side, 1] = (1.0 - 2.0 * h) / np.sqrt(12.0)
        out[mixed, side, 0] = 1.0 - h + 2.0 * h * f[mixed]
        out[mixed, side, 1] = 2.0 * h * MIXED_FRACTION_STD
    return out


@dataclass(frozen=True, eq=False)
class SegmentFeatures:
    """Features of every segment, shape (K,) each.

    Attributes
    ----------
    n_points : int
    width : metres, edge-beam chord (Xue eq. 12)
    depth : metres, sagitta towards the sensor (Zheng §3.2)
    curvature : 1/m, cluster curvature (Zheng §3.2)
    line_rms : metres, residual of the best straight line
    arc_angle : radians, angle the segment subtends at the sensor
    mean_range : metres
    """

    n_points: NDArray[np.int64]
    width: FloatArray
    depth: FloatArray
    curvature: FloatArray
    line_rms: FloatArray
    arc_angle: FloatArray
    mean_range: FloatArray


def segment_features(segs: Segments) -> SegmentFeatures:
    """Compute :class:`SegmentFeatures` for all segments at once."""
    p = segs.points
    n = segs.counts
    theta = _edge_angle(segs) if len(segs) else np.zeros(0)
    width = segment_widths(segs)
    depth = sagitta_depth(segs)
    nf = np.maximum(n, 1).astype(np.float64)
    return SegmentFeatures(
        n_points=n,
        width=width,
        depth=depth,
        curvature=cluster_curvature(width, depth),
        line_rms=line_fit_rms(segs),
        arc_angle=theta,
        mean_range=segment_sum(p.r, segs) / nf,
    )
