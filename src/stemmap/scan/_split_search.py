"""Split search: the best cut of a merged candidate, scored from running Kasa moments (ours,
issue 11, fifteenth round).

A trunk whose segment also holds a neighbour's returns (a branch running on behind the
silhouette, a stub, a stem at a similar range) fails the segment filters (``depth``) or the
RMS test, and the validated concave-corner split (:func:`~stemmap.scan._refit.split_refit`)
finds no cut where the junction is no concave corner. This searches every cut instead.

Kasa (1976) fits the circle ``x^2 + y^2 + D x + E y + F = 0`` by linear least squares: its
normal equations need only the sums of ``1, x, y, x^2, xy, y^2, zx, zy, z, z^2`` (``z = x^2 +
y^2``) over the returns, and its algebraic residual sum of squares is ``sum z^2 + p . s``
(``p = (D, E, F)`` solving ``M p = -s``, ``s = (sum zx, sum zy, sum z)``). The sums over any
run of consecutive returns are differences of prefix sums (:func:`kasa_prefix`), so each run
is scored in O(1) (:func:`run_score`): the two-piece cuts of a candidate of n returns in O(n),
the three-piece cuts in O(n^2). A run scores the smaller of its circle's residual, scaled to
metres as ``algebraic / (4 R^2)`` (``|p - c|^2 - R^2 ~ 2 R (|p - c| - R)`` near the circle),
and the residual of its total-least-squares line (a branch: the circle of infinite radius).
Every piece holds at least ``min_points`` returns: a circle fits three returns exactly, so a
cut that leaves a run of three or fewer explains nothing.

The number of pieces (1, 2 or 3) is chosen by the Bayesian information criterion with the
noise scale known (Schwarz 1978): ``RSS / s^2 + k ln n`` with ``k`` = 3 for one circle, 7 for
two pieces (two circles and the cut), 11 for three; ``s = sqrt(sigma^2 + (b R)^2)`` is the RMS
test's scale (``sigma`` the segment's range-noise sigma, ``b`` ``bark_roughness``, ``R`` the
larger circle radius of the best two-piece cut, clipped to ``[min_radius, max_radius]``; a
piece scored as a line counts as ``max_radius``). Where a cut wins, its pieces are judged as
the corner split's are: inner cut ends occluded (``Segments.cut``: a piece needs
``min_points_partial`` returns), segment filters, the geometric fit and the tests of an arc of
``arc_refit`` (:func:`~stemmap.scan._arcs.piece_passes`: the RMS test without the bark
allowance, the tangent-range and chi-square tests), accepted only together
(:func:`~stemmap.scan._refit.judge_pieces` with validation: one passing piece whose
circle-like siblings fail nothing and whose circle holds no return of the candidate) and only
when no return of the candidate was seen through the piece's circle (:func:`seen_through`).
The detector cuts only candidates rejected as not convex unless ``split_search_convex``: one
convex outline that is no circle was a lumpy rock on the simulator as often as a trunk with a
stub (sixteenth round). Numpy path only (scan-detection-history.md, fifteenth and sixteenth
rounds).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit
from numpy.typing import NDArray

from stemmap.scan._arcs import piece_passes
from stemmap.scan._refit import Refitted, judge_pieces
from stemmap.scan.features import segment_sum
from stemmap.scan.plausibility import segment_sigma
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["best_cuts", "judge_arcs", "kasa_prefix", "run_score", "search_refit", "seen_through"]

#: BIC parameter counts (Schwarz 1978) of one circle, two pieces + cut, three pieces + 2 cuts.
_K1, _K2, _K3 = 3.0, 7.0, 11.0


@njit(cache=True, error_model="numpy")
def kasa_prefix(x: FloatArray, y: FloatArray) -> FloatArray:  # pragma: no cover - compiled
    """Prefix sums (row ``i`` = sum over returns ``[0, i)``, shape (n + 1, 10)) of the Kasa
    (1976) moments ``1, x, y, x^2, xy, y^2, zx, zy, z, z^2`` with ``z = x^2 + y^2``. Centre the
    coordinates first (the candidate's mean) to keep the differences well conditioned."""
    n = x.shape[0]
    out = np.zeros((n + 1, 10))
    for i in range(n):
        xi, yi = x[i], y[i]
        z = xi * xi + yi * yi
        m = (1.0, xi, yi, xi * xi, xi * yi, yi * yi, z * xi, z * yi, z, z * z)
        for c in range(10):
            out[i + 1, c] = out[i, c] + m[c]
    return out


@njit(cache=True, error_model="numpy")
def run_score(prefix: FloatArray, a: int, b: int) -> tuple[float, float]:  # pragma: no cover
    """Residual sum of squares (m^2) of the run of returns ``[a, b)`` from the prefix sums:
    the smaller of the Kasa circle's, scaled to metres (``algebraic / (4 R^2)``), and the
    total-least-squares line's; 0 for three returns or fewer. Returns (score, the circle's
    radius; NaN where the circle is degenerate)."""
    n = prefix[b, 0] - prefix[a, 0]
    sx = prefix[b, 1] - prefix[a, 1]
    sy = prefix[b, 2] - prefix[a, 2]
    sxx = prefix[b, 3] - prefix[a, 3]
    sxy = prefix[b, 4] - prefix[a, 4]
    syy = prefix[b, 5] - prefix[a, 5]
    szx = prefix[b, 6] - prefix[a, 6]
    szy = prefix[b, 7] - prefix[a, 7]
    sz = prefix[b, 8] - prefix[a, 8]
    szz = prefix[b, 9] - prefix[a, 9]
    # adjugate of the symmetric normal matrix [[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, n]]
    c00 = syy * n - sy * sy
    c01 = sx * sy - sxy * n
    c02 = sxy * sy - syy * sx
    c11 = sxx * n - sx * sx
    c12 = sxy * sx - sxx * sy
    c22 = sxx * syy - sxy * sxy
    det = sxx * c00 + sxy * c01 + sx * c02
    circle = radius = math.nan
    if det != 0.0:
        d = -(c00 * szx + c01 * szy + c02 * sz) / det
        e = -(c01 * szx + c11 * szy + c12 * sz) / det
        f = -(c02 * szx + c12 * szy + c22 * sz) / det
        alg = szz + d * szx + e * szy + f * sz
        r2 = 0.25 * (d * d + e * e) - f
        # round-off far below zero: a degenerate (near-collinear) system, not a circle
        if alg > -1e-9 * szz and r2 > 0.0 and math.isfinite(alg):
            circle = max(alg, 0.0) / (4.0 * r2)
            radius = math.sqrt(r2)
    if n <= 3.0:
        return 0.0, radius
    cxx = sxx - sx * sx / n
    cyy = syy - sy * sy / n
    cxy = sxy - sx * sy / n
    line = max(0.5 * (cxx + cyy) - math.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy), 0.0)
    return (line if not circle < line else circle), radius


