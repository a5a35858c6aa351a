"""Numba kernels of :mod:`stemmap.slam.association`: greedy nearest neighbour and joint NIS.

Kept in their own module so that the compiled kernels (``numba.njit(cache=True)``) are not
invalidated by edits to ``association.py``. Both compute exactly what the numpy forms they
replaced computed (same pairs in the same order; the same LAPACK ``gesv`` solve and BLAS
``ddot``), checked in ``tests/slam/test_association.py``; they only remove the per-call overhead
that dominated at the few-detections-per-frame sizes of the EKF.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["greedy_nn", "joint_nis_core"]


@numba.njit(cache=True)
def greedy_nn(D: np.ndarray, gate: float) -> np.ndarray:
    """Greedy one-to-one assignment: the pairs ``gate > D[i, j]`` taken in increasing ``D``
    (stable: equal values in row-major order). Returns (k,) candidate per row, -1 if none."""
    k, c = D.shape
    assign = np.full(k, -1, dtype=np.int64)
    ii = np.empty(k * c, dtype=np.int64)
    jj = np.empty(k * c, dtype=np.int64)
    vals = np.empty(k * c)
    n = 0
    for i in range(k):
        for j in range(c):
            if gate > D[i, j]:
                ii[n], jj[n], vals[n] = i, j, D[i, j]
                n += 1
    order = np.argsort(vals[:n], kind="mergesort")
    used_i = np.zeros(k, dtype=np.bool_)
    used_j = np.zeros(c, dtype=np.bool_)
    for t in order:
        i, j = ii[t], jj[t]
        if used_i[i] or used_j[j]:
            continue
        assign[i] = j
        used_i[i] = True
        used_j[j] = True
    return assign


@numba.njit(cache=True)
def joint_nis_core(
    obs: np.ndarray, cand: np.ndarray, nu: np.ndarray, C: np.ndarray, R: np.ndarray
) -> float:
    """``νᵀ S⁻¹ ν`` of the pairs ``(obs[t], cand[t])``: ``ν`` the stacked innovations
    ``nu[obs, cand]``, ``S`` the rows/columns ``2 cand, 2 cand + 1`` of ``C`` plus ``R[obs[t]]``
    on the diagonal blocks. ``inf`` if ``S`` is singular."""
    m = obs.shape[0]
    S = np.empty((2 * m, 2 * m))
    v = np.empty(2 * m)
    for a in range(m):
        ca = 2 * cand[a]
        v[2 * a] = nu[obs[a], cand[a], 0]
        v[2 * a + 1] = nu[obs[a], cand[a], 1]
        for b in range(m):
            cb = 2 * cand[b]
            S[2 * a, 2 * b] = C[ca, cb]
            S[2 * a, 2 * b + 1] = C[ca, cb + 1]
            S[2 * a + 1, 2 * b] = C[ca + 1, cb]
            S[2 * a + 1, 2 * b + 1] = C[ca + 1, cb + 1]
        S[2 * a, 2 * a] += R[obs[a], 0, 0]
        S[2 * a, 2 * a + 1] += R[obs[a], 0, 1]
        S[2 * a + 1, 2 * a] += R[obs[a], 1, 0]
        S[2 * a + 1, 2 * a + 1] += R[obs[a], 1, 1]
    try:
        x = np.linalg.solve(S, v)
    except Exception:  # singular (numpy's LinAlgError)
        return np.inf
    return float(np.dot(v, x))
