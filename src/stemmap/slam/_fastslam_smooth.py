"""Joint smoothing of the FastSLAM path and map along the best particle's associations (ours).

FastSLAM's trajectory is the ancestry of the final best particle, and its map that particle's
landmark EKFs (Montemerlo et al. 2002). Neither is ever revised after the fact: the particles
share one ancestor a minute back (path degeneracy, Bailey et al., "Consistency of the FastSLAM
algorithm", ICRA 2006), so when a loop closes, the landmarks mapped while the path drifted stay
where the drifting path put them (docs/algorithms/slam.md, FastSLAM diagnosis item 3). A path
re-estimated on that map (:mod:`stemmap.slam._ekf_smooth`, the EKF's smoother) inherits its
errors.

Here both are re-estimated together, after the filter: the maximum a posteriori poses *and*
landmarks given

* the pre-integrated odometry between consecutive frames (the increments and covariances the
  filter's proposal sampled from, :func:`stemmap.slam.motion.preintegrate_spans`; factors as in
  :func:`stemmap.slam._ekf_smooth.odometry_terms`), and
* every detection the best particle's lineage associated with a landmark of the final map (the
  associations the filter made, frame by frame, in the particle that is the ancestor of the
  final best one at that frame), as a range-bearing measurement with the filter's detection
  noise ``R`` (observation model and Jacobians
  :func:`stemmap.slam.treedb.range_bearing_jacobians`), down-weighted by Huber on the whitened
  residual (width 1.345, as the EKF smoother),

with the first pose fixed where the filter started it. This is the full-SLAM least-squares
problem of a pose-landmark graph (Thrun & Montemerlo, "The GraphSLAM algorithm", IJRR 25(5-6),
2006) with the data association taken from the particle filter; Gauss-Newton, each step one
sparse LU solve (SuperLU, minimum-degree ordering on H + Hᵀ) of the normal equations.

The covariance of each smoothed tree is the 2x2 block of the inverse of the last Gauss-Newton
information (the Laplace approximation of the joint posterior, Huber weights included).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.linalg import solveh_banded
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import splu

from stemmap.slam._ekf_smooth import (
    _ODO_FLOOR,
    _PRIOR_INFO,
    banded_lower,
    odometry_terms,
    smooth_path,
)
from stemmap.slam._graph_marginals import _merge_duplicates
from stemmap.slam.base import IntArray
from stemmap.slam.treedb import range_bearing_jacobians
from stemmap.types import FloatArray, Tree, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem
    from stemmap.slam.fastslam import FastSlam

__all__ = ["smooth_fastslam", "smooth_joint"]


def _block_coo(
    blocks: FloatArray, r0: IntArray, c0: IntArray
) -> tuple[IntArray, IntArray, FloatArray]:
    """COO triplets of dense blocks ``blocks`` (N, a, b) placed at rows ``r0 + i``, columns
    ``c0 + j`` (``r0``, ``c0`` (N,))."""
    _, a, b = blocks.shape
    rows = (r0[:, None, None] + np.arange(a)[None, :, None]) + np.zeros((1, 1, b), np.int64)
    cols = (c0[:, None, None] + np.arange(b)[None, None, :]) + np.zeros((1, a, 1), np.int64)
    return rows.ravel(), cols.ravel(), blocks.ravel()


def smooth_joint(
    poses: FloatArray,
    deltas: FloatArray,
    covs: FloatArray,
    obs: tuple[IntArray, IntArray, FloatArray, FloatArray],
    lm_xy: FloatArray,
    sensor_offset: tuple[float, float],
    R1: FloatArray,
    *,
    huber_k: float = 1.345,
    iterations: int = 30,
) -> tuple[FloatArray, FloatArray, FloatArray, dict[str, float | int]]:
    """Poses (N, 3) and landmarks (L, 2) re-estimated jointly, and the landmarks' marginal
    covariances (L, 2, 2) (module docstring).

    poses : (N, 3) the filter's vehicle poses (start of the iteration; ``poses[0]`` is fixed)
    deltas, covs : (N-1, 3) / (N-1, 3, 3) odometry increments between consecutive frames (in
        the earlier frame's vehicle frame) and their covariances
    obs : ``(frame, landmark, range, bearing)`` per associated detection
    lm_xy : (L, 2) the filter's landmark positions (start of the iteration)
    sensor_offset : (a, b) of the sensor in the vehicle frame; R1 : (2, 2) detection noise

    Returns poses, landmarks, landmark covariances and stats (iterations, measurements, mean
    whitened residual² of the measurements before / after, share down-weighted by Huber).
    """
    x = np.array(poses, dtype=np.float64)
    L = np.array(lm_xy, dtype=np.float64)
    n, m = x.shape[0], L.shape[0]
    fr, lj, rz, bz = obs
    om = np.linalg.inv(covs + _ODO_FLOOR)
    W = np.linalg.inv(R1)
    nv = 3 * n + 2 * m
    stats: dict[str, float | int] = {"smoother_measurements": int(fr.size)}
    pf = 3 * np.asarray(fr, dtype=np.int64)  # first row of the measurement's pose
    pl = 3 * n + 2 * np.asarray(lj, dtype=np.int64)  # first row of its landmark
    p3 = 3 * np.arange(n, dtype=np.int64)
    it, d2 = 0, np.zeros(0)
    for it in range(1, iterations + 1):
        diag = np.zeros((n, 3, 3))
        g = np.zeros(nv)
        diag[0] += _PRIOR_INFO * np.eye(3)
        e0 = np.asarray(poses[0], dtype=np.float64) - x[0]
        e0[2] = wrap_angle(e0[2])
        g[:3] += _PRIOR_INFO * e0
        off = np.zeros((0, 3, 3))
        if n > 1:
            Haa, Hbb, off, ga, gb = odometry_terms(x, deltas, om)
            diag[:-1] += Haa
            diag[1:] += Hbb
            g[: 3 * (n - 1)] += ga.ravel()
            g[3 : 3 * n] += gb.ravel()
        z, Jv, Jl = range_bearing_jacobians(x[fr], L[lj], sensor_offset)
        em = np.column_stack((rz - z[:, 0], wrap_angle(bz - z[:, 1])))
        d2 = np.einsum("mi,ij,mj->m", em, W, em)
        dn = np.sqrt(d2)
        w = np.where(dn <= huber_k, 1.0, huber_k / np.maximum(dn, 1e-12))
        JvT_W = w[:, None, None] * (Jv.transpose(0, 2, 1) @ W)
        JlT_W = w[:, None, None] * (Jl.transpose(0, 2, 1) @ W)
        if it == 1:
            stats["smoother_meas_d2_before"] = float(d2.mean()) if d2.size else math.nan
        np.add.at(g, pf[:, None] + np.arange(3), np.einsum("mij,mj->mi", JvT_W, em))
        np.add.at(g, pl[:, None] + np.arange(2), np.einsum("mij,mj->mi", JlT_W, em))
        Hvl = JvT_W @ Jl
        parts = [
            _block_coo(diag, p3, p3),
            _block_coo(off, p3[1:], p3[:-1]),
            _block_coo(off.transpose(0, 2, 1), p3[:-1], p3[1:]),
            _block_coo(JvT_W @ Jv, pf, pf),
            _block_coo(Hvl, pf, pl),
            _block_coo(Hvl.transpose(0, 2, 1), pl, pf),
            _block_coo(JlT_W @ Jl, pl, pl),
        ]
        rows = np.concatenate([q[0] for q in parts])
        cols = np.concatenate([q[1] for q in parts])
        vals = np.concatenate([q[2] for q in parts])
        H = coo_matrix((vals, (rows, cols)), shape=(nv, nv)).tocsc()
        step = splu(H, permc_spec="MMD_AT_PLUS_A").solve(g)
        x += step[: 3 * n].reshape(n, 3)
        x[:, 2] = wrap_angle(x[:, 2])
        L += step[3 * n :].reshape(m, 2)
        # converged: every position (pose and tree) moves < 1 mm, every heading < 1e-5 rad
        # (the Huber reweighting converges linearly: the tail of sub-millimetre steps is left)
        if (
            np.abs(step[: 3 * n].reshape(n, 3)[:, 2]).max() < 1e-5
            and np.abs(np.delete(step, np.arange(2, 3 * n, 3))).max() < 1e-3
        ):
            break
    stats["smoother_iterations"] = it
    stats["smoother_meas_d2_after"] = float(d2.mean()) if d2.size else math.nan
    stats["smoother_huber_share"] = float((d2 > huber_k**2).mean()) if d2.size else 0.0
    # landmark marginals: the (2, 2) blocks of H^-1 of the last linearisation, as the inverse
    # of the Schur complement S = H_ll - H_lp H_pp^-1 H_pl (H_pp block-tridiagonal: banded
    # solves, in chunks of landmarks)
    lm_cov = np.zeros((m, 2, 2))
    if m:
        np.add.at(diag, fr, JvT_W @ Jv)  # H_pp: the pose blocks of the last linearisation
        ab = banded_lower(diag, off)
        r_, c_, v_ = _block_coo(Hvl, pf, pl - 3 * n)
        Hpl = coo_matrix((v_, (r_, c_)), shape=(3 * n, 2 * m)).tocsc()
        r_, c_, v_ = _block_coo(JlT_W @ Jl, pl - 3 * n, pl - 3 * n)
        S = coo_matrix((v_, (r_, c_)), shape=(2 * m, 2 * m)).toarray()
        for lo in range(0, 2 * m, 64):
            blk = Hpl[:, lo : lo + 64].toarray()
            S[:, lo : lo + 64] -= Hpl.T @ solveh_banded(ab, blk, lower=True)
        Sinv = np.linalg.inv(0.5 * (S + S.T))
        i2 = 2 * np.arange(m)
        lm_cov[:, 0, 0] = Sinv[i2, i2]
        lm_cov[:, 1, 1] = Sinv[i2 + 1, i2 + 1]
        lm_cov[:, 0, 1] = lm_cov[:, 1, 0] = 0.5 * (Sinv[i2, i2 + 1] + Sinv[i2 + 1, i2])
    return x, L, lm_cov, stats


def smooth_fastslam(
    fs: FastSlam,
    problem: SlamProblem,
    pre: Any,
    traj: FloatArray,
    trees: list[Tree],
    ids: np.ndarray,
    lineage_ids: list[tuple[int, np.ndarray]],
    R: FloatArray,
) -> tuple[FloatArray, list[Tree], FloatArray, dict[str, float | int]]:
    """The FastSLAM result ``traj`` (N, 3), ``trees`` re-estimated by :func:`smooth_joint`
    on the detections of the best particle's lineage: ``lineage_ids`` holds, per frame with
    detections, the landmark id each detection went to in the ancestor of the final best
    particle at that frame (-1: none); ``ids`` are the ids of ``trees``. Trees the smoothing
    brings within ``fs.merge_dist`` are merged (iSAM2's rule) and the problem solved again, up
    to ``fs.merge_rounds`` times. Returns the path, the trees, the pose covariances (the
    smoothed path given the smoothed map: :func:`stemmap.slam._ekf_smooth.smooth_path`'s chain
    marginals at that path, one linearisation, no step) times ``fs.pose_cov_inflation``, with
    the trees' joint marginals times ``fs.tree_cov_inflation``, and stats."""
    frames = problem.frames
    fr = np.concatenate([np.full(v.size, f, np.int64) for f, v in lineage_ids])
    det = np.concatenate([np.arange(v.size) for _, v in lineage_ids])
    li = np.concatenate([v for _, v in lineage_ids])
    order = np.argsort(ids)
    at = np.minimum(np.searchsorted(ids[order], li), ids.size - 1)
    ok = (li >= 0) & (ids[order][at] == li)
    fr, det, lj = fr[ok], det[ok], order[at[ok]]
    start = np.asarray(frames.ptr[fr], dtype=np.int64)
    rz = np.asarray(frames.ranges)[start + det]
    bz = np.asarray(frames.bearings)[start + det]
    L = np.array([[t.x, t.y] for t in trees])
    off = problem.sensor_offset
    x, n_merged = traj, 0
    st: dict[str, float | int] = {}
    for round_ in range(fs.merge_rounds + 1):
        x, L, lm_cov, st_r = smooth_joint(x, pre.deltas, pre.covs, (fr, lj, rz, bz), L, off, R)
        if round_:
            st_r["smoother_meas_d2_before"] = st["smoother_meas_d2_before"]
            st_r["smoother_iterations"] += st["smoother_iterations"]
        st = st_r
        if round_ == fs.merge_rounds or fs.merge_dist <= 0:
            break
        # trees the smoothing brought together: one trunk mapped twice (iSAM2's rule)
        cnt = np.array([t.n_obs for t in trees], dtype=np.float64)
        dia = np.array([t.diameter for t in trees])
        rep = _merge_duplicates(L, np.nan_to_num(dia, nan=0.0), cnt, fs.merge_dist, fs.merge_ddiam)
        groups, inv = np.unique(rep, return_inverse=True)
        if groups.size == len(trees):
            break
        n_merged += len(trees) - groups.size
        w = np.bincount(inv, weights=cnt)
        L = np.column_stack([np.bincount(inv, weights=cnt * L[:, i]) / w for i in (0, 1)])
        fin = np.isfinite(dia)
        wd = np.bincount(inv, weights=np.where(fin, cnt, 0.0))
        ds = np.bincount(inv, weights=np.where(fin, cnt * np.nan_to_num(dia), 0.0))
        trees = [
            replace(
                trees[int(g)],
                id=i,
                diameter=float(ds[i] / wd[i]) if wd[i] > 0 else math.nan,
                n_obs=int(w[i]),
                first_time=min(t.first_time for t, m in zip(trees, inv, strict=True) if m == i),
                last_time=max(t.last_time for t, m in zip(trees, inv, strict=True) if m == i),
            )
            for i, g in enumerate(groups)
        ]
        lj = inv[lj]
    obs = (fr, lj, rz, bz)
    _, pose_covs, _ = smooth_path(x, pre.deltas, pre.covs, obs, L, lm_cov, off, R, iterations=1)
    pose_covs *= float(fs.pose_cov_inflation or 1.0)
    lm_cov *= float(fs.tree_cov_inflation or 1.0)
    out = [
        replace(t, x=float(L[i, 0]), y=float(L[i, 1]), cov=lm_cov[i]) for i, t in enumerate(trees)
    ]
    st["smoother_merged"] = n_merged
    return x, out, pose_covs, st
