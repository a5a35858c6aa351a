"""Circle fits for trunk cross-sections.

Every fit takes points of shape (N, 2) in metres and returns a :class:`CircleFit`, which is falsy
(and carries ``reason``) when the fit failed -- never silent zeros.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = [
    "FIT_METHODS",
    "CircleFit",
    "fit_circle",
    "fit_circle_kasa",
]


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


def fit_circle_kasa(
    points: ArrayLike, *, origin: ArrayLike | None = None, sigma: float | None = None
) -> CircleFit:
    """Kasa algebraic least-squares circle fit.

    Minimises sum (x^2 + y^2 + D x + E y + F)^2 over (D, E, F), a linear problem. The points are
    centred and scaled first so the normal equations stay well conditioned at large offsets.

    Parameters
    ----------
    points : array_like of shape (N, 2), metres
    origin, sigma : ignored (accepted for a uniform fit signature)

    Returns
    -------
    CircleFit
        Falsy with a reason for fewer than 3 points or (near-)collinear points.

    Notes
    -----
    Kasa (1976), as used by the visual-lidar tree-trunk odometry paper (2023, §2.3). Known to
    under-estimate the radius on short arcs; see docs/algorithms.md.

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
    sol, _, rank, sv = np.linalg.lstsq(A, b, rcond=None)
    if rank < 3 or sv[-1] < 1e-9 * sv[0]:
        return CircleFit.failed("points are collinear", "kasa", n)
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


#: Registry of fit methods by name; ``fit_circle`` dispatches on it. Every registered function
#: takes ``points`` (N, 2) and must accept (and may ignore) the keywords ``origin`` (sensor
#: position in the points' frame, (2,)) and ``sigma`` (range noise, metres).
FIT_METHODS: dict[str, Callable[..., CircleFit]] = {"kasa": fit_circle_kasa}


def fit_circle(points: ArrayLike, method: str = "kasa", **options: Any) -> CircleFit:
    """Fit a circle with the named method (see ``FIT_METHODS``)."""
    try:
        fn = FIT_METHODS[method]
    except KeyError:
        raise ConfigError(
            f"unknown circle fit method {method!r}; choose one of {sorted(FIT_METHODS)}."
        ) from None
    return fn(points, **options)
