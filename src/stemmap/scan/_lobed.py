"""Lobed-outline model of a trunk cross-section (ours, issue 11, fifteenth round).

A real trunk at breast height is not a circle: its outline departs from the best circle in a
few smooth lobes (aRchi tree 1: ±2-3 cm on a 27.6 cm radius). A 2D scan sees one side of it,
and the circle fitted to that side is biased and may fail the RMS test although the outline is
a trunk's. The model is the truncated Fourier series of the radius around the centre,

    r(theta) = r0 + sum_{k=2..K} a_k cos(k theta) + b_k sin(k theta),

a polar Fourier descriptor of a closed outline (Zahn & Roskies 1972, "Fourier descriptors for
plane closed curves", IEEE Trans. Computers C-21(3)) applied to the stem's cross-section, the
radius as a function of direction of Matérn (1956, "On the geometry of the cross-section of a
stem", Meddelanden från Statens Skogsforskningsinstitut 46(11)): its mean is the mean radius,
and its harmonic k = 1 is only the choice of centre, so the model starts at k = 2.

The harmonics are fitted jointly with the centre (:func:`fit_lobed`: orthogonal residuals
``e_i = |p_i - c| - r(theta_i)``, the silhouette's two tangent bearings as in the circle fit,
and a Gaussian prior of std ``lobe_prior x r`` on each coefficient, i.e. Tikhonov
regularisation toward the circle). On a partial arc the low harmonics are almost collinear
with the centre and r0 (condition number 1e3-1e5 on 60-120 degree arcs, scan-detection-history.md,
fifteenth round): the prior, measured on the real rings' full outlines
(``benchmarks/lobed_outlines.py``), decides how much of the arc's departure from a circle is
called a lobe, and the silhouette keeps r0 from sliding along the near-null direction.

Reported: the area-equivalent radius ``sqrt(r0^2 + sum (a_k^2 + b_k^2) / 2)`` (the basal-area
convention; the mean radius r0 differs by < 0.5 % at the real rings' lobe sizes), the residual
RMS to the lobed outline (what the RMS test then judges, with the degrees of freedom the
harmonics take) and the lobe amplitude ``sqrt(sum (a_k^2 + b_k^2) / 2) / r0`` (the RMS of the
lobe profile relative to the radius, bounded by ``lobe_max``). On a partial arc the fitted
amplitude is shrunk by the prior: it bounds what the arc shows, not the whole outline's lobes.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.segment import Segments

#: Fewest returns of a candidate the lobed model is fitted to (3 + 2 (K - 1) parameters: 7 for
#: K = 3; fewer returns than ten leave the residual RMS with too few degrees of freedom).
LOBED_MIN_POINTS = 10


class LobedFit(NamedTuple):
    """One lobed-outline fit: centre, area-equivalent radius, mean radius, harmonic
    coefficients ``(a_2, b_2, ..., a_K, b_K)``, residual RMS to the outline, relative lobe
    amplitude (RMS of the lobe profile / r0), the (x, y, r0) posterior covariance, whether the
    fit converged, and the effective number of parameters (3 for the circle, up to 3 + 2 (K -
    1) as the prior loosens: ``3 + 2 (K - 1) - trace((J^T J)^-1 Lambda)`` with ``Lambda`` the
    prior's precision, the trace of the regularised hat matrix)."""

    center: FloatArray
    radius: float
    r0: float
    coef: FloatArray
    rms: float
    amplitude: float
    cov: FloatArray
    ok: bool
    n_params: float


def harmonic_columns(theta: FloatArray, k_max: int) -> FloatArray:
    """(n, 2 (k_max - 1)) matrix ``[cos 2θ, sin 2θ, ..., cos Kθ, sin Kθ]``."""
    ks = np.arange(2, k_max + 1)
    kt = np.outer(theta, ks)
    out = np.empty((theta.shape[0], 2 * ks.size))
    out[:, 0::2] = np.cos(kt)
    out[:, 1::2] = np.sin(kt)
    return out


def ring_harmonics(xy: FloatArray, center: FloatArray, k_max: int) -> tuple[float, FloatArray]:
    """Fixed-centre linear least-squares fit of ``r(θ) = r0 + a_1 cos θ + b_1 sin θ + sum_k
    ...`` to a ring's points (polar coordinates around ``center``): r0 and the coefficients
    of k = 2..k_max (k = 1, a shift of the centre, is fitted and dropped). For full rings,
    where the harmonics are well conditioned: what :func:`fit_lobed`'s prior is measured on."""
    q = xy - center
    theta = np.arctan2(q[:, 1], q[:, 0])
    rho = np.hypot(q[:, 0], q[:, 1])
    a = np.column_stack((np.ones_like(theta), np.cos(theta), np.sin(theta)))
    a = np.hstack((a, harmonic_columns(theta, k_max)))
    sol = np.linalg.lstsq(a, rho, rcond=None)[0]
    return float(sol[0]), np.asarray(sol[3:])


def _profile(theta: FloatArray, r0: float, coef: FloatArray, k_max: int) -> FloatArray:
    out: FloatArray = r0 + harmonic_columns(np.atleast_1d(theta), k_max) @ coef
    return out


def _residuals(
    p: FloatArray,
    x: FloatArray,
    y: FloatArray,
    sigma: float,
    edges: tuple[tuple[float, float, int], ...],
    tau: float,
    k_max: int,
) -> FloatArray:
    """Normalised residuals of :func:`fit_lobed`: returns, silhouette edges, prior."""
    cx, cy, r0, coef = p[0], p[1], p[2], p[3:]
    dx, dy = x - cx, y - cy
    theta = np.arctan2(dy, dx)
    e = (np.hypot(dx, dy) - _profile(theta, r0, coef, k_max)) / sigma
    out = [e]
    if edges:
        d = math.hypot(cx, cy)
        beta = math.atan2(cy, cx)
        for t_edge, s_edge, side in edges:
            # the tangent point of the side seen at bearing beta + side asin(rho / D) lies at
            # polar angle beta + pi - side acos(rho / D) around the centre (circle geometry,
            # rho the outline's radius there: two passes)
            rho = r0
            for _ in range(2):
                u = min(rho / d, 1.0) if d > 0 else 1.0
                phi = beta + math.pi - side * math.acos(u)
                rho = float(_profile(np.array([phi]), r0, coef, k_max)[0])
            u = min(max(rho / d, -1.0), 1.0) if d > 0 else 1.0
            miss = math.remainder(beta + side * math.asin(u) - t_edge, 2.0 * math.pi)
            out.append(np.array([miss / s_edge]))
    out.append(coef / tau)
    return np.concatenate(out)


def fit_lobed(
    x: FloatArray,
    y: FloatArray,
    center: FloatArray,
    radius: float,
    sigma: float,
    k_max: int,
    prior: float,
    edges: tuple[tuple[float, float, int], ...] = (),
    iterations: int = 50,
) -> LobedFit:
    """The lobed outline (module docstring) fitted to returns ``x, y`` (sensor at the origin)
    from the circle ``center, radius``: Levenberg-Marquardt (numerical Jacobian) on ``(cx, cy,
    r0, a_2, b_2, ..., a_K, b_K)`` minimising ``sum e_i^2 / sigma^2 + sum_edges ((beta + side
    asin(r(phi_edge) / D) - t_edge) / s_edge)^2 + sum_k (a_k^2 + b_k^2) / (prior r)^2``: the
    orthogonal residuals ``e_i`` to the outline, the silhouette's tangent bearings as in the
    circle fit (:func:`~stemmap.scan.circle.fit_circle_ours`, ``edges``: (t_edge, s_edge,
    side) per true edge, side +1 for the larger bearing; the outline's radius at the tangent
    point stands for its support function, exact for the circle and to first order in the
    lobes) and the Gaussian prior (``r`` the circle's radius, fixed). Without the edges a
    partial arc's r0 slides along the near-null direction of the lobes (scan-detection-history.md,
    fifteenth round: a flank of a lobed trunk fits as a flatter, larger circle)."""
    m = 2 * (k_max - 1)
    p = np.concatenate((np.asarray(center, dtype=np.float64), [radius], np.zeros(m)))
    tau = max(prior * radius, 1e-9)
    sigma = max(sigma, 1e-6)

    def res(q: FloatArray) -> FloatArray:
        return _residuals(q, x, y, sigma, edges, tau, k_max)

    f = res(p)
    cost = float(f @ f)
    lam = 1e-3
    ok = False
    jtj = np.eye(3 + m)
    h = np.concatenate((np.full(3, 1e-6), np.full(m, 1e-6)))
    for _ in range(iterations):
        jac = np.empty((f.shape[0], 3 + m))
        for i in range(3 + m):
            q = p.copy()
            q[i] += h[i]
            jac[:, i] = (res(q) - f) / h[i]
        jtj = jac.T @ jac
        g = jac.T @ f
        while True:
            try:
                step = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-12), -g)
            except np.linalg.LinAlgError:
                step = np.full(3 + m, np.nan)
            q = p + step
            fq = res(q) if np.all(np.isfinite(q)) and q[2] > 0 else np.full_like(f, np.inf)
            cq = float(fq @ fq)
            if np.isfinite(cq) and cq <= cost:
                p, f, lam = q, fq, max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
            if lam > 1e8:
                break
        if lam > 1e8:
            ok = True  # no step lowers the cost: a minimum (within the Jacobian's precision)
            break
        done = cost - cq <= 1e-8 * max(cost, 1.0) or float(np.max(np.abs(step[:3]))) < 1e-7
        cost = cq
        if done:
            ok = True
            break
    dx, dy = x - p[0], y - p[1]
    theta = np.arctan2(dy, dx)
    coef = p[3:]
    e = np.hypot(dx, dy) - _profile(theta, float(p[2]), coef, k_max)
    rms = float(np.sqrt(np.mean(e * e)))
    r0 = float(p[2])
    half_sq = 0.5 * float(coef @ coef)
    ok = ok and r0 > 0 and math.isfinite(rms)
    try:
        inv = np.linalg.inv(jtj)
        cov = np.asarray(inv[:3, :3] * max(1.0, rms * rms / (sigma * sigma)), dtype=np.float64)
        n_params = 3 + m - float(np.trace(inv[3:, 3:])) / (tau * tau)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.nan)
        n_params = float(3 + m)
    return LobedFit(
        center=p[:2].copy(),
        radius=math.sqrt(r0 * r0 + half_sq) if r0 > 0 else math.nan,
        r0=r0,
        coef=coef.copy(),
        rms=rms,
        amplitude=math.sqrt(half_sq) / r0 if r0 > 0 else math.inf,
        cov=cov,
        ok=ok,
        n_params=n_params,
    )


