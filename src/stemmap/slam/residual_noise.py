"""Detection noise measured from a SLAM run's own residuals (ours; docs/algorithms/slam.md,
"The EKF's detection noise measured from its residuals").

A range-bearing detection of a tree is modelled as ``z = h(pose, tree) + e`` with ``e`` the
detection error. The filters assume ``e`` white with a constant covariance ``R``. On real data
it is not white: the centre a detector fits to a trunk depends on the viewpoint, which changes
slowly, so the errors of one tree's consecutive detections are correlated (Victoria Park: lag-1
correlation ~0.8, gone after ~5 s). For the *information* a tree's detections carry, what counts
is then not the error variance ``s²`` but its long-run variance (the spectral density at zero
frequency, the variance of a mean of ``n`` detections times ``n``)::

    s²_lr = s² (1 + 2 sum_k w_k rho_k)

with ``rho_k`` the correlation of the errors of one tree's detections ``k`` frames apart and
``w_k = 1 - k / (K + 1)`` the Bartlett weights (Newey & West, Econometrica 55(3), 1987) up to
the lag ``K``. Used as the filter's white ``R``, it gives a run of correlated detections the
weight of the independent detections it is worth.

:func:`residual_noise` estimates ``s`` and ``s_lr`` per component (range, bearing) from the
residuals of the detections a run associated, against its final map at its (smoothed) path:
robust scale (MAD) for ``s``, correlations from the pairs of detections of the same tree ``k``
frames apart, both after removing gross outliers (beyond ``clip`` robust sigmas: wrong
associations are not noise). Residuals against a fitted map and path are slightly smaller than
the errors (each tree's mean is fitted); with tens to hundreds of detections per tree that bias
is small, and the test against a simulation with known noise bounds it
(``tests/slam/test_residual_noise.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stemmap.slam.treedb import range_bearing_jacobians
from stemmap.types import FloatArray, wrap_angle

__all__ = ["ResidualNoise", "detection_residuals", "residual_noise", "residual_noise_stats"]


@dataclass(frozen=True)
class ResidualNoise:
    """Per component (range m, bearing rad): robust error std, correlations by frame lag
    (``rho[k - 1]`` at lag ``k``), long-run std; residuals used / removed as gross."""

    sigma: tuple[float, float]
    rho: tuple[tuple[float, ...], tuple[float, ...]]
    sigma_long_run: tuple[float, float]
    used: int
    removed: int

    @property
    def long_run_factor(self) -> tuple[float, float]:
        """``s²_lr / s²`` per component (1 for white errors)."""
        return (
            (self.sigma_long_run[0] / self.sigma[0]) ** 2,
            (self.sigma_long_run[1] / self.sigma[1]) ** 2,
        )


def detection_residuals(
    poses: FloatArray,
    frame: np.ndarray,
    landmark: np.ndarray,
    rng: FloatArray,
    brg: FloatArray,
    lm_xy: FloatArray,
    sensor_offset: tuple[float, float],
) -> FloatArray:
    """(m, 2) range / bearing residuals of detections (``frame``, ``landmark``, ``rng``,
    ``brg``) against landmarks ``lm_xy`` seen from vehicle ``poses`` (N, 3)."""
    z, _, _ = range_bearing_jacobians(poses[frame], lm_xy[landmark], sensor_offset)
    return np.column_stack((rng - z[:, 0], wrap_angle(brg - z[:, 1])))


def _mad(v: FloatArray) -> float:
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def residual_noise(
    frame: np.ndarray,
    landmark: np.ndarray,
    resid: FloatArray,
    *,
    max_lag: int = 50,
    clip: float = 5.0,
) -> ResidualNoise:
    """The detection noise of residuals ``resid`` (m, 2: range, bearing) of detections of
    ``landmark`` in ``frame`` (module docstring); ``max_lag`` frames is the Bartlett window
    ``K`` (Victoria Park: 50 frames = 10.7 s, twice the lag where the correlation is gone)."""
    frame = np.asarray(frame, dtype=np.int64)
    landmark = np.asarray(landmark, dtype=np.int64)
    e = np.asarray(resid, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 2 or e.shape[0] != frame.size != landmark.size:
        raise ValueError("resid must be (m, 2) with one frame and landmark per row.")
    scale0 = np.array([_mad(e[:, 0]), _mad(e[:, 1])])
    good = np.all(np.abs(e - np.median(e, axis=0)) <= clip * scale0, axis=1)
    f, j, e = frame[good], landmark[good], e[good]
    if f.size < 10:
        raise ValueError(f"too few residuals ({f.size}) to measure the noise.")
    sigma = np.array([_mad(e[:, 0]), _mad(e[:, 1])])
    var = np.mean(e * e, axis=0)
    if not np.all(var > 0):  # exact detections (a noise-free simulation): nothing to measure
        raise ValueError("the residuals have no scatter to measure.")
    key = j * (int(f.max()) + max_lag + 2) + f
    order = np.argsort(key)
    ks = key[order]
    rho = np.zeros((2, max_lag))
    for k in range(1, max_lag + 1):
        at = np.searchsorted(ks, ks + k)
        at_c = np.minimum(at, ks.size - 1)
        hit = (at < ks.size) & (ks[at_c] == ks + k)
        if hit.sum() < 10:
            break
        a, b = e[order][hit], e[order][at_c[hit]]
        rho[:, k - 1] = np.mean(a * b, axis=0) / var
    w = 1.0 - np.arange(1, max_lag + 1) / (max_lag + 1.0)
    factor = np.maximum(1.0 + 2.0 * (rho * w).sum(axis=1), 1.0)
    lr = sigma * np.sqrt(factor)
    return ResidualNoise(
        sigma=(float(sigma[0]), float(sigma[1])),
        rho=(tuple(float(v) for v in rho[0]), tuple(float(v) for v in rho[1])),
        sigma_long_run=(float(lr[0]), float(lr[1])),
        used=int(f.size),
        removed=int((~good).sum()),
    )


def residual_noise_stats(
    poses: FloatArray,
    obs: tuple[np.ndarray, np.ndarray, FloatArray, FloatArray],
    lm_xy: FloatArray,
    sensor_offset: tuple[float, float],
) -> dict[str, float]:
    """A run's ``SlamResult.stats`` entries of :func:`residual_noise` for its associated
    detections ``obs`` (frame, landmark, range, bearing) on ``lm_xy`` from ``poses``: std and
    long-run std of range (m) and bearing (rad), empty when too few detections."""
    fr, lj, rz, bz = obs
    if fr.size < 10:
        return {}
    e = detection_residuals(poses, fr, lj, rz, bz, lm_xy, sensor_offset)
    try:
        r = residual_noise(fr, lj, e)
    except ValueError:
        return {}
    return {
        "residual_sigma_range": r.sigma[0],
        "residual_sigma_bearing": r.sigma[1],
        "residual_sigma_range_long_run": r.sigma_long_run[0],
        "residual_sigma_bearing_long_run": r.sigma_long_run[1],
    }
