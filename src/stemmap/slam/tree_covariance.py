"""Covariance of a mapped tree from the detections averaged into it, with the pose errors
of the observing frames propagated and correlated (issue 14; ours).

The tree DB (visual-lidar 2023 eq. 2, :mod:`stemmap.slam.treedb`) and Forestrix (Öhman 2007
§2.2, :mod:`stemmap.slam.forestrix`) place a tree at an average of its detections mapped to the
world at the estimated poses: ``t̂ = Σ_k W_k z_k`` with ``Σ_k W_k = I`` (equal weights
``W_k = I / n`` for eq. 2's running mean; information weights ``W_k = (Σ Λ)⁻¹ Λ_k`` for the
Kalman refinement of :mod:`stemmap.slam.refine`). To first order a detection's error is

.. math::
    z_k - t = J_{p,k}\\,\\delta p_{f(k)} + J_{z,k}\\,v_k,

with ``J_p`` and ``J_z`` of :func:`~stemmap.slam.refine.world_observation_jacobians`,
``δp_f`` the error of the pose of frame ``f`` (covariance ``P_f``, the back-end's
``SlamResult.pose_covs``) and ``v_k`` the range-bearing noise (``diag(σ_r², σ_φ²)``,
independent between detections). So

.. math::
    \\operatorname{Cov}(\\hat t) = \\sum_k W_k J_{z,k} R_z J_{z,k}^T W_k^T
      + \\sum_k \\sum_l A_k \\operatorname{Cov}(\\delta p_{f(k)}, \\delta p_{f(l)}) A_l^T,
    \\qquad A_k = W_k J_{p,k}.

The second sum is what the earlier reported covariances left out: the tree DB's Kalman
refinement treated the pose error of each detection as independent of the others (so it
averaged down as ``1/n``), Forestrix's scatter-over-``n`` ignored it altogether. A tree is
seen from consecutive frames whose pose errors are nearly the same; averaging ``n`` of them
removes none of that shared error.

**Cross-covariance of pose errors.** A back-end gives only the marginals ``P_f``. The pose
error of dead-reckoned or scan-to-map odometry is a random walk along the drive: the later
frame's error is the earlier one's plus independent increments, so for a scalar error
``Cov(δp_k, δp_l) = min(s_k, s_l)`` in the "variance time" ``s = tr P``. For the 3x3 marginals
we write

.. math::
    \\operatorname{Cov}(\\delta p_k, \\delta p_l) = \\rho_{kl}\\, P_k^{1/2} P_l^{1/2},\\qquad
    \\rho_{kl} = \\sqrt{\\min(s_k, s_l) / \\max(s_k, s_l)},

which is that random walk when the marginals are multiples of one matrix, gives ``P_k`` on the
diagonal, and is positive semi-definite for any marginals (the joint covariance is
``D (ρ ⊗ I_3) Dᵀ`` with ``D = blockdiag(P_k^{1/2})`` and ``ρ`` the Brownian correlation, a
PSD kernel). Equal marginals (a tree seen from poses whose errors are the same) are fully
correlated: averaging ``n`` detections removes nothing of the pose error. After a loop
closure the marginals no longer grow in time (a bridge); ``ρ`` then over-states the
correlation slightly (for a Brownian bridge ``Cov = s(T-t)/T <= sqrt(Var_s Var_t)``), on the
conservative side. Sorting a tree's detections by ``s`` makes the double sum one pass with
prefix sums (``B_k = W_k J_{p,k} P_k^{1/2}``, ``u = sqrt(s)``):
``Σ_q B_q B_qᵀ + Σ_q (u_q⁻¹ Σ_{i<q} u_i B_i) B_qᵀ + transpose``.

**Correlated detection errors within a pass** (Dec 6, after
:func:`~stemmap.slam.uncertainty.fused_positions`). The first sum treats the detections' own
errors ``v_k`` as independent. On real bark the detections of one trunk along one drive-by
pass share about half their centre error (:data:`~stemmap.slam.uncertainty.CENTRE_RHO`,
docs/algorithms/scan-detection.md "Correlated detections of a pass"). With
``rho`` > 0, the detection part of every tree is split into passes (runs of its detections
without a gap of more than ``pass_gap`` s) and within a pass the ``shared`` part ``S_k`` of
each detection's map-frame covariance is correlated as ``rho S_k^{1/2} S_l^{1/2}``
(:func:`~stemmap.slam.uncertainty.correlated_mean_covariance`); passes are independent of each
other. Where the detector gives each detection's own covariance (``TreeFrames.noise_cov``),
:func:`mapped_tree_covariances` can use it for ``J_z R_z J_zᵀ`` instead of the constant one
(``detection_covs``), and that whole covariance is the shared part; detections with the
constant noise stay independent. Positions never change: only the stated covariance.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, StemMap

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import TreeFrames

__all__ = [
    "associate_per_frame",
    "averaged_tree_covariances",
    "check_tree_cov_pass",
    "mapped_tree_covariances",
    "pass_groups",
    "with_tree_covariances",
]

IntArray = NDArray[np.int64]


def associate_per_frame(
    tree_xy: ArrayLike, det_xy: ArrayLike, frame: ArrayLike, gate: float
) -> IntArray:
    """Tree (index into ``tree_xy``) of each map-frame detection: the nearest within ``gate``
    metres, at most one detection per tree and frame (the closest); -1 = none."""
    from scipy.spatial import cKDTree

    t = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(det_xy, dtype=np.float64).reshape(-1, 2)
    fr = np.asarray(frame, dtype=np.int64).reshape(-1)
    if t.shape[0] == 0 or z.shape[0] == 0:
        return np.full(z.shape[0], -1, dtype=np.int64)
    d, j = cKDTree(t).query(z, k=1, distance_upper_bound=gate)
    j = np.where(np.isfinite(d), j, -1).astype(np.int64)
    ok = np.flatnonzero(j >= 0)
    order = ok[np.lexsort((d[ok], j[ok], fr[ok]))]
    key = fr[order] * (t.shape[0] + 1) + j[order]
    dup = np.r_[False, key[1:] == key[:-1]]
    j[order[dup]] = -1
    return j


def check_tree_cov_pass(rho: float, gap: float, who: str) -> None:
    """A back-end's ``tree_cov_pass_rho`` / ``tree_cov_pass_gap_s``, validated."""
    if not 0.0 <= rho <= 1.0:
        raise ConfigError(f"{who}.tree_cov_pass_rho must be in [0, 1], got {rho}.")
    if not (gap >= 0 and math.isfinite(gap)):
        raise ConfigError(f"{who}.tree_cov_pass_gap_s must be >= 0 s, got {gap}.")


