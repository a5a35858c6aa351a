"""The single-segment "ours" circle fit (:func:`fit_circle_ours`, re-exported by
:mod:`stemmap.scan.circle`): input checks and the call of the compiled silhouette-constrained
robust geometric fit (:mod:`stemmap.scan._fit_geometric`) for one segment. The model:
docs/algorithms/scan-fits.md."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import InputError
from stemmap.scan._circle_base import (
    CircleFit,
    _check_divergence,
    _check_increment,
    _check_residuals,
    _check_sigma,
    _check_silhouette,
    _origin,
    as_points,
)
from stemmap.scan._fit_geometric import STATUS_MESSAGES, fit_ours_segments


def fit_circle_ours(
    points: ArrayLike,
    *,
    origin: ArrayLike | None = None,
    sigma: float | None = None,
    angle_increment: float | None = None,
    edges: tuple[bool, bool] = (True, True),
    beam_divergence: float | None = None,
    silhouette: ArrayLike | None = None,
    residuals: str = "range",
) -> CircleFit:
    """Silhouette-constrained robust geometric circle fit for one-sided laser arcs (ours).

    Minimises over (cx, cy, r)

    ``sum_i huber((rho_i - rho_hat_i(c, r)) / sigma)``
    ``+ sum_{edge} ((beta +- asin(r / D) - t_edge) / s_edge)^2 / 2``

    where ``D = |c - origin|`` and ``beta`` is the bearing of the centre. The first term is the
    range-noise model of a laser scanner: ``rho_hat_i`` is the range at which return i's beam
    first meets the circle (``b - sqrt(r^2 - s^2)`` with ``b``, ``s`` the centre's coordinates
    along and across the beam; a beam that misses adds the miss distance as a second residual).
    For the two edge returns of an averaging scanner (``beam_divergence`` > 0) it is the mean
    range over the part of the beam footprint that hits the circle (closed form), which is
    where a beam that grazes the trunk really returns. With ``residuals="orthogonal"`` the
    first term is the former orthogonal-distance fit ``(|p_i - c| - r) / sigma``. Either is made
    robust to a mixed pixel or outlier by a Huber loss (k = 1.5 sigma) followed, for N >= 6, by
    rejecting up to N // 4 returns beyond 4 sigma and refitting (``rms`` is then over the
    inliers). The second term is the beam-width-aware silhouette: a beam returns only if it
    hits the trunk, so the tangent bearing of each side lies between the edge beam and the
    neighbouring beam that missed; by default ``t_edge`` is the middle of that interval (edge
    bearing -+ angle_increment / 2) and ``s_edge = angle_increment / sqrt(12)`` the standard
    deviation of a uniform interval of that width; ``silhouette`` replaces both per side (the
    detector narrows them when the neighbouring beam saw the background or a mixed pixel).
    With a silhouette, steps are only accepted while the centre stays behind the visible arc
    (``D > r`` and ``D`` beyond the nearest return).
    Solved by Levenberg-Marquardt from a silhouette-based start; the covariance is the inverse
    Gauss-Newton Hessian of the normalised residuals (so it is scaled by ``sigma`` if given,
    else by the residual RMS with ``N - 3`` degrees of freedom, floored at 0.2 mm). With both
    edges used, the Gaussian tangent terms are then replaced by the uniform intervals they
    stand for (width ``sqrt(12) * s_edge``): one expectation-propagation sweep on that Gaussian
    posterior, whose mean and covariance are returned (docs/algorithms/scan-fits.md, "Uniform
    tangent intervals").

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
        Returns of one segment, any order.
    origin : array_like of shape (2,), metres, optional
        Sensor position in the points' frame (default (0, 0)).
    sigma : float, metres, optional
        Range noise standard deviation; estimated from the residuals when omitted.
    angle_increment : float, radians, optional
        Beam spacing; estimated as the median bearing gap of the points when omitted.
    edges : (bool, bool)
        Whether the first / last return (in bearing order) is a true silhouette edge. Pass
        False for a side occluded by a nearer object (a partial segment): that side's term is
        dropped. With both False, or when the points are not all within +-90 deg of their mean
        bearing from ``origin`` (no visible side, e.g. a full ring around the sensor), the fit is
        a plain robust geometric (orthogonal-distance) fit started from Kasa.
    beam_divergence : float, radians, optional
        Full angular width of the beam footprint of an averaging scanner (one that reports the
        mean range of what its footprint hits: mixed pixels). 0 / None: thin beams.
    silhouette : array_like of shape (2, 2), optional
        Rows (first, last return in bearing order): ``(offset, std)`` of the tangent bearing
        beyond the edge return, in units of ``angle_increment``; NaN keeps the default
        ``(0.5, 1 / sqrt(12))``.
    residuals : {"range", "orthogonal"}
        Noise model of the returns (see above); "range" by default.

    Returns
    -------
    CircleFit
        With ``cov`` over (cx, cy, r). Falsy with a reason for fewer than 3 points, coincident
        or collinear points without a silhouette, a partial arc (one edge occluded) with only 3
        returns, or when no valid circle behind the arc exists.

    Raises
    ------
    InputError
        If ``points`` is not a finite (N, 2) array, or ``origin``/``sigma``/``angle_increment``/
        ``beam_divergence``/``silhouette`` are invalid.
    ConfigError
        If ``residuals`` is unknown.

    Notes
    -----
    Why it is needed: on a short arc seen from one side, the algebraic fits (Kasa, and
    Fletcher-Reeves which converges to the same solution) shrink the radius toward the chord,
    and any unconstrained fit has a near-flat cost along "bigger circle further away"; the
    silhouette pins r / D to within a beam, the points pin the front surface, and the
    geometric residual has no algebraic bias. See docs/algorithms/scan-fits.md for numbers
    (simulated arcs by range, real TLS trunk geometry) and the known small negative bias.

    References
    ----------
    This project (issue 2). Geometric vs algebraic circle fits and the short-arc bias of Kasa:
    Chernov N. (2010), "Circular and Linear Regression: Fitting Circles and Lines by Least
    Squares", CRC Press.

    Examples
    --------
    >>> import numpy as np
    >>> a = np.radians(np.arange(-1.5, 1.51, 0.5))
    >>> u = np.column_stack((np.cos(a), np.sin(a)))
    >>> b = u @ [5.0, 0.0]
    >>> pts = u * (b - np.sqrt(b * b - (25.0 - 0.15**2)))[:, None]
    >>> fit = fit_circle_ours(pts, angle_increment=np.radians(0.5), sigma=0.005)
    >>> bool(fit), abs(fit.radius - 0.15) < 0.01
    (True, True)
    >>> fit_circle_ours(pts[:2]).reason
    'need at least 3 points for a circle fit'
    """
    p = as_points(points)
    o = _origin(origin)
    n = p.shape[0]
    if n < 3:
        return CircleFit.failed(STATUS_MESSAGES[1], "ours", n)
    sig = _check_sigma(sigma)
    inc = _check_increment(angle_increment)
    e = np.asarray(edges)
    if e.shape != (2,):
        raise InputError(f"edges must be a pair of booleans (first, last), got {edges!r}.")
    lo, hi = bool(e[0]), bool(e[1])
    foot = _check_divergence(beam_divergence)
    sil = _check_silhouette(silhouette, 1)
    use_range = _check_residuals(residuals)
    out, status = fit_ours_segments(
        p[:, 0],
        p[:, 1],
        np.zeros(1, dtype=np.int64),
        np.array([n], dtype=np.int64),
        o[:1],
        o[1:],
        np.array([sig]),
        np.array([inc]),
        np.array([lo]),
        np.array([hi]),
        sil,
        foot,
        use_range,
    )
    if status[0] != 0:
        return CircleFit.failed(STATUS_MESSAGES[int(status[0])], "ours", n)
    row = out[0]
    return CircleFit(
        center=row[:2].copy(),
        radius=float(row[2]),
        cov=row[3:12].reshape(3, 3).copy(),
        rms=float(row[12]),
        n_points=n,
        method="ours",
    )
