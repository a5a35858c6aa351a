"""Data association for landmark SLAM: Mahalanobis gating, nearest neighbour, JCBB.

All functions take the quantities of one frame:

* ``innovations`` (k, c, 2): measurement minus prediction for observation ``i`` and candidate
  landmark ``j`` (bearing component already wrapped);
* ``pred_cov`` (2c, 2c): joint covariance of the *predicted* measurements of the ``c`` candidate
  landmarks (``H P Hᵀ``; off-diagonal blocks carry the correlation through the vehicle pose);
* ``meas_cov`` (k, 2, 2) or (2, 2): measurement noise of each observation;
* ``extra_d2`` (k, c), optional: an additional, independent squared-normalised cue (here the
  diameter difference ``(d_obs - d_lm)² / (σ²_obs + σ²_lm)``) with ``extra_dof`` degrees of
  freedom per pair. The diameter of a trunk is a signature the pose cannot change.

References
----------
J. Neira, J. D. Tardós, "Data association in stochastic mapping using the joint compatibility
test", IEEE T-RA 17(6), 2001 (JCBB, individual compatibility gate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from stemmap.errors import ConfigError, InputError
from stemmap.slam._association_kernel import greedy_nn, joint_nis_core
from stemmap.types import FloatArray

__all__ = [
    "chi2_gate",
    "individual_compatibility",
    "jcbb",
    "joint_nis",
    "nearest_neighbour",
]

IntArray = NDArray[np.int64]

_GATES: dict[tuple[float, int], float] = {}


def chi2_gate(alpha: float, dof: int) -> float:
    """Chi-square quantile ``alpha`` for ``dof`` degrees of freedom (cached)."""
    if not 0.0 < alpha < 1.0:
        raise ConfigError(f"gate probability alpha must be in (0, 1), got {alpha}.")
    key = (alpha, dof)
    if key not in _GATES:
        _GATES[key] = float(chi2.ppf(alpha, dof))
    return _GATES[key]


def _meas_cov(meas_cov: ArrayLike, k: int) -> FloatArray:
    R = np.asarray(meas_cov, dtype=np.float64)
    if R.shape == (2, 2):
        R = np.broadcast_to(R, (k, 2, 2))
    if R.shape != (k, 2, 2):
        raise InputError(f"meas_cov must have shape (2, 2) or ({k}, 2, 2), got {R.shape}.")
    return R


def individual_compatibility(
    innovations: ArrayLike,
    pred_cov: ArrayLike,
    meas_cov: ArrayLike,
    extra_d2: ArrayLike | None = None,
) -> FloatArray:
    """Squared Mahalanobis distance (k, c) of every observation-landmark pair.

    ``d²_ij = ν_ijᵀ (S_j + R_i)⁻¹ ν_ij (+ extra_d2_ij)`` with ``S_j`` the j-th diagonal 2x2 block
    of ``pred_cov`` (vectorised closed-form 2x2 inverse).
    """
    nu = np.asarray(innovations, dtype=np.float64)
    if nu.ndim != 3 or nu.shape[2] != 2:
        raise InputError(f"innovations must have shape (k, c, 2), got {nu.shape}.")
    k, c = nu.shape[:2]
    C = np.asarray(pred_cov, dtype=np.float64)
    if C.shape != (2 * c, 2 * c):
        raise InputError(f"pred_cov must have shape ({2 * c}, {2 * c}), got {C.shape}.")
    idx = np.arange(c)
    S = np.empty((c, 2, 2))
    S[:, 0, 0] = C[2 * idx, 2 * idx]
    S[:, 0, 1] = C[2 * idx, 2 * idx + 1]
    S[:, 1, 0] = C[2 * idx + 1, 2 * idx]
    S[:, 1, 1] = C[2 * idx + 1, 2 * idx + 1]
    T = S[None, :, :, :] + _meas_cov(meas_cov, k)[:, None, :, :]
    a, b, cc, d = T[..., 0, 0], 0.5 * (T[..., 0, 1] + T[..., 1, 0]), T[..., 1, 0], T[..., 1, 1]
    del cc
    det = a * d - b * b
    x, y = nu[..., 0], nu[..., 1]
    d2: FloatArray = (d * x * x - 2.0 * b * x * y + a * y * y) / det
    if extra_d2 is not None:
        d2 = d2 + np.asarray(extra_d2, dtype=np.float64)
    return d2


def nearest_neighbour(d2: ArrayLike, gate: float) -> IntArray:
    """Greedy one-to-one nearest neighbour: pairs taken in increasing ``d²`` below ``gate``.

    Returns ``assign`` (k,): candidate index per observation, ``-1`` if unassigned. Ties in
    ``d²`` go to the earlier pair in row-major order (compiled loop:
    :func:`stemmap.slam._association_kernel.greedy_nn`).
    """
    D = np.ascontiguousarray(d2, dtype=np.float64)
    if D.size == 0:
        return np.full(D.shape[0], -1, dtype=np.int64)
    assign: IntArray = greedy_nn(D, float(gate))
    return assign


def joint_nis(
    pairs: list[tuple[int, int]],
    innovations: FloatArray,
    pred_cov: FloatArray,
    meas_cov: FloatArray,
    extra_d2: FloatArray | None = None,
) -> float:
    """Joint normalised innovation squared of a hypothesis ``[(obs, cand), ...]``.

    ``D² = νᵀ (H P Hᵀ + R)⁻¹ ν`` over the stacked innovations, plus the independent extra cue;
    ``inf`` if the joint covariance is singular. ``meas_cov`` is (k, 2, 2). The stacking and the
    solve are compiled (:func:`stemmap.slam._association_kernel.joint_nis_core`).
    """
    if not pairs:
        return 0.0
    obs = np.array([p[0] for p in pairs])
    cand = np.array([p[1] for p in pairs])
    return _joint_nis(obs, cand, innovations, pred_cov, meas_cov, extra_d2)


def _joint_nis(
    obs: IntArray,
    cand: IntArray,
    innovations: FloatArray,
    pred_cov: FloatArray,
    meas_cov: FloatArray,
    extra_d2: FloatArray | None,
) -> float:
    """:func:`joint_nis` of the pairs ``(obs[t], cand[t])`` (at least one)."""
    val = joint_nis_core(obs, cand, innovations, pred_cov, meas_cov)
    if extra_d2 is not None:
        val += float(extra_d2[obs, cand].sum())
    return val


@dataclass
class _Search:
    best: list[tuple[int, int]]
    best_nis: float
    nodes: int


def jcbb(
    innovations: ArrayLike,
    pred_cov: ArrayLike,
    meas_cov: ArrayLike,
    *,
    alpha: float = 0.99,
    extra_d2: ArrayLike | None = None,
    extra_dof: int = 0,
    max_nodes: int = 5000,
) -> IntArray:
    """Joint Compatibility Branch and Bound (Neira & Tardós 2001).

    Searches the interpretation tree for the hypothesis with the most pairings whose joint NIS
    passes the chi-square gate ``chi2(alpha, dof = (2 + extra_dof) * pairings)``; ties go to the
    smaller joint NIS. Only individually compatible pairs (same gate, one pair) are branched on.
    ``max_nodes`` bounds the work per frame; when hit, the best hypothesis so far is returned.

    Returns
    -------
    ndarray (k,), int
        Candidate index per observation, ``-1`` for "new or spurious".
    """
    nu = np.asarray(innovations, dtype=np.float64)
    if nu.ndim != 3 or nu.shape[2] != 2:
        raise InputError(f"innovations must have shape (k, c, 2), got {nu.shape}.")
    k = nu.shape[0]
    C = np.asarray(pred_cov, dtype=np.float64)
    R = _meas_cov(meas_cov, k)
    E = None if extra_d2 is None else np.asarray(extra_d2, dtype=np.float64)
    dof1 = 2 + extra_dof
    d2 = individual_compatibility(nu, C, R, E)
    gate1 = chi2_gate(alpha, dof1)
    ok = d2 < gate1
    has = ok.any(axis=1)
    # fast path: if greedy NN pairs every observation that has a candidate and the pairing is
    # jointly compatible, no hypothesis can have more pairings -- accept it without searching
    nn = nearest_neighbour(d2, gate1)
    nn_obs = np.flatnonzero(nn >= 0)
    if nn_obs.size == int(has.sum()) and (
        not nn_obs.size
        or _joint_nis(nn_obs, nn[nn_obs], nu, C, R, E) < chi2_gate(alpha, dof1 * nn_obs.size)
    ):
        return nn
    cands = []
    for i in range(k):
        js = np.flatnonzero(ok[i])
        cands.append(js[np.argsort(d2[i, js])].tolist())
    state = _Search([], math.inf, 0)
    remaining = np.array([sum(1 for x in cands[i:] if x) for i in range(k)] + [0])

    def recurse(i: int, hyp: list[tuple[int, int]], used: set[int]) -> None:
        state.nodes += 1
        if i == k:
            n, nb = len(hyp), len(state.best)
            if n > nb or (n == nb and n > 0):
                nis = joint_nis(hyp, nu, C, R, E)
                if n > nb or nis < state.best_nis:
                    state.best, state.best_nis = list(hyp), nis
            return
        if state.nodes > max_nodes:
            return
        for j in cands[i]:
            if j in used:
                continue
            hyp.append((i, int(j)))
            if joint_nis(hyp, nu, C, R, E) < chi2_gate(alpha, dof1 * len(hyp)):
                used.add(int(j))
                recurse(i + 1, hyp, used)
                used.discard(int(j))
            hyp.pop()
        # star branch (observation i unmatched) only if it can still beat the best
        if len(hyp) + int(remaining[i + 1]) > len(state.best):
            recurse(i + 1, hyp, used)

    recurse(0, [], set())
    assign = np.full(k, -1, dtype=np.int64)
    for i, j in state.best:
        assign[i] = j
    return assign