def pass_groups(tree_index: ArrayLike, times: ArrayLike, gap: float) -> IntArray:
    """Pass of each detection: one number per (tree, run of its detections with no time gap
    above ``gap`` s), numbered from 0 over all trees; -1 where ``tree_index`` is negative."""
    idx = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.shape != idx.shape:
        raise InputError(f"pass_groups: {idx.size} tree indices but {t.size} times.")
    if not gap >= 0:
        raise InputError(f"pass_groups: gap must be >= 0 s, got {gap}.")
    out = np.full(idx.shape, -1, dtype=np.int64)
    sel = np.flatnonzero(idx >= 0)
    if sel.size == 0:
        return out
    order = sel[np.lexsort((t[sel], idx[sel]))]
    new = np.ones(order.size, dtype=bool)
    new[1:] = (idx[order][1:] != idx[order][:-1]) | (np.diff(t[order]) > gap)
    out[order] = np.cumsum(new) - 1
    return out


def averaged_tree_covariances(
    tree_index: ArrayLike,
    n_trees: int,
    J_pose: ArrayLike,
    pose_covs: ArrayLike,
    meas_covs: ArrayLike,
    *,
    information: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    shared: ArrayLike | None = None,
    passes: ArrayLike | None = None,
    rho: float = 0.0,
) -> FloatArray:
    """Covariance (n_trees, 2, 2) of each tree's weighted mean of detections (module doc).

    Parameters
    ----------
    tree_index : ndarray (K,), int
        Tree of each detection; negative = not averaged into any tree.
    n_trees : int
    J_pose : ndarray (K, 2, 3)
        d (detection in the map frame) / d (x, y, θ) of its frame's pose.
    pose_covs : ndarray (K, 3, 3)
        Covariance of the pose of each detection's frame (NaN = exact, treated as 0).
    meas_covs : ndarray (K, 2, 2)
        Map-frame covariance of the detection noise alone (``J_z R_z J_zᵀ``).
    information : ndarray (K, 2, 2), optional
        Information ``Λ_k`` the estimate weighted each detection by (``W_k = (Σ Λ)⁻¹ Λ_k``);
        default equal weights (eq. 2's mean).
    weights : ndarray (K, 2, 2), optional
        Explicit ``W_k`` instead (need not sum to ``I``): e.g. ``+W`` on one half of a tree's
        detections and ``-W`` on the other gives the covariance of the difference of the two
        halves' means (benchmarks/tree_covariance_split.py). Not with ``information``.
    shared : ndarray (K, 2, 2), optional
        The part of ``meas_covs`` correlated with ``rho`` between the detections of one pass
        (module doc; default: all of it); the rest ``meas_covs - shared`` is independent.
    passes : ndarray (K,), int, optional
        Pass of each detection (:func:`pass_groups`; detections of one pass belong to one
        tree); default one pass per tree.
    rho : float in [0, 1]
        Correlation of the shared detection errors within a pass. 0 (default): every
        detection's error independent, the covariance of the module doc's first sum.

    Returns
    -------
    ndarray (n_trees, 2, 2)
        NaN for trees without detections.
    """
    idx = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    Jp = np.asarray(J_pose, dtype=np.float64).reshape(-1, 2, 3)
    P = np.nan_to_num(np.asarray(pose_covs, dtype=np.float64).reshape(-1, 3, 3))
    M = np.asarray(meas_covs, dtype=np.float64).reshape(-1, 2, 2)
    k = idx.shape[0]
    if not (Jp.shape[0] == P.shape[0] == M.shape[0] == k):
        raise InputError(
            f"averaged_tree_covariances: {k} tree indices, {Jp.shape[0]} Jacobians, "
            f"{P.shape[0]} pose covariances and {M.shape[0]} detection covariances must agree."
        )
    out = np.full((n_trees, 2, 2), np.nan)
    sel = np.flatnonzero(idx >= 0)
    if sel.size == 0:
        return out
    if np.any(idx[sel] >= n_trees):
        raise InputError(f"averaged_tree_covariances: tree index >= n_trees {n_trees}.")
    n = np.bincount(idx[sel], minlength=n_trees)
    # weights W_k (2x2), summing to I per tree
    if weights is not None:
        if information is not None:
            raise InputError("averaged_tree_covariances: give information or weights, not both.")
        W = np.asarray(weights, dtype=np.float64).reshape(-1, 2, 2)[sel]
    elif information is None:
        W = np.einsum("k,ij->kij", 1.0 / n[idx[sel]], np.eye(2))
    else:
        L = np.asarray(information, dtype=np.float64).reshape(-1, 2, 2)[sel]
        tot = np.zeros((n_trees, 2, 2))
        np.add.at(tot, idx[sel], L)
        has = n > 0
        tot_inv = np.zeros_like(tot)
        tot_inv[has] = np.linalg.inv(tot[has])
        W = tot_inv[idx[sel]] @ L
    # B_k = A_k L_k with L_k = P_k^(1/2); u_k = sqrt(tr P_k), the "variance time"
    w, V = np.linalg.eigh(0.5 * (P[sel] + np.swapaxes(P[sel], 1, 2)))
    L = (V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]) @ np.swapaxes(V, 1, 2)
    u = np.sqrt(np.clip(np.trace(P[sel], axis1=1, axis2=2), 0.0, None))
    order = np.lexsort((u, idx[sel]))  # by tree, then the smaller marginal first
    s = sel[order]
    W, j, u = W[order], idx[s], u[order]
    B = W @ Jp[s] @ L[order]  # (m, 2, 3)
    # prefix sums within each tree: pre_q = sum_{i < q, same tree} u_i B_i
    uB = u[:, None, None] * B
    csum = np.zeros((B.shape[0] + 1, 2, 3))
    csum[1:] = np.cumsum(uB, axis=0)
    first = np.r_[True, j[1:] != j[:-1]]
    start = np.flatnonzero(first)[np.cumsum(first) - 1]  # first detection of each one's tree
    pre = csum[:-1] - csum[start]
    inv_u = np.divide(1.0, u, out=np.zeros_like(u), where=u > 0)
    cross = (inv_u[:, None, None] * pre) @ np.swapaxes(B, 1, 2)
    term = B @ np.swapaxes(B, 1, 2) + cross + np.swapaxes(cross, 1, 2)
    if rho == 0.0:
        term = term + W @ M[s] @ np.swapaxes(W, 1, 2)
    acc = np.zeros((n_trees, 2, 2))
    np.add.at(acc, j, term)
    if rho != 0.0:
        acc += _correlated_detection_part(idx, n_trees, s, W, M, shared, passes, rho)
    has = n > 0
    out[has] = 0.5 * (acc[has] + np.swapaxes(acc[has], 1, 2))
    return out


