"""Circle fits for trunk cross-sections seen by a 2D laser scanner.

Every fit takes points of shape (N, 2) in metres plus the keyword-only ``origin`` (sensor
position), ``sigma`` (range noise, m), ``angle_increment`` (beam spacing, rad) and ``edges``
(are the first/last returns true silhouette edges), and returns a :class:`CircleFit`, which is
falsy (and carries ``reason``) when the fit failed -- never silent zeros.

Registered methods (``FIT_METHODS``): ``kasa`` (Kasa 1976), ``fletcher_reeves`` (Zheng 2012
§3.3), ``three_point`` (Munjer 2025 eqs. 5-8), ``chord_width`` (Xue 2018 eq. 12) and ``ours``
(silhouette-constrained robust geometric fit with covariance). :func:`fit_circles_batch` fits
many segments at once (compiled loop for ours, vectorised numpy for the others). Methods,
decisions and measured accuracy: docs/algorithms/scan-fits.md. The result type and the input
checks live in :mod:`stemmap.scan._circle_base`, the single-segment ours fit in
:mod:`stemmap.scan._circle_ours` (both re-exported here).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.scan import _fit_batch as _fb
from stemmap.scan._circle_base import (
    CircleFit,
    _by_bearing,
    _check_divergence,
    _check_increment,
    _check_residuals,
    _check_silhouette,
    _origin,
    _per_segment,
    _rank_deficient,
    _single_from_batch,
    _with_rms,
    as_points,
)
from stemmap.scan._circle_ours import fit_circle_ours
from stemmap.scan._fit_geometric import STATUS_MESSAGES, fit_ours_segments
from stemmap.types import FloatArray

__all__ = [
    "FIT_METHODS",
    "ZHENG2012_FR",
    "CircleFit",
    "CircleFits",
    "as_points",
    "chord_width",
    "fit_circle",
    "fit_circle_chord_width",
    "fit_circle_fletcher_reeves",
    "fit_circle_kasa",
    "fit_circle_ours",
    "fit_circle_three_point",
    "fit_circles_batch",
]


def fit_circle_kasa(
    points: ArrayLike,
    *,
    origin: ArrayLike | None = None,
    sigma: float | None = None,
    angle_increment: float | None = None,
    edges: tuple[bool, bool] = (True, True),
) -> CircleFit:
    """Kasa algebraic least-squares circle fit.

    Minimises sum (x^2 + y^2 + D x + E y + F)^2 over (D, E, F), a linear problem. The points are
    centred and scaled first so the normal equations stay well conditioned at large offsets.

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
    origin, sigma, angle_increment, edges
        Ignored (accepted for the uniform fit signature, see ``FIT_METHODS``).

    Returns
    -------
    CircleFit
        Falsy with a reason for fewer than 3 points or (near-)collinear points. ``cov`` is NaN
        (the algebraic residual has no calibrated noise model).

    Notes
    -----
    Kasa (1976), as used by the visual-lidar tree-trunk odometry paper (2023, §2.3). Known to
    under-estimate the radius on short arcs; see docs/algorithms/scan-fits.md.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0, np.pi, 20)
    >>> fit = fit_circle_kasa(np.column_stack((1 + 0.2 * np.cos(t), 2 + 0.2 * np.sin(t))))
    >>> round(fit.radius, 6), bool(fit)
    (0.2, True)
    >>> bool(fit_circle_kasa(np.zeros((2, 2))))
    False
    """
    p = as_points(points)
    n = p.shape[0]
    if n < 3:
        return CircleFit.failed(f"need at least 3 points, got {n}", "kasa", n)
    mean = p.mean(axis=0)
    q = p - mean
    scale = float(np.sqrt(np.mean(np.sum(q * q, axis=1))))
    if scale == 0.0:
        return CircleFit.failed("all points coincide", "kasa", n)
    q = q / scale
    A = np.column_stack((q, np.ones(n)))
    b = -(q[:, 0] ** 2 + q[:, 1] ** 2)
    if _rank_deficient(A.T @ A):
        return CircleFit.failed("points are collinear", "kasa", n)
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    D, E, F = sol
    cx, cy = -D / 2.0, -E / 2.0
    r2 = cx * cx + cy * cy - F
    if not r2 > 0.0:
        return CircleFit.failed("degenerate algebraic solution (r^2 <= 0)", "kasa", n)
    center = np.array([cx, cy]) * scale + mean
    radius = math.sqrt(r2) * scale
    fit = CircleFit(center=center, radius=radius, n_points=n, method="kasa")
    rms = float(np.sqrt(np.mean(fit.residuals(p) ** 2)))
    return CircleFit(center=center, radius=radius, rms=rms, n_points=n, method="kasa")


# --------------------------------------------------------------------------------------------
# Helpers shared by the fits
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Zheng et al. (2012) §3.3: Fletcher-Reeves conjugate gradient on the Kasa normal equations
# --------------------------------------------------------------------------------------------

#: Published parameters of Zheng et al. (2012) §3.3: k_max = 1000 iterations, x0 = 0. The paper
#: gives no value for the termination threshold epsilon on ||d_k||; 1e-12 (on the centred and
#: scaled problem, where the unknowns are O(1)) is our choice and reaches machine precision.
ZHENG2012_K_MAX: int = 1000
ZHENG2012_TOL: float = 1e-12
ZHENG2012_FR: dict[str, float] = {"k_max": ZHENG2012_K_MAX, "tol": ZHENG2012_TOL}


def fit_circle_fletcher_reeves(
    points: ArrayLike,
    *,
    origin: ArrayLike | None = None,
    sigma: float | None = None,
    angle_increment: float | None = None,
    edges: tuple[bool, bool] = (True, True),
    k_max: int = ZHENG2012_K_MAX,
    tol: float = ZHENG2012_TOL,
) -> CircleFit:
    """Circle fit by Fletcher-Reeves conjugate gradient on the linear system of Zheng eq. (8).

    Each point gives one row of ``A x = b`` with ``a_i = [2 p_x, 2 p_y, 1]``,
    ``b_i = p_x^2 + p_y^2`` and ``x = [O_x, O_y, R^2 - O_x^2 - O_y^2]`` (eqs. 4-9). The
    least-squares solution is found by the F-R iteration of §3.3 (steps 1-8): ``g = A^T A x - A^T
    b``, ``d_0 = -g_0``, ``alpha_k = -g_k^T d_k / (d_k^T A^T A d_k)``, ``beta_k = |g_{k+1}|^2 /
    |g_k|^2``, restarted (``d = -g``) every 3 iterations, from ``x_0 = 0`` until ``||d_k|| < tol``
    or ``k = k_max``. The radius follows from eq. (7).

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
    origin, sigma, angle_increment, edges
        Ignored (uniform fit signature, see ``FIT_METHODS``).
    k_max : int, >= 1
        Maximum number of iterations (paper: 1000).
    tol : float, > 0
        Termination threshold on ``||d_k||`` (the paper leaves it open).

    Returns
    -------
    CircleFit
        Falsy with a reason for fewer than 3 points, coincident or collinear points, or no
        convergence within ``k_max``.

    Notes
    -----
    The points are centred and scaled to unit RMS radius before the iteration (the paper works
    in raw centimetres). This changes nothing in exact arithmetic -- the system is the same up to
    an affine change of unknowns -- but keeps ``A^T A`` well conditioned so that CG converges in
    the textbook 3 steps even at UTM-size offsets. The converged solution equals Kasa's.

    References
    ----------
    Zheng L., Liu J., Li W., Yang H. (2012), "Research on laser scanning of trees for logging
    harvesters", §3.3, eqs. (4)-(10).

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0, np.pi, 10)
    >>> fit = fit_circle_fletcher_reeves(np.column_stack((3 + 0.2 * np.cos(t), 0.2 * np.sin(t))))
    >>> round(fit.radius, 9), bool(fit)
    (0.2, True)
    """
    p = as_points(points)
    method = "fletcher_reeves"
    n = p.shape[0]
    if int(k_max) < 1 or not (tol > 0):
        raise ConfigError(f"k_max must be >= 1 and tol > 0, got k_max={k_max}, tol={tol}.")
    if n < 3:
        return CircleFit.failed(f"need at least 3 points, got {n}", method, n)
    mean = p.mean(axis=0)
    q = p - mean
    scale = float(np.sqrt(np.mean(np.sum(q * q, axis=1))))
    if scale == 0.0:
        return CircleFit.failed("all points coincide", method, n)
    q = q / scale
    A = np.column_stack((2.0 * q, np.ones(n)))
    b = q[:, 0] ** 2 + q[:, 1] ** 2
    M = A.T @ A
    Atb = A.T @ b
    if _rank_deficient(M):
        return CircleFit.failed("points are collinear", method, n)
    x = np.zeros(3)  # step 1: x_0 = 0
    g = M @ x - Atb  # step 2
    d = -g  # step 3
    converged = False
    for k in range(int(k_max)):
        if float(np.linalg.norm(d)) < tol:  # step 8
            converged = True
            break
        Md = M @ d
        den = float(d @ Md)
        if not den > 0.0:
            converged = float(np.linalg.norm(g)) < tol
            break
        alpha = -float(g @ d) / den  # step 4
        x = x + alpha * d
        g_new = M @ x - Atb  # step 5
        gg = float(g @ g)
        beta = float(g_new @ g_new) / gg if gg > 0 else 0.0  # step 6
        d = -g_new if (k + 1) % 3 == 0 else -g_new + beta * d  # restart every n = 3 steps
        g = g_new
    if not converged:
        return CircleFit.failed(f"no convergence within k_max={k_max} iterations", method, n)
    cx, cy, x3 = x
    r2 = cx * cx + cy * cy + x3  # eq. (7)
    if not r2 > 0.0:
        return CircleFit.failed("degenerate algebraic solution (R^2 <= 0)", method, n)
    center = np.array([cx, cy]) * scale + mean
    return _with_rms(p, center, math.sqrt(r2) * scale, method)


# --------------------------------------------------------------------------------------------
# Munjer et al. (2025) eqs. 5-8: arc through three points (perpendicular bisectors)
# --------------------------------------------------------------------------------------------


def fit_circle_three_point(
    points: ArrayLike,
    *,
    origin: ArrayLike | None = None,
    sigma: float | None = None,
    angle_increment: float | None = None,
    edges: tuple[bool, bool] = (True, True),
) -> CircleFit:
    """Circle through the first, middle and last point of the arc (Munjer eqs. 5-8).

    The points are ordered by bearing as seen from ``origin`` (scan order); A = first,
    C = middle (index ``N // 2``), B = last. The centre is the intersection of the perpendicular
    bisectors of AC and CB, the radius the mean distance of A, B, C to it.

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
    origin : array_like of shape (2,), optional
        Sensor position used to order the points by bearing (default (0, 0)).
    sigma, angle_increment, edges
        Ignored (uniform fit signature).

    Returns
    -------
    CircleFit
        Falsy for fewer than 3 points or collinear A, C, B. ``cov`` is NaN.

    Notes
    -----
    The paper writes the bisectors in slope form (eqs. 5-6, ``m* = -1/m``) and solves for
    ``x_0`` (eq. 7) and ``y_0`` (eq. 8); that form divides by zero when a chord is horizontal or
    vertical. We solve the same two bisector equations in normal form,
    ``2 (C - A) . O = |C|^2 - |A|^2`` and ``2 (B - C) . O = |B|^2 - |C|^2``, which has the same
    solution wherever the slope form is defined and also covers axis-aligned chords.

    References
    ----------
    Munjer et al. (2025), "LiDAR vs depth image tree mapping", §3.4, eqs. (5)-(8).

    Examples
    --------
    >>> fit = fit_circle_three_point([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]], origin=[0, 5])
    >>> [round(float(v), 9) for v in (*fit.center, fit.radius)]
    [0.0, 0.0, 1.0]
    """
    p = as_points(points)
    return _single_from_batch(p, _origin(origin), "three_point")


# --------------------------------------------------------------------------------------------
# Xue et al. (2018) eq. 12: chord width by the law of cosines
# --------------------------------------------------------------------------------------------


def chord_width(
    points: ArrayLike, *, origin: ArrayLike | None = None
) -> tuple[float, float, float]:
    """Trunk width from the two edge beams by the law of cosines (Xue 2018, eq. 12).

    ``AB^2 = O_R A^2 + O_R B^2 - 2 O_R A O_R B cos(theta)`` with ``O_R`` the sensor, A and B the
    first and last returns (by bearing) and ``theta`` the angle between their beams.

    Returns
    -------
    width : float, metres
    bisector : float, radians
        Bearing of the ray bisecting the two edge beams (input frame, from ``origin``).
    theta : float, radians
    """
    p = as_points(points)
    o = _origin(origin)
    _, th, rho = _by_bearing(p, o)
    theta = float(th[-1] - th[0])
    ra, rb = float(rho[0]), float(rho[-1])
    w2 = ra * ra + rb * rb - 2.0 * ra * rb * math.cos(theta)
    return math.sqrt(max(w2, 0.0)), 0.5 * float(th[0] + th[-1]), theta


def fit_circle_chord_width(
    points: ArrayLike,
    *,
    origin: ArrayLike | None = None,
    sigma: float | None = None,
    angle_increment: float | None = None,
    edges: tuple[bool, bool] = (True, True),
) -> CircleFit:
    """Circle whose diameter is the Xue (2018) eq. 12 chord width of the edge beams.

    Radius = width / 2. The centre is placed on the ray bisecting the two edge beams, at
    ``range + r``, where ``range`` is the range of the front surface along that ray
    (linearly interpolated between the returns either side of it).

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
    origin : array_like of shape (2,), optional
        Sensor position (default (0, 0)); ranges and beam angles are measured from it.
    sigma, angle_increment, edges
        Ignored (uniform fit signature).

    Returns
    -------
    CircleFit
        Falsy for fewer than 2 points or a zero width. ``cov`` is NaN.

    Notes
    -----
    The paper uses the width only as evidence for a trunk (eq. 13) and states it is smaller
    than the diameter (6-16.7 % in their orchard). Using it as the diameter is the issue's
    baseline; the centre placement is our choice (the paper does not place one): the nearest
    surface point of a circle along the ray through its centre is at ``|c| - r``.

    References
    ----------
    Xue J. et al. (2018), "Trunk detection based on laser radar and vision data fusion",
    Int J Agric & Biol Eng 11(6), §2.4.2, eq. (12).

    Examples
    --------
    >>> fit = fit_circle_chord_width([[5.0, -0.2], [4.8, 0.0], [5.0, 0.2]])
    >>> round(fit.diameter, 6), [round(float(v), 6) for v in fit.center]
    (0.4, [5.0, 0.0])
    """
    p = as_points(points)
    return _single_from_batch(p, _origin(origin), "chord_width")


# --------------------------------------------------------------------------------------------
# Ours: silhouette-constrained robust geometric fit
# --------------------------------------------------------------------------------------------


#: Registry of fit methods by name; ``fit_circle`` dispatches on it. Every registered function
#: takes ``points`` (N, 2) and the keyword-only ``origin`` (sensor position in the points'
#: frame, (2,), default (0, 0)), ``sigma`` (range noise std, metres, optional),
#: ``angle_increment`` (beam spacing, radians, optional) and ``edges`` ((bool, bool): are the
#: first/last returns true silhouette edges), which it may ignore.
FIT_METHODS: dict[str, Callable[..., CircleFit]] = {
    "kasa": fit_circle_kasa,
    "fletcher_reeves": fit_circle_fletcher_reeves,
    "three_point": fit_circle_three_point,
    "chord_width": fit_circle_chord_width,
    "ours": fit_circle_ours,
}


def fit_circle(points: ArrayLike, method: str = "kasa", **options: Any) -> CircleFit:
    """Fit a circle with the named method (see ``FIT_METHODS``).

    Raises
    ------
    ConfigError
        If ``method`` is not registered.
    """
    return _method(method)(points, **options)


def _method(method: str) -> Callable[..., CircleFit]:
    try:
        return FIT_METHODS[method]
    except KeyError:
        raise ConfigError(
            f"unknown circle fit method {method!r}; choose one of {sorted(FIT_METHODS)}."
        ) from None


# --------------------------------------------------------------------------------------------
# Batched fits
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CircleFits:
    """Columnar results of :func:`fit_circles_batch`, one row per segment.

    Attributes
    ----------
    segment_ids : ndarray of shape (K,), int -- the segment id of each row (sorted ascending)
    centers : ndarray of shape (K, 2), metres (NaN where failed)
    radii : ndarray of shape (K,), metres (NaN where failed)
    covs : ndarray of shape (K, 3, 3) over (cx, cy, r) (NaN where not estimated)
    rms : ndarray of shape (K,), metres
    n_points : ndarray of shape (K,), int
    ok : ndarray of shape (K,), bool
    reasons : tuple of K str (empty where ok)
    method : str
    """

    segment_ids: NDArray[np.int64]
    centers: FloatArray
    radii: FloatArray
    covs: FloatArray
    rms: FloatArray
    n_points: NDArray[np.int64]
    ok: NDArray[np.bool_]
    reasons: tuple[str, ...]
    method: str

    def __len__(self) -> int:
        return int(self.segment_ids.shape[0])

    @property
    def diameters(self) -> FloatArray:
        return 2.0 * self.radii

    def __getitem__(self, k: int) -> CircleFit:
        if not self.ok[k]:
            return CircleFit.failed(self.reasons[k], self.method, int(self.n_points[k]))
        return CircleFit(
            center=self.centers[k].copy(),
            radius=float(self.radii[k]),
            cov=self.covs[k].copy(),
            rms=float(self.rms[k]),
            n_points=int(self.n_points[k]),
            method=self.method,
        )


_STATUS_TEXT = np.array([STATUS_MESSAGES[k] for k in range(max(STATUS_MESSAGES) + 1)], dtype=object)


def _check_edge_window(share: float) -> float:
    """The edge range window's share of the footprint, checked (``fit_circles_batch``)."""
    if not 0.0 < share <= 1.0:
        raise InputError(f"edge_window must be in (0, 1], got {share}.")
    return float(share)


