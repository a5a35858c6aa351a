"""The result type and input checks shared by the circle fits of :mod:`stemmap.scan.circle`
(single and batched): :class:`CircleFit`, point and option validation, bearing order, the
collinearity test and the single-segment route through the vectorised fits."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError, InputError
from stemmap.scan import _fit_batch as _fb
from stemmap.types import FloatArray


@dataclass(frozen=True, eq=False)
class CircleFit:
    """Result of a circle fit.

    Attributes
    ----------
    center : ndarray of shape (2,), metres
    radius : float, metres
    cov : ndarray of shape (3, 3)
        Covariance over (cx, cy, r); NaN-filled when the method does not estimate it.
    rms : float, metres
        Root-mean-square orthogonal distance of the points to the circle.
    n_points : int
    method : str
    ok : bool
    reason : str
        Why the fit failed (empty when ``ok``).
    """

    center: FloatArray
    radius: float
    cov: FloatArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    rms: float = math.nan
    n_points: int = 0
    method: str = ""
    ok: bool = True
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius

    @classmethod
    def failed(cls, reason: str, method: str, n_points: int = 0) -> CircleFit:
        return cls(
            center=np.full(2, np.nan),
            radius=math.nan,
            n_points=n_points,
            method=method,
            ok=False,
            reason=reason,
        )

    def residuals(self, points: ArrayLike) -> FloatArray:
        """Signed orthogonal distances of ``points`` (N, 2) to the circle (outside positive)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return np.hypot(p[:, 0] - self.center[0], p[:, 1] - self.center[1]) - self.radius


def as_points(points: ArrayLike, name: str = "points") -> FloatArray:
    """Validate and promote to a float64 (N, 2) array; raise InputError otherwise."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise InputError(f"{name} must have shape (N, 2), got {p.shape}.")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{name} contains NaN or inf values.")
    return p


def _origin(origin: ArrayLike | None) -> FloatArray:
    if origin is None:
        return np.zeros(2)
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (2,) or not np.all(np.isfinite(o)):
        raise InputError(f"origin must be a finite (x, y) pair in metres, got {o!r}.")
    return o


def _check_sigma(sigma: float | None) -> float:
    """``sigma`` as a float, 0.0 meaning "unknown"; raise InputError if negative or not finite."""
    if sigma is None:
        return 0.0
    s = float(sigma)
    if not (math.isfinite(s) and s >= 0.0):
        raise InputError(f"sigma (range noise std, metres) must be finite and >= 0, got {sigma!r}.")
    return s


def _check_increment(angle_increment: float | None) -> float:
    """``angle_increment`` as a positive float, 0.0 meaning "estimate from the bearings"."""
    if angle_increment is None:
        return 0.0
    a = abs(float(angle_increment))
    if not (math.isfinite(a) and a > 0.0):
        raise InputError(
            f"angle_increment (radians between beams) must be finite and non-zero, "
            f"got {angle_increment!r}."
        )
    return a


def _check_divergence(beam_divergence: float | None) -> float:
    """``beam_divergence`` (full footprint width, radians) as a float >= 0 (0 = thin beam)."""
    if beam_divergence is None:
        return 0.0
    b = float(beam_divergence)
    if not (math.isfinite(b) and 0.0 <= b < 0.5):
        raise InputError(
            f"beam_divergence (full angular width of the beam footprint, radians) must be finite, "
            f">= 0 and < 0.5 rad, got {beam_divergence!r}."
        )
    return b


_RESIDUALS = ("range", "orthogonal")


def _check_residuals(residuals: str) -> bool:
    """True for range residuals; raise ConfigError for an unknown name."""
    if residuals not in _RESIDUALS:
        raise ConfigError(f"residuals must be one of {_RESIDUALS}, got {residuals!r}.")
    return residuals == "range"


def _check_silhouette(silhouette: ArrayLike | None, k: int) -> FloatArray:
    """Per-segment silhouette priors as a (k, 4) array (lo offset, lo std, hi offset, hi std) in
    beam spacings; NaN = default. Accepts (2, 2) (shared) or (k, 2, 2)."""
    if silhouette is None:
        return np.full((k, 4), np.nan)
    a = np.asarray(silhouette, dtype=np.float64)
    if a.shape == (2, 2):
        a = np.broadcast_to(a, (k, 2, 2))
    if a.shape != (k, 2, 2):
        raise InputError(
            f"silhouette must have shape (2, 2) or ({k}, 2, 2): per side (first, last) the "
            f"(offset, std) of the tangent beyond the edge return, in beam spacings; got "
            f"{a.shape}."
        )
    flat = a.reshape(k, 4)
    off, std = flat[:, [0, 2]], flat[:, [1, 3]]
    if np.any(np.isinf(flat)) or np.any(std <= 0) or np.any(off < -1e3):
        raise InputError(
            "silhouette offsets must be finite (NaN = default) and stds finite and > 0 "
            "(beam spacings)."
        )
    return np.ascontiguousarray(flat)


def _by_bearing(p: FloatArray, o: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Points sorted by bearing from ``o`` (bearings relative to their mean direction, so an
    arc straddling +-pi sorts correctly). Returns sorted points, bearings and ranges."""
    q = p - o
    rho = np.hypot(q[:, 0], q[:, 1])
    safe = np.where(rho > 0, rho, 1.0)
    mean_dir = math.atan2(float(np.sum(q[:, 1] / safe)), float(np.sum(q[:, 0] / safe)))
    c, s = math.cos(mean_dir), math.sin(mean_dir)
    th = np.arctan2(-s * q[:, 0] + c * q[:, 1], c * q[:, 0] + s * q[:, 1])
    # bearings quantised to 1e-12 rad so that round-off cannot reorder returns that share a
    # bearing; ties broken by range (nearest first)
    order = np.lexsort((rho, np.round(th * 1e12)))
    return p[order], th[order] + mean_dir, rho[order]