def _correlated_detection_part(
    idx: IntArray,
    n_trees: int,
    s: IntArray,
    W: FloatArray,
    M: FloatArray,
    shared: ArrayLike | None,
    passes: ArrayLike | None,
    rho: float,
) -> FloatArray:
    """Per tree, the detection part ``Cov(Σ W_k v_k)`` with the ``shared`` part of ``v_k``
    correlated with ``rho`` within a pass (rows ``s`` of the inputs, weights ``W`` in that
    order; module doc)."""
    from stemmap.slam.uncertainty import correlated_mean_covariance

    k = idx.shape[0]
    S = M if shared is None else np.asarray(shared, dtype=np.float64).reshape(-1, 2, 2)
    g = idx if passes is None else np.asarray(passes, dtype=np.int64).reshape(-1)
    if S.shape[0] != k or g.shape[0] != k:
        raise InputError(
            f"averaged_tree_covariances: {k} tree indices, {S.shape[0]} shared covariances "
            f"and {g.shape[0]} passes must agree."
        )
    if np.any(g[s] < 0):
        raise InputError("averaged_tree_covariances: a detection of a tree has no pass.")
    groups, gi = np.unique(g[s], return_inverse=True)
    tree_of = np.full(groups.size, -1, dtype=np.int64)
    tree_of[gi] = idx[s]
    bad = np.zeros(groups.size, dtype=bool)
    np.logical_or.at(bad, gi, idx[s] != tree_of[gi])
    if np.any(bad):
        raise InputError("averaged_tree_covariances: a pass holds detections of two trees.")
    per_pass = correlated_mean_covariance(gi, W, M[s] - S[s], S[s], int(groups.size), rho=rho)
    acc = np.zeros((n_trees, 2, 2))
    np.add.at(acc, tree_of, per_pass)
    return acc