def fit_circles_batch(
    points: ArrayLike,
    segment_ids: ArrayLike,
    method: str = "ours",
    *,
    origin: ArrayLike | None = None,
    sigma: ArrayLike | None = None,
    angle_increment: float | None = None,
    edges: ArrayLike | None = None,
    beam_divergence: float | None = None,
    silhouette: ArrayLike | None = None,
    residuals: str = "range",
    edge_window: float = 0.5,
) -> CircleFits:
    """Fit one circle per segment of a batch of points.

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
    segment_ids : array_like of shape (N,), int
        Segment of each point. Need not be sorted (a stable sort groups them, keeping the
        order of points inside a segment).
    method : str
        A name in ``FIT_METHODS``. "ours" runs one compiled loop over all segments; kasa,
        fletcher_reeves (paper preset k_max, tol), three_point and chord_width run as vectorised
        numpy over all segments (same results as the single fits to round-off); any other
        registered method is called segment by segment.
    origin : array_like of shape (2,) or (K, 2), metres, optional
        Sensor position for all segments or per segment (K = number of distinct ids).
    sigma : float or array_like of shape (K,), metres, optional
        Range noise std; NaN/None/0 means "estimate from the residuals" (ours only).
    angle_increment : float, radians, optional
        Beam spacing (estimated per segment when omitted).
    edges : array_like of shape (K, 2), bool, optional
        Whether the first/last return of each segment is a true silhouette edge (default all
        True).
    beam_divergence, residuals : see :func:`fit_circle_ours` (ours only).
    silhouette : array_like of shape (2, 2) or (K, 2, 2), optional
        Per segment, see :func:`fit_circle_ours` (ours only).
    edge_window : float in (0, 1]
        Least share of the footprint in the range window of an averaging scanner's edge return
        (ours only; 0.5 = the default edge model, a beam returns when half its footprint hits;
        ``DetectorConfig.edge_hit_window``).

    Returns
    -------
    CircleFits
        One row per distinct segment id, in ascending id order.

    Raises
    ------
    InputError
        If shapes disagree or values are not finite.
    ConfigError
        If ``method`` is unknown.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0.0, np.pi, 8)
    >>> ring = np.column_stack((np.cos(t), np.sin(t)))
    >>> pts = np.vstack((ring * 0.1 + [2.0, 0.0], ring * 0.2 + [0.0, 3.0]))
    >>> fits = fit_circles_batch(pts, np.repeat([0, 1], 8), "kasa")
    >>> np.round(fits.radii, 6).tolist(), fits.ok.tolist()
    ([0.1, 0.2], [True, True])
    """
    fn = _method(method)
    p = as_points(points)
    ids = np.asarray(segment_ids)
    if ids.shape != (p.shape[0],) or not np.issubdtype(ids.dtype, np.integer):
        raise InputError(
            f"segment_ids must be an integer array of shape ({p.shape[0]},) (one per point), "
            f"got dtype {ids.dtype} and shape {ids.shape}."
        )
    if ids.size and np.any(ids[1:] < ids[:-1]):
        order = np.argsort(ids, kind="stable")
        p, ids = p[order], ids[order]
    # ids are sorted now: segment starts where the id changes (cheaper than np.unique)
    if ids.size:
        starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    else:
        starts = np.zeros(0, dtype=np.int64)
    uniq = ids[starts]
    counts = np.diff(np.r_[starts, ids.size])
    k = uniq.shape[0]
    stops = starts + counts
    if origin is None:
        o = np.zeros((k, 2))
    else:
        o = np.asarray(origin, dtype=np.float64)
        if o.shape == (2,):
            o = np.broadcast_to(o, (k, 2))
        if o.shape != (k, 2) or not np.all(np.isfinite(o)):
            raise InputError(
                f"origin must be a finite (2,) pair or ({k}, 2) per segment, got shape {o.shape}."
            )
    sig = _per_segment(sigma, k, "sigma", 0.0)
    sig = np.where(np.isnan(sig), 0.0, sig)
    if np.any(~np.isfinite(sig)) or np.any(sig < 0):
        raise InputError("sigma (range noise std, metres) must be finite and >= 0.")
    inc = _check_increment(angle_increment)
    if edges is None:
        e = np.ones((k, 2), dtype=bool)
    else:
        e = np.asarray(edges, dtype=bool)
        if e.shape == (2,):
            e = np.broadcast_to(e, (k, 2))
        if e.shape != (k, 2):
            raise InputError(f"edges must have shape (2,) or ({k}, 2), got {e.shape}.")
    foot = _check_divergence(beam_divergence)
    sil = _check_silhouette(silhouette, k)
    use_range = _check_residuals(residuals)

    if method == "ours":
        out, status = fit_ours_segments(
            p[:, 0],
            p[:, 1],
            starts,
            stops,
            o[:, 0],
            o[:, 1],
            sig,
            np.full(k, inc),
            e[:, 0],
            e[:, 1],
            sil,
            foot,
            use_range,
            edge_window=_check_edge_window(edge_window),
        )
        ok = status == 0
        return CircleFits(
            segment_ids=uniq.astype(np.int64),
            centers=out[:, :2].copy(),
            radii=out[:, 2].copy(),
            covs=out[:, 3:12].reshape(k, 3, 3).copy(),
            rms=out[:, 12].copy(),
            n_points=counts.astype(np.int64),
            ok=ok,
            reasons=tuple(_STATUS_TEXT[status].tolist()),
            method=method,
        )

    vectorised = {
        "kasa": lambda: _fb.kasa_batch(p, starts, counts),
        "fletcher_reeves": lambda: _fb.fletcher_reeves_batch(
            p, starts, counts, ZHENG2012_K_MAX, ZHENG2012_TOL
        ),
        "three_point": lambda: _fb.three_point_batch(p, starts, counts, o),
        "chord_width": lambda: _fb.chord_width_batch(p, starts, counts, o),
    }
    if method in vectorised and fn is FIT_METHODS[method]:
        centers, radii, why = vectorised[method]()
        ok = np.isfinite(radii)
        return CircleFits(
            segment_ids=uniq.astype(np.int64),
            centers=centers,
            radii=radii,
            covs=np.full((k, 3, 3), np.nan),
            rms=_fb.rms_batch(p, starts, counts, centers, radii),
            n_points=counts.astype(np.int64),
            ok=ok,
            reasons=tuple(str(r) for r in why),
            method=method,
        )

    # any other registered method: one call per segment
    centers = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    covs = np.full((k, 3, 3), np.nan)
    rms = np.full(k, np.nan)
    ok = np.zeros(k, dtype=bool)
    reasons: list[str] = []
    for j in range(k):
        fit = fn(
            p[starts[j] : stops[j]],
            origin=o[j],
            sigma=float(sig[j]) if sig[j] > 0 else None,
            angle_increment=inc or None,
            edges=(bool(e[j, 0]), bool(e[j, 1])),
        )
        reasons.append(fit.reason)
        if fit:
            ok[j] = True
            centers[j] = fit.center
            radii[j] = fit.radius
            covs[j] = fit.cov
            rms[j] = fit.rms
    return CircleFits(
        segment_ids=uniq.astype(np.int64),
        centers=centers,
        radii=radii,
        covs=covs,
        rms=rms,
        n_points=counts.astype(np.int64),
        ok=ok,
        reasons=tuple(reasons),
        method=method,
    )
