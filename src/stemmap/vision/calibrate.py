"""Laser-camera calibration: laser-plane-to-image homography G, the notched plate, and PnP.

* :func:`fit_homography_xue2018` -- G by linear least squares with g11 = 1 (Xue 2018, eqs. 7-11).
* :func:`fit_homography_dlt` -- Hartley-normalised DLT (SVD, no fixed entry).
* :func:`fit_homography_ransac` -- robust DLT on minimal 4-point samples.
* :func:`refine_homography` -- Levenberg-Marquardt on the pixel reprojection error.
* :func:`solve_plate_points` -- the notched plate model (Xue 2018 §2.3.4, eqs. 4-6).
* :func:`solve_pnp` -- LiDAR-camera extrinsics from 3D-2D pairs with known intrinsics
  (visual-lidar odometry paper, §2.1, eq. 1; OpenCV solvePnP).

Every fit returns a result that is falsy with a ``reason`` when it fails.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray
from stemmap.vision.camera import CameraModel, RigidTransform, apply_homography

__all__ = [
    "HOMOGRAPHY_METHODS",
    "XUE2018_PLATE",
    "HomographyFit",
    "PlateModel",
    "PlatePoints",
    "PoseFit",
    "fit_homography",
    "fit_homography_dlt",
    "fit_homography_ransac",
    "fit_homography_xue2018",
    "plate_edges_from_scan",
    "refine_homography",
    "reprojection_errors",
    "solve_plate_points",
    "solve_pnp",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# Homography G: laser plane (x, y) metres -> image (u, v) pixels
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class HomographyFit:
    """A fitted laser-to-image homography.

    Attributes
    ----------
    G : ndarray (3, 3), scaled so g11 = 1 (Xue's normalisation) when |g11| is not tiny
    rms_px : float
        Root-mean-square reprojection error over the inliers, pixels.
    residuals_px : ndarray (N,)
        Per-correspondence reprojection error, pixels.
    inliers : ndarray of bool (N,)
    method : str
    ok : bool
    reason : str
    """

    G: FloatArray
    rms_px: float
    residuals_px: FloatArray
    inliers: NDArray[np.bool_]
    method: str
    ok: bool = True
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok

    @classmethod
    def failed(cls, reason: str, method: str, n: int = 0) -> HomographyFit:
        return cls(
            np.full((3, 3), np.nan),
            math.nan,
            np.full(n, np.nan),
            np.zeros(n, bool),
            method,
            False,
            reason,
        )

    def project(self, xy: ArrayLike) -> FloatArray:
        """Map laser points (N, 2) to pixels (N, 2)."""
        return apply_homography(self.G, xy)


def _pairs(xy: ArrayLike, uv: ArrayLike) -> tuple[FloatArray, FloatArray]:
    p = np.asarray(xy, dtype=np.float64)
    q = np.asarray(uv, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or q.shape != p.shape:
        raise InputError(
            f"laser points xy and image points uv must both have shape (N, 2); got {p.shape} "
            f"and {q.shape}."
        )
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise InputError("calibration correspondences contain NaN or inf values.")
    return p, q


def _normalise_g(G: FloatArray) -> FloatArray:
    if abs(G[0, 0]) > 1e-9 * np.abs(G).max():
        return G / G[0, 0]
    return G / np.linalg.norm(G)


def reprojection_errors(G: ArrayLike, xy: ArrayLike, uv: ArrayLike) -> FloatArray:
    """Pixel distance between ``G``-projected laser points and measured pixels, shape (N,)."""
    p, q = _pairs(xy, uv)
    d = apply_homography(G, p) - q
    err = np.hypot(d[:, 0], d[:, 1])
    return np.where(np.isfinite(err), err, np.inf)


def _finish(
    G: FloatArray,
    p: FloatArray,
    q: FloatArray,
    method: str,
    inliers: NDArray[np.bool_] | None = None,
) -> HomographyFit:
    if not np.all(np.isfinite(G)):
        return HomographyFit.failed("solution is not finite", method, p.shape[0])
    G = _normalise_g(G)
    res = reprojection_errors(G, p, q)
    inl = np.ones(p.shape[0], bool) if inliers is None else inliers
    rms = float(np.sqrt(np.mean(res[inl] ** 2))) if np.any(inl) else math.nan
    return HomographyFit(G, rms, res, inl, method)


def _degenerate(p: FloatArray) -> bool:
    """True if the laser points are (near-)collinear: a homography is then undetermined."""
    q = p - p.mean(axis=0)
    sv = np.linalg.svd(q, compute_uv=False)
    return bool(sv[-1] < 1e-9 * max(sv[0], 1e-300))


def fit_homography_xue2018(xy: ArrayLike, uv: ArrayLike) -> HomographyFit:
    """Laser-to-image matrix G by linear least squares with g11 = 1 (Xue et al. 2018, eq. 11).

    Each pair (x, y, u, v) gives the two rows of eq. 10:

        g12 y + g13 - u (g31 x + g32 y + g33) = -x
        g21 x + g22 y + g23 - v (g31 x + g32 y + g33) = 0

    stacked into A X = b with X = (g12, g13, g21, g22, g23, g31, g32, g33) and solved by least
    squares. As printed the system is unnormalised (pixels ~1e3 next to metres ~1): we solve it
    exactly as the paper does; :func:`fit_homography_dlt` is the conditioned alternative.

    Parameters
    ----------
    xy : array_like (N, 2), metres -- laser-frame points
    uv : array_like (N, 2), pixels -- their image positions; N >= 5 (eq. 9: 2N >= 8 unknowns)

    Returns
    -------
    HomographyFit
        Falsy if N < 5, the laser points are collinear, or the system is rank-deficient.
        Fixing g11 = 1 fails when the true g11 is 0 (rare: laser x axis mapping to no u change).

    Examples
    --------
    >>> G = np.array([[1.0, 0.52, -0.14], [0.01, 0.24, 0.49], [2e-4, 1.6e-3, -2e-4]])
    >>> xy = np.array([[0.2, 2.2], [0.4, 1.9], [-0.8, 2.2], [0.0, 3.0], [0.5, 2.6], [-0.3, 1.5]])
    >>> fit = fit_homography_xue2018(xy, apply_homography(G, xy))
    >>> bool(fit), bool(np.allclose(fit.G, G, atol=1e-6)), fit.rms_px < 1e-6
    (True, True, True)
    """
    method = "xue2018"
    p, q = _pairs(xy, uv)
    n = p.shape[0]
    if n < 5:
        return HomographyFit.failed(f"need at least 5 correspondences (eq. 9), got {n}", method, n)
    if _degenerate(p):
        return HomographyFit.failed("laser points are collinear", method, n)
    x, y = p[:, 0], p[:, 1]
    u, v = q[:, 0], q[:, 1]
    z, o = np.zeros(n), np.ones(n)
    A = np.empty((2 * n, 8))
    A[0::2] = np.column_stack((y, o, z, z, z, -u * x, -u * y, -u))
    A[1::2] = np.column_stack((z, z, x, y, o, -v * x, -v * y, -v))
    b = np.empty(2 * n)
    b[0::2] = -x
    b[1::2] = 0.0
    sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 8:
        return HomographyFit.failed(f"eq. 11 is rank-deficient (rank {rank} < 8)", method, n)
    g12, g13, g21, g22, g23, g31, g32, g33 = sol
    G = np.array([[1.0, g12, g13], [g21, g22, g23], [g31, g32, g33]])
    return _finish(G, p, q, method)


def _similarity(pts: FloatArray) -> FloatArray:
    """Hartley normalisation: centroid to 0, mean distance sqrt(2)."""
    c = pts.mean(axis=0)
    d = float(np.mean(np.hypot(*(pts - c).T)))
    s = math.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])


def _dlt(p: FloatArray, q: FloatArray) -> FloatArray:
    Tp, Tq = _similarity(p), _similarity(q)
    pn = p @ Tp[:2, :2].T + Tp[:2, 2]
    qn = q @ Tq[:2, :2].T + Tq[:2, 2]
    n = p.shape[0]
    x, y, u, v = pn[:, 0], pn[:, 1], qn[:, 0], qn[:, 1]
    z, o = np.zeros(n), np.ones(n)
    A = np.empty((2 * n, 9))
    A[0::2] = np.column_stack((x, y, o, z, z, z, -u * x, -u * y, -u))
    A[1::2] = np.column_stack((z, z, z, x, y, o, -v * x, -v * y, -v))
    _, _, vt = np.linalg.svd(A)
    Hn = vt[-1].reshape(3, 3)
    return np.linalg.inv(Tq) @ Hn @ Tp


def fit_homography_dlt(xy: ArrayLike, uv: ArrayLike, *, refine: bool = False) -> HomographyFit:
    """Hartley-normalised direct linear transform (SVD), optionally refined by LM.

    Both point sets are translated to their centroid and scaled to mean distance sqrt(2) before
    the 2N x 9 system is solved by SVD (no entry fixed, so no g11 = 0 singularity).

    Parameters
    ----------
    xy : (N, 2) metres; uv : (N, 2) pixels; N >= 4
    refine : bool
        Follow with :func:`refine_homography` (minimises the pixel error, not the algebraic one).

    Returns
    -------
    HomographyFit (falsy for N < 4 or collinear laser points)

    References
    ----------
    Hartley R., Zisserman A. (2004). Multiple View Geometry, 2nd ed., Alg. 4.2.
    """
    method = "dlt_refined" if refine else "dlt"
    p, q = _pairs(xy, uv)
    n = p.shape[0]
    if n < 4:
        return HomographyFit.failed(f"need at least 4 correspondences, got {n}", method, n)
    if _degenerate(p):
        return HomographyFit.failed("laser points are collinear", method, n)
    G = _dlt(p, q)
    fit = _finish(G, p, q, method)
    if refine and fit:
        return refine_homography(fit.G, p, q, method=method)
    return fit


def refine_homography(
    G0: ArrayLike,
    xy: ArrayLike,
    uv: ArrayLike,
    *,
    inliers: NDArray[np.bool_] | None = None,
    method: str = "refined",
) -> HomographyFit:
    """Levenberg-Marquardt refinement of G on the pixel reprojection error (gold standard).

    Minimises sum_i |pi(G (x_i, y_i, 1)) - (u_i, v_i)|^2 over the 8 free entries of G (scale fixed
    by keeping the largest-magnitude entry of G0 constant).
    """
    p, q = _pairs(xy, uv)
    G0a = _normalise_g(np.asarray(G0, dtype=np.float64))
    inl = np.ones(p.shape[0], bool) if inliers is None else np.asarray(inliers, bool)
    pi, qi = p[inl], q[inl]
    if pi.shape[0] < 4:
        return HomographyFit.failed("fewer than 4 inliers to refine on", method, p.shape[0])
    fixed = int(np.argmax(np.abs(G0a.reshape(-1))))
    free = np.array([k for k in range(9) if k != fixed])
    g = G0a.reshape(-1).copy()

    def resid(theta: FloatArray) -> FloatArray:
        gg = g.copy()
        gg[free] = theta
        H = gg.reshape(3, 3)
        w = pi @ H[2, :2] + H[2, 2]
        w = np.where(np.abs(w) < 1e-12, 1e-12, w)
        u = (pi @ H[0, :2] + H[0, 2]) / w
        v = (pi @ H[1, :2] + H[1, 2]) / w
        return np.concatenate((u - qi[:, 0], v - qi[:, 1]))

    sol = least_squares(resid, g[free], method="lm" if pi.shape[0] >= 5 else "trf")
    g[free] = sol.x
    return _finish(g.reshape(3, 3), p, q, method, inl)


def fit_homography_ransac(
    xy: ArrayLike,
    uv: ArrayLike,
    *,
    threshold_px: float = 3.0,
    max_trials: int = 500,
    confidence: float = 0.999,
    refine: bool = True,
    rng: np.random.Generator | int | None = None,
) -> HomographyFit:
    """Robust G: RANSAC over minimal 4-point normalised-DLT fits, refit on the inliers.

    Parameters
    ----------
    threshold_px : float
        Inlier threshold on the reprojection error, pixels.
    max_trials : int
        Upper bound on samples; stops early once ``confidence`` is reached.
    refine : bool
        LM-refine the final inlier fit (:func:`refine_homography`).
    rng : Generator or seed
    """
    method = "ransac"
    p, q = _pairs(xy, uv)
    n = p.shape[0]
    if threshold_px <= 0 or max_trials < 1 or not 0 < confidence < 1:
        raise ConfigError(
            f"RANSAC needs threshold_px > 0, max_trials >= 1, confidence in (0, 1); got "
            f"{threshold_px}, {max_trials}, {confidence}."
        )
    if n < 4:
        return HomographyFit.failed(f"need at least 4 correspondences, got {n}", method, n)
    if _degenerate(p):
        return HomographyFit.failed("laser points are collinear", method, n)
    gen = np.random.default_rng(rng)
    best_inl = np.zeros(n, bool)
    best_count = 0
    trials_needed = max_trials
    trial = 0
    while trial < min(max_trials, trials_needed):
        trial += 1
        idx = gen.choice(n, 4, replace=False)
        if _degenerate(p[idx]):
            continue
        G = _dlt(p[idx], q[idx])
        if not np.all(np.isfinite(G)):
            continue
        inl = reprojection_errors(G, p, q) < threshold_px
        cnt = int(inl.sum())
        if cnt > best_count:
            best_count, best_inl = cnt, inl
            w = cnt / n
            denom = math.log(max(1e-12, 1 - w**4))
            trials_needed = math.ceil(math.log(1 - confidence) / denom) if denom < 0 else max_trials
    if best_count < 4:
        return HomographyFit.failed("no 4-point sample found a consensus set", method, n)
    G = _dlt(p[best_inl], q[best_inl])
    # Re-estimate the consensus once with the refit (standard RANSAC polish).
    inl = reprojection_errors(G, p, q) < threshold_px
    if inl.sum() >= 4:
        best_inl = inl
        G = _dlt(p[best_inl], q[best_inl])
    if refine:
        fit = refine_homography(G, p, q, inliers=best_inl, method=method)
    else:
        fit = _finish(G, p, q, method, best_inl)
    log.debug("RANSAC: %d trials, %d/%d inliers", trial, int(best_inl.sum()), n)
    return fit


HOMOGRAPHY_METHODS = ("xue2018", "dlt", "dlt_refined", "ransac")


def fit_homography(
    xy: ArrayLike, uv: ArrayLike, method: str = "dlt_refined", **options: object
) -> HomographyFit:
    """Fit G with the named method: one of :data:`HOMOGRAPHY_METHODS`."""
    if method == "xue2018":
        return fit_homography_xue2018(xy, uv)
    if method == "dlt":
        return fit_homography_dlt(xy, uv)
    if method == "dlt_refined":
        return fit_homography_dlt(xy, uv, refine=True)
    if method == "ransac":
        return fit_homography_ransac(xy, uv, **options)  # type: ignore[arg-type]
    raise ConfigError(f"unknown homography method {method!r}; choose one of {HOMOGRAPHY_METHODS}.")


# ---------------------------------------------------------------------------------------------
# The notched calibration plate (Xue 2018 §2.3.4)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlateModel:
    """Geometry of Xue's plate in plate units (x right, y up on the plate face).

    The isosceles-trapezoid notch has waists y = slope x and y = -slope x + intercept; the
    rectangle notch's left edge is x = rect_x. Paper values (Fig. 5): slope 4, intercept 4,
    rect_x 1.4. ``unit`` converts plate units to metres (not printed in the paper; we take
    0.2 m so the trapezoid base is 0.2 m wide, a size a 0.5 deg scanner resolves at ~2 m).
    ``depth`` is the notch depth, metres.
    """

    slope: float = 4.0
    intercept: float = 4.0
    rect_x: float = 1.4
    rect_width: float = 0.4
    unit: float = 0.2
    depth: float = 0.05

    def waist_a(self, x: ArrayLike) -> FloatArray:
        return self.slope * np.asarray(x, dtype=np.float64)

    def waist_b(self, x: ArrayLike) -> FloatArray:
        return -self.slope * np.asarray(x, dtype=np.float64) + self.intercept


XUE2018_PLATE = PlateModel()


@dataclass(frozen=True, eq=False)
class PlatePoints:
    """Solution of eqs. 4-6: A, B, C in plate units (x, y), and metres on the plate face."""

    A: FloatArray
    B: FloatArray
    C: FloatArray
    residual: float
    ok: bool = True
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok

    def as_array(self) -> FloatArray:
        """(3, 2) rows A, B, C in plate units."""
        return np.vstack((self.A, self.B, self.C))


def solve_plate_points(
    l_ab: float, l_bc: float, plate: PlateModel = XUE2018_PLATE, *, tol: float = 0.01
) -> PlatePoints:
    """Plate coordinates of the special points A, B, C from laser segment lengths
    (Xue et al. 2018, eqs. 4-6).

    With A = (x_A, s x_A), B = (x_B, -s x_B + c), C = (rect_x, y_C) (s = slope, c = intercept):

        (x_A - x_B)^2 + (s x_A + s x_B - c)^2 = l_AB^2                          (4)
        (rect_x - x_B)^2 + (y_C + s x_B - c)^2 = l_BC^2                         (5)
        (s x_A + s x_B - c) / (x_A - x_B) = (y_C + s x_B - c) / (rect_x - x_B)  (6)

    Eq. 6 is used in its cross-multiplied form (no division by x_A - x_B). The system is solved
    by Levenberg-Marquardt from three horizontal-scan-line guesses; of the solutions the one
    inside the trapezoid (0 <= y_A, y_B <= apex) with the smallest residual is kept. Noisy
    lengths can have no exact solution (l_BC below its minimum for the given l_AB): the
    least-squares point is accepted when its length residuals are below ``tol`` metres.

    The problem is ill-conditioned in the scan line's slope: y_C moves ~10 plate units per
    plate unit of length error (measured in tests/vision/test_calibrate.py); see the docs.

    Parameters
    ----------
    l_ab, l_bc : float, metres
        Lengths of AB and BC measured by the laser.
    plate : PlateModel
    tol : float, metres
        Largest accepted length residual of eqs. 4-5.

    Returns
    -------
    PlatePoints (falsy when no consistent solution exists, e.g. l_AB longer than the notch)

    Examples
    --------
    A horizontal scan line at plate height 1 crosses the waists at x = 0.25 and 0.75:

    >>> pp = solve_plate_points(0.5 * 0.2, 0.65 * 0.2)
    >>> np.round(pp.as_array(), 4).tolist()
    [[0.25, 1.0], [0.75, 1.0], [1.4, 1.0]]
    """
    if not (l_ab > 0 and l_bc > 0 and math.isfinite(l_ab) and math.isfinite(l_bc)):
        raise InputError(f"segment lengths must be positive and finite, got {l_ab}, {l_bc} m.")
    s, c, rx = plate.slope, plate.intercept, plate.rect_x
    lab, lbc = l_ab / plate.unit, l_bc / plate.unit
    apex_y = c / 2.0

    def f(z: FloatArray) -> FloatArray:
        xa, xb, yc = z
        dyab = s * xa + s * xb - c
        dycb = yc + s * xb - c
        return np.array(
            [
                math.hypot(xa - xb, dyab) - lab,
                math.hypot(rx - xb, dycb) - lbc,
                dyab * (rx - xb) - dycb * (xa - xb),
            ]
        )

    # Horizontal guess: AB width at height h is (c - 2h)/s  ->  h = (c - s lab) / 2.
    h0 = float(np.clip((c - s * lab) / 2.0, 0.0, apex_y * 0.999))
    best: PlatePoints | None = None
    for dh in (0.0, 0.3, -0.3):
        h = float(np.clip(h0 + dh, 0.0, apex_y * 0.999))
        z0 = np.array([h / s, (c - h) / s, h])
        sol = least_squares(f, z0, method="lm", xtol=1e-14, ftol=1e-14)
        xa, xb, yc = sol.x
        ya, yb = s * xa, -s * xb + c
        res = float(np.max(np.abs(sol.fun[:2]))) * plate.unit
        inside = -1e-6 <= ya <= apex_y + 1e-6 and -1e-6 <= yb <= apex_y + 1e-6 and xa < xb
        cand = PlatePoints(np.array([xa, ya]), np.array([xb, yb]), np.array([rx, yc]), res)
        if inside and res <= tol and (best is None or res < best.residual):
            best = cand
    if best is None:
        return PlatePoints(
            np.full(2, np.nan),
            np.full(2, np.nan),
            np.full(2, np.nan),
            math.nan,
            False,
            f"no solution of eqs. 4-6 inside the trapezoid for l_AB={l_ab} m, l_BC={l_bc} m",
        )
    return best


def plate_edges_from_scan(
    points: ArrayLike, *, min_depth: float = 0.02
) -> tuple[FloatArray, bool, str]:
    """Find the laser points A, B, C on a scan of the notched plate (Xue 2018 §2.3.4, Fig. 5).

    The scan of the plate lies on the front face except inside the two notches, where it is
    recessed by the notch depth. A line fitted robustly to the face gives each point's depth
    behind it; the recessed runs are the notches. The plate faces the sensor with its x axis to
    the sensor's right, so in order of increasing beam angle (counter-clockwise) the rectangle
    notch comes first, then the trapezoid: C is the rectangle's left edge, B and A the
    trapezoid's right and left edges. Each edge is placed at the midpoint of the two
    straddling beams, moved along the beam onto the face line.

    Parameters
    ----------
    points : (N, 2) metres, the plate's returns only (any order)
    min_depth : float, metres -- smallest recess that counts as a notch

    Returns
    -------
    abc : (3, 2) metres, rows A, B, C (NaN if not found); ok : bool; reason : str
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 6:
        raise InputError(f"plate scan points must have shape (N >= 6, 2), got {p.shape}.")
    p = p[np.argsort(np.arctan2(p[:, 1], p[:, 0]))]
    keep = np.ones(p.shape[0], bool)
    n_vec = np.zeros(2)
    c = p.mean(axis=0)
    depth = np.zeros(p.shape[0])
    for _ in range(5):
        c = p[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(p[keep] - c)
        n_vec = vt[-1]
        if float(n_vec @ c) < 0:  # orient the normal away from the sensor
            n_vec = -n_vec
        depth = (p - c) @ n_vec
        keep = depth < np.median(depth) + min_depth / 2.0
    face = depth - np.median(depth[keep])
    recessed = face > min_depth / 2.0
    change = np.flatnonzero(recessed[1:] != recessed[:-1])
    if change.size != 4 or recessed[0]:
        return (
            np.full((3, 2), np.nan),
            False,
            f"found {change.size} notch edges, need exactly 4 (two notches inside the face)",
        )
    k = change[[3, 2, 1]]  # A, B, C
    mid = 0.5 * (p[k] + p[k + 1])
    face_off = float(c @ n_vec + np.median(depth[keep]))
    scale = face_off / (mid @ n_vec)
    return mid * scale[:, None], True, ""


# ---------------------------------------------------------------------------------------------
# PnP (visual-lidar paper §2.1)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PoseFit:
    """Sensor-to-camera extrinsics from PnP; falsy with ``reason`` on failure."""

    transform: RigidTransform | None
    rms_px: float
    residuals_px: FloatArray = field(default_factory=lambda: np.zeros(0))
    inliers: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    ok: bool = True
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok


def solve_pnp(
    points3d: ArrayLike,
    uv: ArrayLike,
    camera: CameraModel,
    *,
    ransac: bool = False,
    threshold_px: float = 3.0,
    refine: bool = True,
) -> PoseFit:
    """Sensor (LiDAR) to camera pose from 3D-2D pairs with known intrinsics (eq. 1 of the
    visual-lidar tree-trunk odometry paper, §2.1): s (u, v, 1)^T = K [R | t] (X, Y, Z, 1)^T.

    Uses OpenCV ``solvePnP`` (iterative LM from an EPnP/IPPE start; coplanar laser points are
    fine), or ``solvePnPRansac`` when ``ransac``; then ``solvePnPRefineLM`` on the inliers.

    Parameters
    ----------
    points3d : (N, 3) metres in the sensor frame (2D laser points: z = 0); N >= 4
    uv : (N, 2) pixels
    camera : CameraModel (its distortion is used)

    Returns
    -------
    PoseFit with ``transform`` mapping sensor to camera frame.
    """
    P = np.asarray(points3d, dtype=np.float64)
    q = np.asarray(uv, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or q.shape != (P.shape[0], 2):
        raise InputError(f"PnP needs points3d (N, 3) and uv (N, 2); got {P.shape} and {q.shape}.")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(q))):
        raise InputError("PnP correspondences contain NaN or inf values.")
    n = P.shape[0]
    if n < 4:
        return PoseFit(None, math.nan, ok=False, reason=f"PnP needs at least 4 points, got {n}")
    K, dist = camera.K.copy(), camera.dist.copy()
    inl = np.ones(n, bool)
    try:
        if ransac:
            ok, rvec, tvec, idx = cv2.solvePnPRansac(
                P,
                q,
                K,
                dist,
                reprojectionError=threshold_px,
                iterationsCount=500,
                confidence=0.999,
                flags=cv2.SOLVEPNP_EPNP if n >= 6 else cv2.SOLVEPNP_ITERATIVE,
            )
            if ok and idx is not None:
                inl = np.zeros(n, bool)
                inl[idx.reshape(-1)] = True
        else:
            ok, rvec, tvec = cv2.solvePnP(P, q, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if ok and refine and inl.sum() >= 4:
            rvec, tvec = cv2.solvePnPRefineLM(P[inl], q[inl], K, dist, rvec, tvec)
    except cv2.error as exc:
        return PoseFit(None, math.nan, ok=False, reason=f"OpenCV solvePnP failed: {exc}")
    if not ok:
        return PoseFit(None, math.nan, ok=False, reason="OpenCV solvePnP found no pose")
    R, _ = cv2.Rodrigues(rvec)
    T = RigidTransform(
        np.asarray(R, dtype=np.float64), np.asarray(tvec, dtype=np.float64).reshape(3)
    )
    proj, _ = cv2.projectPoints(P, rvec, tvec, K, dist)
    res = np.hypot(*(proj.reshape(-1, 2) - q).T)
    rms = float(np.sqrt(np.mean(res[inl] ** 2)))
    return PoseFit(T, rms, res, inl)
