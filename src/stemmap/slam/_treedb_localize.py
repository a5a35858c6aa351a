"""Pose-only EKF localisation of the tree DB back-end against its promoted landmarks
(:class:`~stemmap.slam.treedb.TreeDbSlam` with ``localize=True``; ours, after the
visual-lidar paper's use of the tree DB's landmarks for localisation, §2.5)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.treedb import TreeDb

IntArray = NDArray[np.int64]
#: (K, H_x, H_m, matched detections, their landmarks) of one update; :func:`localize_pose`
Gain = tuple[FloatArray, FloatArray, FloatArray, IntArray, IntArray]


def compose_jacobian(pose: FloatArray, delta: FloatArray) -> FloatArray:
    """d (pose ⊕ delta) / d pose."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array(
        [
            [1.0, 0.0, -s * delta[0] - c * delta[1]],
            [0.0, 1.0, c * delta[0] - s * delta[1]],
            [0.0, 0.0, 1.0],
        ]
    )


def landmark_covariances(db: TreeDb, idx: IntArray) -> FloatArray:
    """The localisation's covariance of landmarks ``idx``: the scatter of their averaged
    detections over their count (a standard error of the mean, floored at 1 cm² / n)."""
    n = db.count[idx].astype(np.float64)
    cov: FloatArray = db.sq_dev[idx] / np.maximum(n - 1.0, 1.0)[:, None, None] / n[:, None, None]
    return cov + np.eye(2) * (1e-4 / n)[:, None, None]


def localize_pose(
    pose: FloatArray,
    P: FloatArray,
    ranges: FloatArray,
    bearings: FloatArray,
    lm_xy: FloatArray,
    lm_cov: FloatArray,
    R: FloatArray,
    offset: tuple[float, float],
    chi2_gate: float,
) -> tuple[FloatArray, FloatArray, IntArray, Gain | None]:
    """Pose-only EKF update from detections matched to fixed landmarks (nearest, gated).

    Returns the updated pose and covariance, per detection the matched landmark (index into
    ``lm_xy``) or -1, and the update's linear form (None without a match): the gain ``K``
    (3, 2m) over the matched detections' stacked (range, bearing) innovations, their pose and
    landmark Jacobians ``H_x`` (2m, 3) and ``H_m`` (m, 2, 2), the matched detections' indices
    and their landmarks' (for :class:`~stemmap.slam._tree_map_errors.TreeMapErrors`).
    """
    from stemmap.slam.treedb import range_bearing_jacobians

    z_pred, Hx, Hm = range_bearing_jacobians(pose[None, :], lm_xy, offset)  # (L, ...)
    S = np.einsum("lij,jk,lmk->lim", Hx, P, Hx)
    S = S + Hm @ lm_cov @ np.swapaxes(Hm, 1, 2) + R
    Sinv = np.linalg.inv(S)  # (L, 2, 2)
    z = np.column_stack((ranges, bearings))  # (K, 2)
    nu = z[:, None, :] - z_pred[None, :, :]  # (K, L, 2)
    nu[..., 1] = wrap_angle(nu[..., 1])
    d2 = np.einsum("kli,lij,klj->kl", nu, Sinv, nu)
    j = np.argmin(d2, axis=1)
    best = d2[np.arange(z.shape[0]), j]
    ok = best <= chi2_gate
    # one detection per landmark: keep the closest
    if np.any(ok):
        order = np.argsort(best)
        seen: set[int] = set()
        for k in order:
            if ok[k]:
                if int(j[k]) in seen:
                    ok[k] = False
                else:
                    seen.add(int(j[k]))
    kk = np.flatnonzero(ok)
    matched = np.where(ok, j, -1).astype(np.int64)
    if kk.size == 0:
        return pose, P, matched, None
    jj = j[kk]
    H = Hx[jj].reshape(-1, 3)
    y = nu[kk, jj].reshape(-1)
    Rb = np.zeros((2 * kk.size, 2 * kk.size))
    Rl = Hm[jj] @ lm_cov[jj] @ np.swapaxes(Hm[jj], 1, 2) + R
    for i in range(kk.size):
        Rb[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = Rl[i]
    S_all = H @ P @ H.T + Rb
    K = np.linalg.solve(S_all, H @ P).T
    new_pose = pose + K @ y
    new_pose[2] = wrap_angle(new_pose[2])
    I_KH = np.eye(3) - K @ H
    P_new = I_KH @ P @ I_KH.T + K @ Rb @ K.T  # Joseph form
    gain = (K, H, Hm[jj], kk.astype(np.int64), jj.astype(np.int64))
    return new_pose, 0.5 * (P_new + P_new.T), matched, gain
