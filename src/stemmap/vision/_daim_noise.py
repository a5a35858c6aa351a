"""Measurement covariance of one DAIM detection from the depth camera's noise model (ours).

Munjer et al. (2025, §3.4-3.6) give DAIM's detections no covariance: FastSLAM and the Kalman
refinement weigh a trunk seen at 2 m like one seen at 11 m. A stereo depth camera's error grows
with the square of the depth (``sigma_z = k z^2``; RealSense D435: ``k = subpixel / (focal x
baseline)``, :data:`stemmap.vision.depth.D435_DEPTH_NOISE_K`), and the three-point circle
(Munjer eqs. 5-8) amplifies its arc points' errors, most where the arc is flat. This module
propagates the noise model through the fit to first order:

* each arc point ``P_i`` (horizontal plane, range ``rho_i`` from the camera along the unit ray
  ``u_i``) moves along its ray with ``sigma = k rho_i^2`` (the per-pixel RMS of the model: the
  bin median's reduction is not counted, a real stereo camera's error is correlated across the
  matching window) and across it with ``rho_i * stride / (f_x sqrt(12))`` (the pixel column's
  quantisation);
* the centre ``O`` and radius ``r`` of the fit are differentiated by the points: analytically
  for the three-point circle (the bisector equations ``(C - A).O = (|C|^2 - |A|^2) / 2`` and
  ``(B - C).O = (|B|^2 - |C|^2) / 2`` differentiated:
  ``(C - A).dO = (C - O).dC - (A - O).dA``, ``(B - C).dO = (B - O).dB - (C - O).dC``;
  ``r`` the mean of ``|P - O|`` over A, B, C), by central differences for any other fit;
* ``cov(O_x, O_y, r) = G Sigma_P G^T``;
* bounded by the trunk's geometry (:func:`physical_bound`, :func:`bound_covariance`): a nearly
  collinear arc makes ``G`` ill-conditioned and the first-order sigma metres to kilometres,
  where the linearisation no longer describes the error. The centre of a trunk is its
  visible surface's middle point ``B`` plus one radius along the ray, and a radius above the
  width check's limit ``r_lim`` is not a trunk's, so the centre cannot be less certain than
  ``B + r u`` with ``r`` anywhere in ``[0, r_lim]``: ``Sigma_phys = J diag(Sigma_B, r_lim^2)
  J^T`` with ``J = [[I, u], [0, 1]]`` (variance ``r_lim^2``: the second moment of an error up
  to ``r_lim`` either way). The covariance is clipped to it in ``Sigma_phys``'s metric
  (eigenvalues of ``L^-1 Sigma L^-T`` above 1 set to 1, ``Sigma_phys = L L^T``): unchanged
  where it is already the smaller, the bound where it is not;
* a fit that fails the width check (its circle, wider than the trunk can be, is the noise
  flattening the arc) or has its centre on the camera's side of the arc
  (:func:`centre_behind_arc`: the noise bent it the wrong way) has no trunk centre to
  propagate: the detection's centre is then
  :func:`surface_centre` (``B`` plus half the visible width along the ray, the radius of a
  cylinder whose arc is that wide) and its covariance ``Sigma_phys``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from stemmap.scan._circle_base import _by_bearing
from stemmap.scan.circle import fit_circle
from stemmap.types import FloatArray

__all__ = [
    "arc_point_covariances",
    "bound_covariance",
    "centre_behind_arc",
    "fit_covariance",
    "physical_bound",
    "surface_centre",
]


def arc_point_covariances(
    arc: ArrayLike, origin_xy: ArrayLike, *, depth_noise_k: float, pixel_angle: float
) -> FloatArray:
    """Covariances (M, 2, 2) of the arc points: ``sigma_r = k rho^2`` along the ray from
    ``origin_xy``, ``sigma_t = rho pixel_angle / sqrt(12)`` across it.

    Examples
    --------
    >>> c = arc_point_covariances([[10.0, 0.0]], [0.0, 0.0], depth_noise_k=0.0036,
    ...                           pixel_angle=0.0)
    >>> round(float(np.sqrt(c[0, 0, 0])), 3), float(c[0, 1, 1])
    (0.36, 0.0)
    """
    p = np.asarray(arc, dtype=np.float64).reshape(-1, 2)
    rel = p - np.asarray(origin_xy, dtype=np.float64).reshape(2)
    rho = np.hypot(rel[:, 0], rel[:, 1])
    u = rel / np.where(rho > 0, rho, 1.0)[:, None]
    t = np.column_stack((-u[:, 1], u[:, 0]))
    sr2 = (depth_noise_k * rho**2) ** 2
    st2 = (rho * pixel_angle) ** 2 / 12.0
    out: FloatArray = sr2[:, None, None] * np.einsum("mi,mj->mij", u, u) + st2[
        :, None, None
    ] * np.einsum("mi,mj->mij", t, t)
    return out


def _three_point_jacobian(abc: FloatArray, center: FloatArray) -> FloatArray:
    """G (3, 6): d(O_x, O_y, r) / d(A, C, B) of the three-point circle (module docstring)."""
    a, c, b = abc
    o = center
    m = np.array([c - a, b - c])
    minv = np.linalg.inv(m)
    g = np.zeros((3, 6))
    g[:2, 0:2] = minv @ np.array([-(a - o), [0.0, 0.0]])
    g[:2, 2:4] = minv @ np.array([c - o, -(c - o)])
    g[:2, 4:6] = minv @ np.array([[0.0, 0.0], b - o])
    for i, p in enumerate((a, c, b)):
        n = (p - o) / max(float(np.hypot(*(p - o))), 1e-12)
        # dr = mean over the points of n_P . (dP - dO)
        g[2, 2 * i : 2 * i + 2] += n / 3.0
        g[2] -= (n @ g[:2]) / 3.0
    return g


def fit_covariance(
    arc: ArrayLike,
    center: ArrayLike,
    origin_xy: ArrayLike,
    method: str,
    *,
    depth_noise_k: float,
    pixel_angle: float,
    step: float = 1e-4,
) -> FloatArray:
    """Covariance (3, 3) of a fit's (centre x, centre y, radius) from the depth-noise model,
    first order (module docstring).

    Parameters
    ----------
    arc : (M, 2) metres, the points the fit used
    center : (2,) the fit's centre
    origin_xy : (2,) the camera position (orders the points by bearing, as the fit does)
    method : the fit's name (``"three_point"``: analytic; others: central differences)
    depth_noise_k, pixel_angle : :func:`arc_point_covariances`
    step : metres, the central-difference step

    Returns
    -------
    (3, 3) symmetric; NaN if the fit is degenerate (collinear points).

    Examples
    --------
    A half circle of radius 0.15 m at 5 m: the centre's range error is about the point noise
    (k 5^2 = 0.09 m; on a half circle the radius is stationary in the sagitta, so the centre
    follows the middle point), its cross-range error small.

    >>> a = np.array([[4.85, 0.0], [5.0, -0.15], [5.0, 0.15]])
    >>> c = fit_covariance(a, [5.0, 0.0], [0.0, 0.0], "three_point", depth_noise_k=0.0036,
    ...                    pixel_angle=0.0)
    >>> bool(0.5 * 0.09 < np.sqrt(c[0, 0]) < 2 * 0.09), bool(np.sqrt(c[1, 1]) < 0.01)
    (True, True)
    """
    p = np.asarray(arc, dtype=np.float64).reshape(-1, 2)
    o = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    ctr = np.asarray(center, dtype=np.float64).reshape(2)
    kw = {"depth_noise_k": depth_noise_k, "pixel_angle": pixel_angle}
    if method == "three_point":
        srt, _, _ = _by_bearing(p, o)
        abc = srt[[0, srt.shape[0] // 2, srt.shape[0] - 1]]
        try:
            g = _three_point_jacobian(abc, ctr)
        except np.linalg.LinAlgError:
            return np.full((3, 3), np.nan)
        pts = abc
    else:
        m = p.shape[0]
        g = np.zeros((3, 2 * m))
        for j in range(m):
            for ax in range(2):
                cols = []
                for sgn in (1.0, -1.0):
                    pp = p.copy()
                    pp[j, ax] += sgn * step
                    f = fit_circle(pp, method, origin=o)
                    if not f:
                        return np.full((3, 3), np.nan)
                    cols.append(np.r_[f.center, f.radius])
                g[:, 2 * j + ax] = (cols[0] - cols[1]) / (2.0 * step)
        pts = p
    pc = arc_point_covariances(pts, o, **kw)
    sp = np.zeros((2 * pts.shape[0], 2 * pts.shape[0]))
    for j in range(pts.shape[0]):
        sp[2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = pc[j]
    cov: FloatArray = g @ sp @ g.T
    return 0.5 * (cov + cov.T)


def _middle_ray(arc: ArrayLike, origin_xy: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The arc's middle point by bearing (the three-point fit's ``B``) and its unit ray."""
    srt, _, _ = _by_bearing(np.asarray(arc, dtype=np.float64).reshape(-1, 2), origin_xy)
    b: FloatArray = srt[srt.shape[0] // 2]
    rel = b - origin_xy
    return b, rel / max(float(np.hypot(*rel)), 1e-12)


def centre_behind_arc(arc: ArrayLike, center: ArrayLike, origin_xy: ArrayLike) -> bool:
    """Whether ``center`` lies beyond the arc's middle point (by bearing) along its ray from
    ``origin_xy``: a trunk shows the camera its near, convex side, so its centre is behind
    the visible arc. A fit with the centre on the camera's side is the depth noise bending
    the arc the wrong way (the middle point pushed back, the ends pulled in), not a trunk.

    Examples
    --------
    >>> arc, o = [[9.9, -0.1], [9.85, 0.0], [9.9, 0.1]], [0.0, 0.0]
    >>> centre_behind_arc(arc, [10.0, 0.0], o), centre_behind_arc(arc, [9.7, 0.0], o)
    (True, False)
    """
    o = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    b, u = _middle_ray(arc, o)
    return bool((np.asarray(center, dtype=np.float64).reshape(2) - b) @ u > 0.0)


def surface_centre(arc: ArrayLike, origin_xy: ArrayLike, radius: float) -> FloatArray:
    """The centre one ``radius`` behind the arc's middle point along its ray: where a trunk
    whose arc does not resolve its curvature (a fit failing the width check) stands, with the
    covariance :func:`physical_bound`.

    Examples
    --------
    >>> surface_centre([[9.9, -0.1], [9.85, 0.0], [9.9, 0.1]], [0.0, 0.0], 0.1).tolist()
    [9.95, 0.0]
    """
    o = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    b, u = _middle_ray(arc, o)
    out: FloatArray = b + radius * u
    return out


def physical_bound(
    arc: ArrayLike,
    origin_xy: ArrayLike,
    r_lim: float,
    *,
    depth_noise_k: float,
    pixel_angle: float,
    keep_cross: ArrayLike | None = None,
) -> FloatArray:
    """Covariance (3, 3) of (centre x, centre y, radius) when the centre is the arc's middle
    point (by bearing) plus a radius with variance ``r_lim^2`` along its ray (module docstring).

    ``keep_cross`` (3, 3), a fit's covariance: the bound takes its variance across the ray
    when larger (the bearings determine it, not the ill-conditioned range: only the range and
    radius are bounded).

    Examples
    --------
    >>> b = physical_bound([[9.9, -0.1], [9.85, 0.0], [9.9, 0.1]], [0.0, 0.0], 0.3,
    ...                    depth_noise_k=0.0036, pixel_angle=0.0)
    >>> round(float(np.sqrt(b[0, 0])), 3), round(float(np.sqrt(b[2, 2])), 3)
    (0.46, 0.3)
    """
    o = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    b, u = _middle_ray(arc, o)
    sb = arc_point_covariances(b[None], o, depth_noise_k=depth_noise_k, pixel_angle=pixel_angle)
    j = np.zeros((3, 3))
    j[:2, :2] = np.eye(2)
    j[:2, 2] = u
    j[2, 2] = 1.0
    s = np.zeros((3, 3))
    s[:2, :2] = sb[0]
    s[2, 2] = r_lim**2
    out: FloatArray = j @ s @ j.T
    if keep_cross is not None:
        t = np.array([-u[1], u[0]])
        more = float(t @ np.asarray(keep_cross, dtype=np.float64)[:2, :2] @ t) - float(
            t @ out[:2, :2] @ t
        )
        if np.isfinite(more) and more > 0:
            out[:2, :2] += more * np.outer(t, t)
    return out


def bound_covariance(cov: ArrayLike, bound: ArrayLike) -> FloatArray:
    """``cov`` clipped to ``bound`` (both (3, 3)): in the metric of ``bound = L L^T`` the
    eigenvalues of ``L^-1 cov L^-T`` above 1 become 1, so the result is below both (Loewner
    order) and equals ``cov`` where ``cov`` is already below ``bound``; non-finite ``cov``
    (a degenerate fit) becomes ``bound``.

    Examples
    --------
    >>> c = bound_covariance(np.diag([100.0, 0.01, 4.0]), np.diag([0.25, 0.25, 0.09]))
    >>> np.round(np.diag(c), 3).tolist()
    [0.25, 0.01, 0.09]
    """
    c = np.asarray(cov, dtype=np.float64).reshape(3, 3)
    bd = np.asarray(bound, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(c).all():
        return bd.copy()
    ell = np.linalg.cholesky(0.5 * (bd + bd.T))
    m = np.linalg.solve(ell, np.linalg.solve(ell, c).T)  # L^-1 C L^-T (symmetric)
    w, v = np.linalg.eigh(0.5 * (m + m.T))
    if w.max() <= 1.0:
        return c
    out: FloatArray = ell @ (v * np.minimum(w, 1.0)) @ v.T @ ell.T
    return 0.5 * (out + out.T)