def mapped_tree_covariances(
    tree_xy: ArrayLike,
    poses: ArrayLike,
    pose_covs: ArrayLike,
    frame_ptr: ArrayLike,
    ranges: ArrayLike,
    bearings: ArrayLike,
    *,
    sigma_range: float,
    sigma_bearing: float,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
    gate: float,
    information_pose_covs: ArrayLike | None = None,
    detection_covs: ArrayLike | None = None,
    times: ArrayLike | None = None,
    pass_rho: float = 0.0,
    pass_gap: float = 5.0,
) -> tuple[FloatArray, IntArray]:
    """Covariance of each mapped tree from its detections (module doc), the detections given to
    the trees by :func:`associate_per_frame` at the final ``poses``.

    Parameters
    ----------
    tree_xy : ndarray (N, 2), m -- the mapped trees (map frame)
    poses : ndarray (F, 3) -- final vehicle poses
    pose_covs : ndarray (F, 3, 3)
        Covariance of each frame's pose in the map frame (``SlamResult.pose_covs``): the
        error propagated into every detection, correlated between frames (module doc).
    frame_ptr : ndarray (F + 1,), int; ranges, bearings : ndarray (K,)
        Detections in the sensor frame (:class:`~stemmap.slam.base.TreeFrames`).
    sigma_range : float, m; sigma_bearing : float, rad
        Detection noise.
    sensor_offset : (a, b), m
    gate : float, m
        Association radius.
    information_pose_covs : ndarray (F, 3, 3), optional
        The pose covariances the estimator weighted the detections with (the tree DB's Kalman
        refinement: ``Λ_k = (J_p P_f J_pᵀ + J_z R_z J_zᵀ)⁻¹``); default equal weights.
        The weights always use the constant ``sigma_range`` / ``sigma_bearing`` (what the
        estimator weighted with), whatever ``detection_covs``.
    detection_covs : ndarray (K, 2, 2), optional
        Each detection's own (range, bearing) covariance (``TreeFrames.noise_cov``; NaN rows
        = none): the detection noise of the stated covariance where finite, instead of the
        constant ``diag(sigma_range², sigma_bearing²)``.
    times : ndarray (F,), s
        Frame times, to split a tree's detections into passes (needed with ``pass_rho``).
    pass_rho : float in [0, 1]
        Correlation within a pass (:func:`pass_groups`, ``pass_gap`` s) of the errors of the
        detections that carry their own covariance (module doc); 0: independent.

    Returns
    -------
    cov : ndarray (N, 2, 2)
        NaN for trees without an associated detection.
    n_obs : ndarray (N,), int
    """
    from stemmap.slam.base import observation_to_world
    from stemmap.slam.refine import world_observation_jacobians

    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    ptr = np.asarray(frame_ptr, dtype=np.int64).reshape(-1)
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    b = np.asarray(bearings, dtype=np.float64).reshape(-1)
    txy = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    if ptr.shape[0] != p.shape[0] + 1 or ptr[-1] != r.shape[0] or b.shape != r.shape:
        raise InputError(
            f"mapped_tree_covariances: {p.shape[0]} poses need {p.shape[0] + 1} frame pointers "
            f"ending at the {r.shape[0]} detections; got {ptr.shape[0]} pointers."
        )
    n = txy.shape[0]
    frame = np.repeat(np.arange(p.shape[0]), np.diff(ptr))
    z = observation_to_world(p[frame], r, b, sensor_offset)
    idx = associate_per_frame(txy, z, frame, gate)
    use = np.flatnonzero(idx >= 0)
    Pf = np.broadcast_to(np.asarray(pose_covs, dtype=np.float64), (p.shape[0], 3, 3))
    Jp, Jz = world_observation_jacobians(p[frame[use]], r[use], b[use], sensor_offset)
    Rz = np.diag([sigma_range**2, sigma_bearing**2])
    M = Jz @ Rz @ np.swapaxes(Jz, 1, 2)
    info = None
    if information_pose_covs is not None:
        Pw = np.nan_to_num(
            np.broadcast_to(np.asarray(information_pose_covs, np.float64), (p.shape[0], 3, 3))
        )
        info = np.linalg.inv(Jp @ Pw[frame[use]] @ np.swapaxes(Jp, 1, 2) + M)
    own = np.zeros(use.size, dtype=bool)
    if detection_covs is not None:
        dc = np.asarray(detection_covs, dtype=np.float64).reshape(-1, 2, 2)
        if dc.shape[0] != r.shape[0]:
            raise InputError(
                f"mapped_tree_covariances: {dc.shape[0]} detection covariances for "
                f"{r.shape[0]} detections."
            )
        dc = dc[use]
        own = np.all(np.isfinite(dc), axis=(1, 2))
        M = M.copy()
        M[own] = Jz[own] @ dc[own] @ np.swapaxes(Jz[own], 1, 2)
    if not 0.0 <= pass_rho <= 1.0:
        raise InputError(f"mapped_tree_covariances: pass_rho must be in [0, 1], got {pass_rho}.")
    kw: dict[str, object] = {}
    if pass_rho > 0.0 and np.any(own):
        if times is None:
            raise InputError("mapped_tree_covariances: pass_rho needs the frame times.")
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        if t.shape[0] != p.shape[0]:
            raise InputError(f"mapped_tree_covariances: {t.shape[0]} times, {p.shape[0]} poses.")
        kw = {
            "shared": np.where(own[:, None, None], M, 0.0),
            "passes": pass_groups(idx[use], t[frame[use]], pass_gap),
            "rho": pass_rho,
        }
    cov = averaged_tree_covariances(
        idx[use],
        n,
        Jp,
        Pf[frame[use]],
        M,
        information=info,
        **kw,  # type: ignore[arg-type]
    )
    return cov, np.bincount(idx[use], minlength=n).astype(np.int64)


