"""State algebra shared by the full and the compressed EKF-SLAM (:mod:`stemmap.slam.ekf`,
:mod:`stemmap.slam._ekf_compressed`): buffer growth, landmark augmentation (Dissanayake et al.
2001), stacked range-bearing Jacobians, block-diagonal noise and 2x2 covariance blocks."""

from __future__ import annotations

import math

import numpy as np

from stemmap.slam.base import IntArray
from stemmap.types import FloatArray

__all__ = ["augment_landmark_covariance", "block_diag_noise", "grow_buffers"]


def grow_buffers(n: int, need: int, P: FloatArray, *rows: FloatArray) -> list[FloatArray] | None:
    """Capacity growth of an EKF state buffer (amortised: x1.5 + 64).

    ``P`` is the (cap, cap) covariance and ``rows`` arrays whose first axis has ``cap``
    entries (the mean, the compressed filter's Phi). Returns ``None`` when ``need`` entries
    fit already, else new zeroed buffers ``[P, *rows]`` with the first ``n`` entries copied.
    """
    if need <= P.shape[0]:
        return None
    cap = max(need, int(P.shape[0] * 1.5) + 64)
    P2 = np.zeros((cap, cap))
    P2[:n, :n] = P[:n, :n]
    out = [P2]
    for r in rows:
        r2 = np.zeros((cap, *r.shape[1:]))
        r2[:n] = r[:n]
        out.append(r2)
    return out


def augment_landmark_covariance(
    P: FloatArray, n: int, theta: float, a: float, b: float, rng_: float, ang: float,
    R1: FloatArray,
) -> FloatArray:  # fmt: skip
    """Add the rows/columns ``n, n+1`` of a new landmark to the covariance ``P`` in place.

    The landmark is ``m = s(x) + r (cos(ang), sin(ang))`` with the sensor at ``(a, b)`` in the
    vehicle frame and ``ang = theta + bearing``: ``P_mx = G_x P_vx``, ``P_mm = G_x P_vv G_xᵀ +
    G_z R G_zᵀ`` (Dissanayake et al. 2001). Returns ``G_x`` (2, 3), the Jacobian w.r.t. the pose.
    Shared by the full and the compressed filter.
    """
    c, s = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(ang), math.sin(ang)
    Gx = np.array(
        [
            [1.0, 0.0, -a * s - b * c - rng_ * sa],
            [0.0, 1.0, a * c - b * s + rng_ * ca],
        ]
    )
    Gz = np.array([[ca, -rng_ * sa], [sa, rng_ * ca]])
    P[n : n + 2, :n] = Gx @ P[:3, :n]
    P[:n, n : n + 2] = P[n : n + 2, :n].T
    P[n : n + 2, n : n + 2] = Gx @ P[:3, :3] @ Gx.T + Gz @ R1 @ Gz.T
    return Gx


def _stack_jacobian(Jv: FloatArray, Jl: FloatArray) -> FloatArray:
    """``H`` (2c, 3 + 2c) over [vehicle, landmark 1..c] from per-landmark blocks
    ``Jv`` (c, 2, 3) and ``Jl`` (c, 2, 2) (block diagonal in the landmark columns)."""
    c = Jv.shape[0]
    H = np.zeros((c, 2, 3 + 2 * c))
    H[:, :, :3] = Jv
    t = np.arange(c)
    H[t, :, 3 + 2 * t] = Jl[:, :, 0]
    H[t, :, 4 + 2 * t] = Jl[:, :, 1]
    return H.reshape(2 * c, 3 + 2 * c)


def block_diag_noise(m: int, R1: FloatArray) -> FloatArray:
    """``kron(I_m, R1)``: the (2m, 2m) noise of m stacked 2-d measurements (same values)."""
    out = np.zeros((2 * m, 2 * m))
    i = 2 * np.arange(m)
    out[i, i], out[i, i + 1] = R1[0, 0], R1[0, 1]
    out[i + 1, i], out[i + 1, i + 1] = R1[1, 0], R1[1, 1]
    return out


def _blocks(P: FloatArray, ri: IntArray, rj: IntArray) -> FloatArray:
    """The 2x2 blocks ``P[ri:ri+2, rj:rj+2]`` for arrays of row starts (p, 2, 2)."""
    out = np.empty((ri.size, 2, 2))
    out[:, 0, 0], out[:, 0, 1] = P[ri, rj], P[ri, rj + 1]
    out[:, 1, 0], out[:, 1, 1] = P[ri + 1, rj], P[ri + 1, rj + 1]
    return out