@njit(cache=True, error_model="numpy")
def best_cuts(
    x: FloatArray,
    y: FloatArray,
    sigma: float,
    min_points: int,
    min_radius: float,
    max_radius: float,
    bark: float,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """Where to cut one candidate (returns ``x``, ``y`` in beam order; module docstring: the
    BIC over one, two and three pieces of at least ``min_points`` returns each). Returns the
    indices at which the second and third pieces start, -1 for none: (-1, -1) no cut,
    (k, -1) two pieces."""
    n = x.shape[0]
    m = min_points
    if n < 2 * m:
        return -1, -1
    pre = kasa_prefix(x - x.mean(), y - y.mean())
    rss1 = run_score(pre, 0, n)[0]
    # two pieces [0, k), [k, n), each with >= min_points returns (a circle fits three returns
    # exactly: a cut that leaves a run of three or fewer is no evidence of anything)
    rss2, k2, r_a, r_b = math.inf, -1, math.nan, math.nan
    for k in range(m, n - m + 1):
        sa, ra = run_score(pre, 0, k)
        sb, rb = run_score(pre, k, n)
        if sa + sb < rss2:
            rss2, k2, r_a, r_b = sa + sb, k, ra, rb
    if k2 < 0:
        return -1, -1
    # three pieces [0, a), [a, b), [b, n), each with >= min_points returns
    rss3, a3, b3 = math.inf, -1, -1
    for a in range(m, n - 2 * m + 1):
        sa = run_score(pre, 0, a)[0]
        for b in range(a + m, n - m + 1):
            t = sa + run_score(pre, a, b)[0] + run_score(pre, b, n)[0]
            if t < rss3:
                rss3, a3, b3 = t, a, b
    # the RMS test's noise scale, with the larger circle of the best two-piece cut (a piece
    # scored as a line: max_radius)
    r_ref = max(
        r_a if math.isfinite(r_a) else max_radius, r_b if math.isfinite(r_b) else max_radius
    )
    r_ref = min(max(r_ref, min_radius), max_radius)
    s2 = sigma * sigma + (bark * r_ref) ** 2
    if not s2 > 0.0:
        return -1, -1
    ln_n = math.log(n)
    c1 = rss1 / s2 + _K1 * ln_n if math.isfinite(rss1) else math.inf
    c2 = rss2 / s2 + _K2 * ln_n
    c3 = rss3 / s2 + _K3 * ln_n
    if c3 < c2 and c3 < c1:
        return a3, b3
    if c2 < c1:
        return k2, -1
    return -1, -1


def search_refit(
    detector: ScanTrunkDetector,
    every: Segments,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> Refitted | None:
    """``split_search``: the candidates of ``every`` (before footprint correction) flagged by
    ``which`` cut where :func:`best_cuts` says, the pieces judged and validated as those of
    the corner split (:func:`~stemmap.scan._refit.judge_pieces`) with the arcs' tests
    (:func:`~stemmap.scan._arcs.piece_passes`). ``parent`` indexes ``every``; None when
    nothing was cut."""
    cfg = detector.config
    if not np.any(which):
        return None
    sub = every.select(which)
    p = sub.points
    sigma = segment_sigma(cfg, sub, segment_sum(p.r, sub) / sub.counts)
    cuts = np.zeros(len(p), dtype=bool)
    for j, (a, b) in enumerate(zip(sub.start, sub.stop, strict=True)):
        for c in best_cuts(
            p.x[a:b],
            p.y[a:b],
            float(sigma[j]),
            cfg.min_points,
            cfg.min_radius,
            cfg.max_radius,
            cfg.bark_roughness,
        ):
            if c >= 0:
                cuts[a + c] = True
    if not np.any(cuts):
        return None
    # inner cut ends occluded, as the corner split's pieces (Segments.cut): a piece of a cut
    # candidate needs min_points_partial returns to be a trunk
    pieces = sub.cut(np.cumsum(cuts) % 2 == 1)
    local = sub.labels[pieces.start].astype(np.int64)
    keep = (np.bincount(local, minlength=len(sub)) > 1)[local]
    # a piece is judged as an arc of arc_refit is (piece_passes: no bark allowance, tangent
    # range, chi-square): both are the part of a merged candidate that one circle explains
    return judge_arcs(detector, every, sub, pieces.select(keep), local[keep], which, grid, wrap)


def judge_arcs(
    detector: ScanTrunkDetector,
    every: Segments,
    sub: Segments,
    pieces: Segments,
    local: NDArray[np.int64],
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> Refitted | None:
    """The pieces of the candidates ``sub`` (= ``every.select(which)``; ``local`` indexes
    ``sub``) judged as arcs (:func:`~stemmap.scan._arcs.piece_passes`), validated as the
    corner split's (:func:`~stemmap.scan._refit.judge_pieces`), and vetoed when a return of
    the candidate was seen through the piece's circle (:func:`seen_through`); the pieces of
    ``split_search`` and of ``step_split``. ``parent`` indexes ``every``."""
    got = judge_pieces(
        detector, sub, pieces, local, which, grid, wrap, validate=True, tests=piece_passes
    )
    if got is None or not np.any(got.ok):
        return got
    through = seen_through(
        every, got.parent, got.fitted.centers, got.fitted.radii, got.fitted.sigma, got.ok, _SIGMAS
    )
    return got._replace(ok=got.ok & ~through)


#: Noise sigmas of the seen-through test (as ``_refit._returns_inside``).
_SIGMAS = 3.0


def seen_through(
    every: Segments,
    parent: NDArray[np.int64],
    centers: FloatArray,
    radii: FloatArray,
    sigma: FloatArray,
    which: NDArray[np.bool_],
    k: float,
) -> NDArray[np.bool_]:
    """Per piece (``which``), whether a return of its parent segment was seen through the
    piece's circle: its beam passes more than ``k`` sigma inside the circle's edge and the
    return lies beyond the beam's entry into the circle by more than ``k`` sigma. A trunk
    hides what is behind it, so such a piece is an arc of something else."""
    p = every.points
    out = np.zeros(parent.shape[0], dtype=bool)
    for i in np.flatnonzero(which):
        a, b = every.start[parent[i]], every.stop[parent[i]]
        r = p.r[a:b]
        ux, uy = p.x[a:b] / r, p.y[a:b] / r
        cx, cy = centers[i]
        along = cx * ux + cy * uy
        perp2 = (cx * cx + cy * cy) - along * along
        inner = radii[i] - k * sigma[i]
        hit = (inner > 0) & (perp2 < inner * inner) & (along > 0)
        entry = along - np.sqrt(np.maximum(radii[i] ** 2 - perp2, 0.0))
        out[i] = bool(np.any(hit & (r > entry + k * sigma[i])))
    return out