_COLLINEAR_EIG = 1e-14  # smallest / largest eigenvalue of A^T A (= singular value ratio 1e-7)


def _rank_deficient(M: FloatArray) -> bool:
    """Collinearity test on the 3x3 normal matrix A^T A of the centred, scaled points (the
    same test as the batch fits, so single and batch decide alike)."""
    return not float(_fb.eig_ratio_sym3(M[None])[0]) >= _COLLINEAR_EIG


def _single_from_batch(p: FloatArray, o: FloatArray, method: str) -> CircleFit:
    """One segment through the vectorised implementation (so single and batch agree exactly)."""
    n = p.shape[0]
    starts = np.zeros(1, dtype=np.int64)
    counts = np.array([n], dtype=np.int64)
    fn = _fb.three_point_batch if method == "three_point" else _fb.chord_width_batch
    centers, radii, why = fn(p, starts, counts, o[None, :])
    if not np.isfinite(radii[0]):
        return CircleFit.failed(str(why[0]), method, n)
    return _with_rms(p, centers[0].copy(), float(radii[0]), method)


def _with_rms(
    p: FloatArray, center: FloatArray, radius: float, method: str, cov: FloatArray | None = None
) -> CircleFit:
    rms = float(np.sqrt(np.mean((np.hypot(*(p - center).T) - radius) ** 2)))
    return CircleFit(
        center=center,
        radius=float(radius),
        cov=np.full((3, 3), np.nan) if cov is None else cov,
        rms=rms,
        n_points=p.shape[0],
        method=method,
    )


def _per_segment(value: ArrayLike | None, k: int, name: str, default: float) -> FloatArray:
    if value is None:
        return np.full(k, default)
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(k, float(v))
    if v.shape != (k,):
        raise InputError(
            f"{name} must be a scalar or have shape ({k},) (one per segment), got {v.shape}."
        )
    return v
