"""Particle-set arithmetic of the FastSLAM back-end (Montemerlo et al. 2002), vectorised.

Split out of :mod:`stemmap.slam.fastslam` (it had reached the ~800-line limit), unchanged: the
per-particle landmark EKF update and innovation covariances written element by element over
``(P, M)`` arrays (the numpy reference the compiled kernel
:mod:`stemmap.slam._fastslam_kernel` is tested against), the motion-noise sampling, systematic
resampling, and the particle set's pose and landmark covariances. Re-exported by
:mod:`stemmap.slam.fastslam`.
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.types import FloatArray, wrap_angle

__all__ = [
    "particle_landmark_covariance",
    "posterior_mean_path",
    "systematic_resample",
    "weighted_pose_covariance",
]


def particle_landmark_covariance(
    mu: FloatArray,
    sig: FloatArray,
    nlm: np.ndarray,
    weights: FloatArray,
    best: int,
    j: int,
    gate: float = 1.0,
) -> FloatArray:
    """Covariance of landmark slot ``j`` of particle ``best`` over the particle set.

    The map posterior of FastSLAM is a mixture over particles of per-landmark Gaussians
    (Montemerlo et al. 2002, eq. 3), so the landmark's covariance is the mixture covariance
    ``sum_p w_p (Sigma_p + (mu_p - mu_bar)(mu_p - mu_bar)^T)`` over the particles that hold
    the same landmark (slot ``j`` within ``gate`` metres of the best particle's estimate:
    slots are inherited through resampling). It adds the spread of the particles' trajectories
    to the best particle's own landmark EKF covariance.
    """
    have = np.flatnonzero(nlm > j)
    d = np.hypot(*(mu[have, j] - mu[best, j]).T)
    sel = have[d < gate]
    w = weights[sel] / max(float(weights[sel].sum()), 1e-300)
    m = w @ mu[sel, j]
    dev = mu[sel, j] - m
    cov = np.einsum("p,pij->ij", w, sig[sel, j]) + np.einsum("p,pi,pk->ik", w, dev, dev)
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def weighted_pose_covariance(X: FloatArray, w: FloatArray) -> FloatArray:
    """Weighted covariance (3, 3) of particle poses ``X`` (P, 3) with weights ``w`` (P,) summing
    to 1; the heading deviations are wrapped about the weighted circular mean."""
    th0 = math.atan2(float(w @ np.sin(X[:, 2])), float(w @ np.cos(X[:, 2])))
    dev = np.empty_like(X)
    dev[:, :2] = X[:, :2] - w @ X[:, :2]
    dev[:, 2] = wrap_angle(X[:, 2] - th0)
    dev[:, 2] -= w @ dev[:, 2]
    cov = (dev * w[:, None]).T @ dev
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def posterior_mean_path(
    pose_hist: FloatArray, parents: np.ndarray, log_weights: FloatArray
) -> FloatArray:
    """The particle set's posterior-mean path (F, 3): per frame, the mean of every final
    particle's ancestral pose, weighted by its final weight (headings by their circular mean).

    Each final particle carries a sample of the whole path (its lineage through the
    resamplings, Montemerlo et al. 2002, §3); the best particle's lineage is one sample, the
    weighted mean over all of them the minimum-mean-square-error estimate of the path. They
    differ where the weights stay flat (the detections hardly discriminate the particles):
    then the best particle is an arbitrary draw of the motion noise around the odometry.

    Parameters
    ----------
    pose_hist : (F, P, 3) -- the particles' poses at every frame (after that frame's
        resampling, as stored by the filter)
    parents : (F, P) int -- per frame, the particle each one was resampled from (identity
        where the frame did not resample)
    log_weights : (P,) -- final log weights (any offset)

    Examples
    --------
    Two particles, never resampled, equal weights: the mean of their paths.

    >>> ph = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.2, 0.1], [1.0, -0.2, -0.1]]])
    >>> posterior_mean_path(ph, np.array([[0, 1], [0, 1]]), np.zeros(2))[1].round(6).tolist()
    [1.0, 0.0, 0.0]
    """
    nf, n_p, _ = pose_hist.shape
    w = np.exp(log_weights - np.max(log_weights))
    w /= w.sum()
    out = np.empty((nf, 3))
    cur = np.arange(n_p)
    for f in range(nf - 1, -1, -1):
        x = pose_hist[f, cur]
        out[f, :2] = w @ x[:, :2]
        out[f, 2] = math.atan2(float(w @ np.sin(x[:, 2])), float(w @ np.cos(x[:, 2])))
        cur = parents[f, cur]
    return out


def systematic_resample(weights: FloatArray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling: indices (P,) drawn with one uniform offset.

    Parameters
    ----------
    weights : ndarray (P,), non-negative, summing to 1
    rng : numpy Generator

    Returns
    -------
    ndarray (P,) of int, non-decreasing
    """
    p = weights.shape[0]
    positions = (rng.random() + np.arange(p)) / p
    cdf = np.cumsum(weights)
    cdf[-1] = 1.0
    return np.searchsorted(cdf, positions, side="left").astype(np.int64)