def with_tree_covariances(
    stem_map: StemMap,
    poses: ArrayLike,
    pose_covs: ArrayLike,
    frames: TreeFrames,
    *,
    sigma_range: float,
    sigma_bearing: float,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
    gate: float,
    information_pose_covs: ArrayLike | None = None,
    detection_covs: bool = False,
    pass_rho: float = 0.0,
    pass_gap: float = 5.0,
) -> StemMap:
    """``stem_map`` with every tree's ``cov`` from :func:`mapped_tree_covariances` (trees
    without an associated detection keep theirs); positions and everything else unchanged.
    The tree DB's and Forestrix's reported tree covariance (issue 14). ``detection_covs``:
    use the detections' own covariances (``frames.noise_cov``) where given; ``pass_rho``,
    ``pass_gap``: their correlation within a pass (module doc)."""
    if len(stem_map) == 0:
        return stem_map
    cov, _ = mapped_tree_covariances(
        stem_map.xy,
        poses,
        pose_covs,
        frames.ptr,
        frames.ranges,
        frames.bearings,
        sigma_range=sigma_range,
        sigma_bearing=sigma_bearing,
        sensor_offset=sensor_offset,
        gate=gate,
        information_pose_covs=information_pose_covs,
        detection_covs=frames.noise_cov if detection_covs else None,
        times=frames.times,
        pass_rho=pass_rho,
        pass_gap=pass_gap,
    )
    trees = tuple(
        replace(t, cov=cov[i]) if np.all(np.isfinite(cov[i])) else t
        for i, t in enumerate(stem_map.trees)
    )
    return replace(stem_map, trees=trees)
