"""Duplicate-landmark merging of EKF-SLAM (ours; docs/algorithms/slam.md "Duplicate merging").

Used by both the full filter (:mod:`stemmap.slam.ekf`) and the compressed one
(:mod:`stemmap.slam._ekf_compressed`): find landmark pairs closer than ``merge_radius``
(:func:`close_pairs`) and decide which are one tree (:func:`decide_merges`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from stemmap.slam.association import chi2_gate
from stemmap.slam.base import IntArray
from stemmap.types import FloatArray

__all__ = ["close_pairs", "decide_merges", "inv2_quad"]


def inv2_quad(T: FloatArray, x: FloatArray, y: FloatArray) -> FloatArray:
    """``[x y] T⁻¹ [x y]ᵀ`` for stacked 2x2 ``T`` (same closed form as
    :func:`stemmap.slam.association.individual_compatibility`)."""
    a, b, d = T[..., 0, 0], 0.5 * (T[..., 0, 1] + T[..., 1, 0]), T[..., 1, 1]
    det = a * d - b * b
    out: FloatArray = (d * x * x - 2.0 * b * x * y + a * y * y) / det
    return out


def close_pairs(
    xy: FloatArray, recent: NDArray[np.bool_], radius: float
) -> tuple[IntArray, IntArray]:
    """Landmark pairs closer than ``radius`` with at least one member seen recently (sorted)."""
    from scipy.spatial import cKDTree

    if xy.shape[0] < 2:
        e = np.zeros(0, dtype=np.int64)
        return e, e
    pr = cKDTree(xy).query_pairs(radius, output_type="ndarray")
    if pr.shape[0]:
        pr = pr[recent[pr[:, 0]] | recent[pr[:, 1]]]
        pr = pr[np.lexsort((pr[:, 1], pr[:, 0]))]
    return pr[:, 0].astype(np.int64), pr[:, 1].astype(np.int64)


def decide_merges(
    pi: IntArray,
    pj: IntArray,
    xy: FloatArray,
    Pii: FloatArray,
    Pjj: FloatArray,
    Pij: FloatArray,
    d_mean: FloatArray,
    d_n: IntArray,
    nobs: IntArray,
    together: NDArray[np.bool_],
    *,
    sd2: float | None,
    alpha: float,
) -> list[tuple[int, int, bool]]:
    """Which close pairs are one tree: ``[(keep, drop, compatible), ...]`` (greedy, one merge
    per landmark per pass; the kept landmark is the more-observed one).

    * **compatible** -- the pair is statistically one point: ``d² = Δᵀ S⁻¹ Δ`` with the joint
      ``S = P_ii + P_jj - P_ij - P_ji`` (plus the diameter cue ``(d̄_i - d̄_j)² / (σ²/n_i +
      σ²/n_j)``, one more dof) below ``chi2(alpha)``;
    * or the filter is too confident to call them one point but the data say they are one
      tree: the trunk circles overlap, ``|Δ| < (d̄_i + d̄_j) / 2`` (two real trunks cannot),
      or the two were never matched in the same scan (``together`` False: a laser scan shows
      two trunks 1 m apart as two detections, one trunk as one).

    The filter then applies the constraint ``m_i - m_j = 0`` and marginalises ``m_drop`` out
    (``EkfConfig.merge_constraint``; without it, incompatible pairs are only marginalised).
    """
    if not pi.size:
        return []
    S = Pii + Pjj - Pij - Pij.transpose(0, 2, 1)
    D = xy[pi] - xy[pj]
    d2 = inv2_quad(S, D[:, 0], D[:, 1])
    has = (d_n[pi] > 0) & (d_n[pj] > 0)
    dof = np.full(pi.size, 2)
    if sd2 is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            e = (d_mean[pi] - d_mean[pj]) ** 2 / (sd2 / d_n[pi] + sd2 / d_n[pj])
        d2 = d2 + np.where(has, e, 0.0)
        dof[has] = 3
    gate = np.array([chi2_gate(alpha, int(k)) for k in dof])
    fuse = d2 < gate
    dist = np.hypot(D[:, 0], D[:, 1])
    with np.errstate(invalid="ignore"):
        overlap = has & (dist < 0.5 * (d_mean[pi] + d_mean[pj]))
    same = ~fuse & (overlap | ~together)
    order = np.concatenate(
        (np.flatnonzero(fuse)[np.argsort(d2[fuse], kind="stable")],
         np.flatnonzero(same)[np.argsort(dist[same], kind="stable")])
    )  # fmt: skip
    used: set[int] = set()
    out = []
    for t in order:
        i, j = int(pi[t]), int(pj[t])
        if i in used or j in used:
            continue
        used.update((i, j))
        keep, drop = (i, j) if nobs[i] >= nobs[j] else (j, i)
        out.append((keep, drop, bool(fuse[t])))
    return out