def lobed_refit(
    cfg: DetectorConfig,
    segs: Segments,
    centers: FloatArray,
    radii: FloatArray,
    covs: FloatArray,
    ok: NDArray[np.bool_],
    test_rms: FloatArray,
    sigma: FloatArray,
    sil_width: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """``lobe_harmonics``: every fitted candidate of >= :data:`LOBED_MIN_POINTS` returns that
    fails the RMS test (:func:`~stemmap.scan.plausibility.rms_limit`) fitted again with the
    lobed outline (:func:`fit_lobed`). It takes the lobed fit's centre, area-equivalent radius,
    covariance and residual RMS when that RMS passes the RMS test at that radius, the lobe
    amplitude is <= ``lobe_max`` and the silhouette is no wider than the outline (``sil_width
    <= 2 (r0 + max lobe) + 2 max_rms_sigma sigma``). Returns new centres, radii, covariances
    and test RMS (the inputs are not modified) and which candidates the lobed fit replaced."""
    from stemmap.scan.plausibility import rms_limit

    with np.errstate(invalid="ignore"):
        fails = ok & (segs.counts >= LOBED_MIN_POINTS) & ~(test_rms <= rms_limit(cfg, sigma, radii))
    lobed = np.zeros(len(segs), dtype=bool)
    if not np.any(fails):
        return centers, radii, covs, test_rms, lobed
    centers, radii, covs, test_rms = centers.copy(), radii.copy(), covs.copy(), test_rms.copy()
    p = segs.points
    one = np.ones(1)
    inc = abs(p.angle_increment)
    s_edge = inc / math.sqrt(12.0)
    # true silhouette edges (neither occluded nor truncated), in beam order
    first = ~(segs.occluded_start | segs.truncated_start)
    last = ~(segs.occluded_end | segs.truncated_end)
    for j in np.flatnonzero(fails):
        a, b = int(segs.start[j]), int(segs.stop[j])
        s = float(sigma[j])
        x, y = p.x[a:b], p.y[a:b]
        bear = np.unwrap(np.arctan2(y, x))
        up = 1 if bear[-1] >= bear[0] else -1  # +1: bearings increase in beam order
        ends = ((0, bool(first[j]), -up), (-1, bool(last[j]), up))
        # the tangent lies between the edge beam and the next one that missed: half a step out
        edges = tuple((float(bear[i]) + side * 0.5 * inc, s_edge, side) for i, f, side in ends if f)
        fit = fit_lobed(
            x, y, centers[j], float(radii[j]), s, cfg.lobe_harmonics, cfg.lobe_prior, edges
        )
        if not (fit.ok and fit.amplitude <= cfg.lobe_max):
            continue
        limit = float(rms_limit(cfg, s * one, fit.radius * one)[0])
        # the residual scale with the degrees of freedom the harmonics take (the circle's
        # plain RMS convention when they take none): RSS / (n - (n_params - 3))
        n = b - a
        scale = fit.rms * math.sqrt(n / max(n - (fit.n_params - 3.0), 1.0))
        # the widest the outline can be: twice its largest radius (r0 + the lobes' peak)
        widest = 2.0 * (fit.r0 + float(np.sum(np.abs(fit.coef)))) + 2.0 * cfg.max_rms_sigma * s
        if scale <= limit and sil_width[j] <= widest:
            centers[j], radii[j], covs[j], test_rms[j] = fit.center, fit.radius, fit.cov, fit.rms
            lobed[j] = True
    return centers, radii, covs, test_rms, lobed