def _psd_sqrt_stack(covs: FloatArray) -> FloatArray:
    """Eigen square roots (N, 3, 3) of a stack of possibly singular PSD covariances.

    ``rng.standard_normal((n, 3)) @ sq[i].T`` is then n samples of N(0, covs[i]).
    """
    c = np.nan_to_num(0.5 * (covs + np.swapaxes(covs, 1, 2)))
    w, v = np.linalg.eigh(c)
    out: FloatArray = v * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
    return out


def _sample_batch(covs: FloatArray, rng: np.random.Generator) -> FloatArray:
    """One sample (P, 3) of N(0, covs[p]) per particle (eigen square roots, PSD-safe)."""
    w, v = np.linalg.eigh(0.5 * (covs + np.swapaxes(covs, 1, 2)))
    sq = v * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
    out: FloatArray = np.einsum("pij,pj->pi", sq, rng.standard_normal((covs.shape[0], 3)))
    return out


def _inv2(S: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Inverse and determinant of a stack of 2x2 matrices (..., 2, 2)."""
    a, b, c, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 0], S[..., 1, 1]
    det = a * d - b * c
    inv = np.empty_like(S)
    inv[..., 0, 0] = d / det
    inv[..., 0, 1] = -b / det
    inv[..., 1, 0] = -c / det
    inv[..., 1, 1] = a / det
    return inv, det


def _wrap_inplace(a: FloatArray) -> None:
    """``a[:] = wrap_angle(a)`` without temporaries (same formula: pi - mod(pi - a, 2 pi))."""
    np.subtract(np.pi, a, out=a)
    np.mod(a, 2.0 * np.pi, out=a)
    np.subtract(np.pi, a, out=a)


def _observe(
    px: FloatArray, py: FloatArray, th: FloatArray, m: FloatArray, a: float, b: float
) -> tuple[FloatArray, ...]:
    """Predicted (range, bearing) and H_m elements: the arithmetic of range_bearing_jacobians."""
    c, s = np.cos(th), np.sin(th)
    dx = m[..., 0] - (px + a * c - b * s)
    dy = m[..., 1] - (py + a * s + b * c)
    q = np.maximum(dx * dx + dy * dy, 1e-12)
    zr = np.sqrt(q)
    zb = np.arctan2(dy, dx) - th
    _wrap_inplace(zb)
    return zr, zb, dx / zr, dy / zr, -dy / q, dx / q


def _predict_and_inv(
    X: FloatArray, m: FloatArray, m_S: FloatArray, off: tuple[float, float], r00: float, r11: float
) -> tuple[FloatArray, ...]:
    """Predicted (range, bearing) and inverse innovation covariance, element by element.

    Same arithmetic as :func:`~stemmap.slam.treedb.range_bearing_jacobians` (poses ``X`` (P, 3)
    against landmarks ``m`` (P, M, 2)) followed by ``S = H_m Sig H_m^T + R`` (R diagonal) and
    :func:`_inv2`, without the (P, M, 2, 2) temporaries. Returns ``zr, zb, i00, i01, i10, i11,
    det`` as (P, M) arrays.
    """
    zr, zb, h00, h01, h10, h11 = _observe(
        X[:, 0][:, None], X[:, 1][:, None], X[:, 2][:, None], m, float(off[0]), float(off[1])
    )
    s00, s01, s10, s11 = m_S[..., 0, 0], m_S[..., 0, 1], m_S[..., 1, 0], m_S[..., 1, 1]
    a00 = h00 * s00 + h01 * s10  # A = H_m Sig
    a01 = h00 * s01 + h01 * s11
    a10 = h10 * s00 + h11 * s10
    a11 = h10 * s01 + h11 * s11
    S00 = a00 * h00 + a01 * h01 + r00  # S = A H_m^T + R
    S01 = a00 * h10 + a01 * h11
    S10 = a10 * h00 + a11 * h01
    S11 = a10 * h10 + a11 * h11 + r11
    det = S00 * S11 - S01 * S10
    return zr, zb, S11 / det, -S01 / det, -S10 / det, S00 / det, det


def _ekf_update(
    mu: FloatArray,
    Sig: FloatArray,
    wp: np.ndarray,
    lm: np.ndarray,
    Xw: FloatArray,
    zw: FloatArray,
    off: tuple[float, float],
    r00: float,
    r11: float,
) -> None:
    """Landmark EKF update of ``mu[wp, lm]``, ``Sig[wp, lm]`` (unique pairs) in place.

    Element formulas of ``K = Sig H^T (H Sig H^T + R)^-1``, ``mu += K nu``,
    ``Sig = sym((I - K H) Sig)`` with the matrix products summed in the same order.
    """
    m = mu[wp, lm]
    Ss = Sig[wp, lm]
    zr, zb, h00, h01, h10, h11 = _observe(
        Xw[:, 0], Xw[:, 1], Xw[:, 2], m, float(off[0]), float(off[1])
    )
    n0 = zw[:, 0] - zr
    n1 = zw[:, 1] - zb
    _wrap_inplace(n1)
    s00, s01, s10, s11 = Ss[:, 0, 0], Ss[:, 0, 1], Ss[:, 1, 0], Ss[:, 1, 1]
    t00 = h00 * s00 + h01 * s10  # T = H Sig
    t01 = h00 * s01 + h01 * s11
    t10 = h10 * s00 + h11 * s10
    t11 = h10 * s01 + h11 * s11
    S00 = t00 * h00 + t01 * h01 + r00  # S = T H^T + R
    S01 = t00 * h10 + t01 * h11 + 0.0
    S10 = t10 * h00 + t11 * h01 + 0.0
    S11 = t10 * h10 + t11 * h11 + r11
    det = S00 * S11 - S01 * S10
    j00, j01, j10, j11 = S11 / det, -S01 / det, -S10 / det, S00 / det
    u00 = s00 * h00 + s01 * h01  # U = Sig H^T
    u01 = s00 * h10 + s01 * h11
    u10 = s10 * h00 + s11 * h01
    u11 = s10 * h10 + s11 * h11
    k00 = u00 * j00 + u01 * j10  # K = U S^-1
    k01 = u00 * j01 + u01 * j11
    k10 = u10 * j00 + u11 * j10
    k11 = u10 * j01 + u11 * j11
    out = np.empty_like(m)
    out[:, 0] = m[:, 0] + (k00 * n0 + k01 * n1)
    out[:, 1] = m[:, 1] + (k10 * n0 + k11 * n1)
    mu[wp, lm] = out
    w00 = 1.0 - (k00 * h00 + k01 * h10)  # W = I - K H
    w01 = 0.0 - (k00 * h01 + k01 * h11)
    w10 = 0.0 - (k10 * h00 + k11 * h10)
    w11 = 1.0 - (k10 * h01 + k11 * h11)
    newS = np.empty_like(Ss)
    v01 = w00 * s01 + w01 * s11  # W Sig, symmetrised
    v10 = w10 * s00 + w11 * s10
    newS[:, 0, 0] = 0.5 * ((w00 * s00 + w01 * s10) * 2.0)
    newS[:, 1, 1] = 0.5 * ((w10 * s01 + w11 * s11) * 2.0)
    newS[:, 0, 1] = 0.5 * (v01 + v10)
    newS[:, 1, 0] = 0.5 * (v10 + v01)
    Sig[wp, lm] = newS
