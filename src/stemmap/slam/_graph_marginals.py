"""Tree-level helpers of the iSAM2 back-end: duplicate merging and tree marginals (ours).

Split out of :mod:`stemmap.slam.graph` (which re-exports the names; graph.py had grown past the
~800-line limit): :func:`_merge_duplicates` (union-find over close, diameter-compatible trees)
and :func:`_point_marginals` (the trees' 2x2 marginal covariances by the Schur complement over
the pose chain), both used by the batch back-end and by :mod:`stemmap.slam.online`; and the
GPS-free fit diagnostics at the optimum (:func:`_fit_diagnostics`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from stemmap.slam._isam2_track import band_cho_solve
from stemmap.types import FloatArray, wrap_angle

log = logging.getLogger("stemmap.slam.graph")

__all__ = [
    "_fit_diagnostics",
    "_merge_duplicates",
    "_point_marginals",
    "_tree_and_pose_marginals",
    "_tree_joint_information",
    "_tree_schur",
    "final_marginals",
]


def _merge_duplicates(
    xy: FloatArray, diam: FloatArray, nobs: np.ndarray, dist: float, max_ddiam: float
) -> np.ndarray:
    """Representative index of each landmark after merging close, diameter-compatible pairs.

    Pairs closer than ``dist`` (m) whose mean diameters differ by less than ``max_ddiam`` are
    joined (union-find), and so are pairs whose trunk circles would overlap whatever their
    diameters (on Victoria Park the detector sometimes reports ~1 m "trunks" on top of a
    0.3 m tree; the diameter cue keeps them apart during association). Each group is
    represented by its most-observed member.
    """
    from scipy.spatial import cKDTree

    n = xy.shape[0]
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    for i, j in sorted(cKDTree(xy).query_pairs(dist)):
        d_ij = float(np.hypot(*(xy[i] - xy[j])))
        overlap = d_ij < 0.5 * (diam[i] + diam[j])  # two real trunks cannot overlap
        if abs(diam[i] - diam[j]) > max_ddiam and not overlap:
            continue
        ri, rj = find(i), find(j)
        if ri == rj:
            continue
        if nobs[ri] >= nobs[rj]:
            parent[rj] = ri
        else:
            parent[ri] = rj
    return np.array([find(i) for i in range(n)], dtype=np.int64)


def _information_blocks(
    graph: Any, values: Any
) -> tuple[FloatArray, Any, Any, Callable[[FloatArray], FloatArray], np.ndarray, np.ndarray]:
    """The Gauss-Newton information ``H = AᵀA`` of GTSAM's whitened linearisation split into
    trees ``L`` and poses ``P``: ``(H_LL dense, H_PL sparse, H_PP COO, solve(H_PP, ·), tree
    keys, pose keys)`` (keys sorted, as the columns), see :func:`_point_marginals`."""
    import scipy.linalg as sla
    import scipy.sparse as sp

    ijs = graph.linearize(values).sparseJacobian_()  # 1-based (row, col, value); last col = b
    # columns follow the sorted keys (GTSAM's default ordering of sparseJacobian); GTSAM
    # Symbol keys hold their letter in the top byte: 'l' = Point2 (2), 'x' = Pose2 (3)
    all_keys = np.array(sorted(values.keys()), dtype=np.uint64)
    is_pt = (all_keys >> np.uint64(56)) == ord("l")
    dims = np.where(is_pt, 2, 3)
    start = np.concatenate(([0], np.cumsum(dims)))
    n_col = int(start[-1])
    cols = ijs[1].astype(np.int64) - 1
    # (GTSAM leaves out entries below 1e-12, of b too: at an exact fit there is no b column)
    if int(cols.max(initial=0)) > n_col:
        raise ValueError("unexpected variable layout in the linearised graph")
    a_mat = sp.csr_matrix(
        (ijs[2][cols < n_col], (ijs[0][cols < n_col].astype(np.int64) - 1, cols[cols < n_col])),
        shape=(int(ijs[0].max(initial=0)), n_col),
    )
    h = (a_mat.T @ a_mat).tocsr()
    col_of = [np.arange(start[i], start[i + 1]) for i in range(all_keys.size)]
    i_l = np.concatenate([col_of[i] for i in np.flatnonzero(is_pt)] or [np.zeros(0, int)])
    i_p = np.concatenate([col_of[i] for i in np.flatnonzero(~is_pt)] or [np.zeros(0, int)])
    h_ll = h[i_l][:, i_l].toarray()
    h_pl = h[i_p][:, i_l]
    h_pp = h[i_p][:, i_p].tocoo()
    w = 5
    solve: Callable[[FloatArray], FloatArray]
    if h_pp.nnz and int(np.abs(h_pp.row - h_pp.col).max()) <= w:
        ab = np.zeros((w + 1, i_p.size))
        up = h_pp.row <= h_pp.col
        ab[w + h_pp.row[up] - h_pp.col[up], h_pp.col[up]] = h_pp.data[up]
        ub = sla.cholesky_banded(ab)
        solve = lambda rhs: band_cho_solve(ub, rhs)  # noqa: E731
    else:
        from scipy.sparse.linalg import splu

        try:
            solve = splu(h_pp.tocsc()).solve
        except RuntimeError as exc:  # SuperLU: "Factor is exactly singular" (e.g. a bare key)
            raise np.linalg.LinAlgError(f"pose information is singular: {exc}") from exc
    return h_ll, h_pl, h_pp, solve, all_keys[is_pt], all_keys[~is_pt]


def _tree_schur(graph: Any, values: Any) -> tuple[FloatArray, np.ndarray]:
    """The trees' joint information ``S = H_LL - H_LP H_PP⁻¹ H_PL`` (dense, 2 rows per tree) and
    the tree keys in its order (sorted), see :func:`_point_marginals`."""
    s_mat, h_pl, _, solve, pt_keys, _ = _information_blocks(graph, values)
    # S = H_LL - H_LP H_PP⁻¹ H_PL, 128 tree columns at a time (a dense n_P x n_L right side
    # would add ~60 MB to the peak memory of the full run)
    for c0 in range(0, s_mat.shape[0], 128):
        h_c = h_pl[:, c0 : c0 + 128]
        s_mat[:, c0 : c0 + 128] -= h_pl.T @ solve(h_c.toarray())
    return s_mat, pt_keys


def _tree_and_pose_marginals(
    graph: Any, values: Any, tree_keys: list[int], pose_keys: list[int]
) -> tuple[FloatArray, FloatArray]:
    """:func:`_point_marginals` of ``tree_keys`` and the (m, 3, 3) marginal covariances of the
        Pose2 variables ``pose_keys`` (GTSAM's tangent: right perturbation, (x, y) in the pose's own
        frame), from one linearisation (ours).

        ``Σ_PP = (H_PP - H_PL H_LL⁻¹ H_LP)⁻¹ = H_PP⁻¹ + X S⁻¹ Xᵀ`` with ``X = H_PP⁻¹ H_PL`` and
        ``S`` the trees' Schur complement (the block-inverse identity): the diagonal blocks of
        ``H_PP⁻¹`` by the block RTS recursion of the pose chain
        (:func:`stemmap.slam._ekf_smooth.chain_marginals`), those of ``X S⁻¹ Xᵀ = (X U⁻¹)(X U⁻¹)ᵀ``
        from rows of ``X U⁻¹`` (``S = UᵀU``). ``X`` is held whole (n_P x n_L doubles: ~29 MB on the
    full Victoria Park run, which the tree-only path avoids by chunks). Needs the poses to
        form a chain (3x3 blocks, block-tridiagonal ``H_PP``, as :class:`Isam2Slam` builds it),
        GNSS antenna poses eliminated first (:func:`_chain_blocks`); otherwise ValueError.

        Raises ``numpy.linalg.LinAlgError`` when the information is not positive definite.
    """
    from stemmap.slam._ekf_smooth import chain_marginals

    h_ll, h_pl, h_pp, solve, pt_keys, ps_keys = _information_blocks(graph, values)
    blocks, off, cpos = _chain_blocks(h_pp, ps_keys)
    pp = np.searchsorted(ps_keys, np.array(pose_keys, dtype=np.uint64))
    if np.any(cpos[pp] < 0):
        raise ValueError("pose marginals asked for a pose outside the keyframe chain")
    pose_cov = chain_marginals(blocks, off)[cpos[pp]] if blocks.shape[0] else np.zeros((0, 3, 3))
    tree_cov = np.zeros((0, 2, 2))
    if h_pl.shape[1]:
        x_mat = solve(h_pl.toarray())
        s_mat = h_ll - h_pl.T @ x_mat
        u_inv = _inverse_factor(s_mat)
        tree_cov = _tree_blocks(u_inv, pt_keys, tree_keys)
        x3 = x_mat.reshape(ps_keys.size, 3, -1)
        for r0 in range(0, pp.size, 256):  # rows of X U⁻¹ in chunks (no second n_P x n_L)
            y = x3[pp[r0 : r0 + 256]] @ u_inv
            pose_cov[r0 : r0 + 256] += np.einsum("jak,jbk->jab", y, y)
    return (
        np.asarray(tree_cov, dtype=np.float64),
        np.asarray(0.5 * (pose_cov + pose_cov.transpose(0, 2, 1)), dtype=np.float64),
    )


def _chain_blocks(h_pp: Any, ps_keys: np.ndarray) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """The keyframe chain's block-tridiagonal information with the other Pose2 variables
    eliminated: ``(diagonal blocks, sub-diagonal blocks, chain position of each pose key or
    -1)`` (ours).

    Chain = the ``'x'`` keys (keyframe sensor poses), after the ``'w'`` keys of a continued
    earlier session (:mod:`stemmap.slam._graph_continue`; its own chain, no factor links the
    two, so the block between them is zero). Any other Pose2 variable must be a leaf
    tied to one keyframe (a GNSS fix's antenna pose ``Z(i)``: a between factor to its keyframe
    and a prior of its own, :mod:`stemmap.slam.gnss`); it is eliminated exactly by the Schur
    complement ``H_cc - H_cz H_zz⁻¹ H_zc``, which only adds to its keyframe's diagonal block,
    so the chain stays block-tridiagonal and the marginals of the keyframes are those of the
    whole graph. Any other structure: ValueError.
    """
    n_b = ps_keys.size
    sym = ps_keys >> np.uint64(56)
    leaf = (sym != np.uint64(ord("x"))) & (sym != np.uint64(ord("w")))
    cpos = np.full(n_b, -1, dtype=np.int64)
    cpos[~leaf] = np.arange(int((~leaf).sum()))
    n_c = int((~leaf).sum())
    r, c, v = h_pp.row, h_pp.col, h_pp.data
    rb, cb = r // 3, c // 3
    cc = ~leaf[rb] & ~leaf[cb]
    if np.any(np.abs(cpos[rb[cc]] - cpos[cb[cc]]) > 1) or np.any(leaf[rb] & leaf[cb] & (rb != cb)):
        raise ValueError("the poses do not form a chain: no pose marginals")
    blocks = np.zeros((n_c, 3, 3))
    off = np.zeros((max(n_c - 1, 0), 3, 3))
    on = cc & (rb == cb)
    blocks[cpos[rb[on]], r[on] % 3, c[on] % 3] = v[on]
    lo = cc & (cpos[rb] == cpos[cb] + 1)
    off[cpos[cb[lo]], r[lo] % 3, c[lo] % 3] = v[lo]
    if leaf.any():
        h_zz = np.zeros((n_b, 3, 3))
        zz = leaf[rb] & (rb == cb)
        h_zz[rb[zz], r[zz] % 3, c[zz] % 3] = v[zz]
        zc = leaf[rb] & ~leaf[cb]  # rows of a leaf, columns of its keyframe
        partner = np.full(n_b, -1, dtype=np.int64)
        partner[rb[zc]] = cb[zc]
        if np.any(partner[rb[zc]] != cb[zc]):
            raise ValueError("a non-keyframe pose is tied to two keyframes: no pose marginals")
        h_zc = np.zeros((n_b, 3, 3))
        h_zc[rb[zc], r[zc] % 3, c[zc] % 3] = v[zc]
        z = np.flatnonzero(leaf & (partner >= 0))
        corr = np.swapaxes(h_zc[z], 1, 2) @ np.linalg.solve(h_zz[z], h_zc[z])
        np.add.at(blocks, cpos[partner[z]], -corr)
    return blocks, off, cpos


def _point_marginals(graph: Any, values: Any, keys: list[int]) -> FloatArray:
    """(n, 2, 2) marginal covariances of the Point2 variables ``keys`` at ``values`` (ours).

    The same quantity as ``gtsam.Marginals(graph, values).marginalCovariance(key)``: the
    inverse of the Gauss-Newton information ``H = AᵀA`` of GTSAM's whitened linearisation
    (robust weights included), restricted to the trees ``L`` by the Schur complement over the
    poses ``P``: ``Σ_LL = (H_LL - H_LP H_PP⁻¹ H_PL)⁻¹`` (exact: the marginal of a Gaussian in
    information form is the Schur complement of the other block). The poses of :class:`Isam2Slam`
    form a chain (a prior and odometry between consecutive keyframes), so ``H_PP`` is banded
    (bandwidth 5 with the keyframes in key order): one banded Cholesky and a compiled solve
    with the ~800 tree columns as right sides; any other structure takes a sparse LU. The
    dense ``S⁻¹`` is only needed on its 2x2 diagonal blocks: ``S = UᵀU``, ``S⁻¹ = U⁻¹U⁻ᵀ``,
    the blocks are products of row pairs of ``U⁻¹``. Full Victoria Park run: ~0.25 s instead
    of ~0.5 s for GTSAM's joint marginals in chunks of 128 trees (which eliminate the whole
    graph once per chunk); the covariances agree to ~1e-10 relative (round-off).

    Raises ``numpy.linalg.LinAlgError`` when the information is not positive definite.
    """
    s_mat, pt_keys = _tree_schur(graph, values)
    return _tree_blocks(_inverse_factor(s_mat), pt_keys, keys)


def _inverse_factor(s_mat: FloatArray) -> FloatArray:
    """``U⁻¹`` of the Cholesky factor ``S = UᵀU`` (so ``S⁻¹ = U⁻¹U⁻ᵀ``); LinAlgError if ``S``
    is not positive definite."""
    from scipy.linalg import lapack

    u, info = lapack.dpotrf(s_mat, lower=0, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"tree information not positive definite (dpotrf {info})")
    u_inv, info = lapack.dtrtri(u, lower=0)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular tree information (dtrtri {info})")
    return np.asarray(u_inv, dtype=np.float64)


def _tree_blocks(u_inv: FloatArray, pt_keys: np.ndarray, keys: list[int]) -> FloatArray:
    """The 2x2 diagonal blocks of ``S⁻¹ = U⁻¹U⁻ᵀ`` of the tree ``keys``: products of row pairs
    of ``U⁻¹`` (rows of each key in the L block: points in sorted-key order)."""
    pos = np.searchsorted(pt_keys, np.array(keys, dtype=np.uint64))
    rows = u_inv.reshape(-1, 2, u_inv.shape[1])[pos]
    return np.asarray(np.einsum("jak,jbk->jab", rows, rows), dtype=np.float64)


def _fit_diagnostics(
    gtsam: Any,
    result: Any,
    odo_fac: list[Any],
    meas_fac: list[Any],
    meas_rec: list[tuple[int, int, float, float, float, float]],
    kf_pose: FloatArray,
    tree_xy: FloatArray,
) -> tuple[float, float, int]:
    """chi² of the odometry and of the measurement factors at the optimum ``result``, and the
    number of measurements whose normalised residual exceeds 3.

    chi² per degree of freedom is ~1 when the noise models match the data (robust factors
    report their robust cost); one C++ error sum per kind over the factors in graph order
    (equal to summing them one by one from Python, ~10x faster). Association quality without
    ground truth: a correctly associated (merged) detection has a bearing-range residual
    beyond 3 sigma with probability ~1 %. ``meas_rec`` rows are ``(keyframe, tree, bearing,
    range, sigma_b, sigma_r)``; ``kf_pose`` (nk, 3) the keyframes' sensor poses; ``tree_xy``
    the position of each row's tree slot (merged slots already mapped).
    """
    chi2_kind = []
    for facs in (odo_fac, meas_fac):
        g_kind = gtsam.NonlinearFactorGraph()
        for fac_i in facs:
            g_kind.add(fac_i)
        chi2_kind.append(2.0 * g_kind.error(result))
    n_outlier = 0
    if meas_rec and tree_xy.size:
        mr = np.array(meas_rec)
        kf_xyt = kf_pose[mr[:, 0].astype(np.int64)]
        lmp = tree_xy[mr[:, 1].astype(np.int64)]
        dxm, dym = lmp[:, 0] - kf_xyt[:, 0], lmp[:, 1] - kf_xyt[:, 1]
        rb = wrap_angle(mr[:, 2] - (np.arctan2(dym, dxm) - kf_xyt[:, 2])) / mr[:, 4]
        rr_ = (mr[:, 3] - np.hypot(dxm, dym)) / mr[:, 5]
        n_outlier = int(np.count_nonzero(rb * rb + rr_ * rr_ > 9.0))
    return chi2_kind[0], chi2_kind[1], n_outlier


def _tree_joint_information(graph: Any, values: Any, keys: list[int]) -> FloatArray:
    """(2n, 2n) joint information of the Point2 variables ``keys`` (in that order: x0, y0,
    x1, ...) at ``values``, every other variable (poses, the trees not in ``keys``)
    marginalised out: ``(Σ_KK)⁻¹`` with ``Σ = S⁻¹`` (:func:`_tree_schur`). Unlike the 2x2 blocks
    of :func:`_point_marginals` it keeps the correlations between trees (their relative
    positions are known much better than their absolute ones): the prior a later session
    continues from (:func:`stemmap.slam.relocalise.joint_prior_factor`).

    Raises ``numpy.linalg.LinAlgError`` when the information is not positive definite.
    """
    import scipy.linalg as sla

    s_mat, pt_keys = _tree_schur(graph, values)
    pos = np.searchsorted(pt_keys, np.array(keys, dtype=np.uint64))
    idx = np.stack((2 * pos, 2 * pos + 1), axis=1).reshape(-1)
    cov = sla.cho_solve(sla.cho_factor(s_mat), np.eye(s_mat.shape[0])[:, idx])[idx]
    cov = 0.5 * (cov + cov.T)
    return np.asarray(sla.cho_solve(sla.cho_factor(cov), np.eye(idx.size)), dtype=np.float64)


def final_marginals(
    graph: Any, values: Any, tree_keys: list[int], pose_keys: list[int], cfg: Any
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """The end-of-run covariances of :class:`~stemmap.slam.graph.Isam2Slam` (its ``cfg``):
    the trees' 2x2 marginals (``cfg.marginals``), the keyframes' 3x3 pose marginals
    (``cfg.pose_marginals``, both from one linearisation, :func:`_tree_and_pose_marginals`)
    and the trees' joint information (``cfg.joint_information``), NaN / None where not asked
    or not available (a warning says why: poses that are not a chain with leaves
    (:func:`_chain_blocks`), an indeterminant system)."""
    tree_cov = np.full((len(tree_keys), 2, 2), np.nan)
    pose_cov = np.full((len(pose_keys), 3, 3), np.nan)
    info_j = None
    want_trees = bool(cfg.marginals and tree_keys)
    if cfg.pose_marginals:
        try:
            t_c, pose_cov = _tree_and_pose_marginals(
                graph, values, tree_keys if want_trees else [], pose_keys
            )
            tree_cov = t_c if want_trees else tree_cov
        except ValueError as exc:  # expected with GNSS: said once, not a problem
            log.info("iSAM2: no pose covariances: %s", exc)
        except np.linalg.LinAlgError as exc:
            log.warning("iSAM2: pose covariances unavailable: %s", exc)
    if want_trees:
        try:
            if not np.isfinite(tree_cov).all():
                tree_cov = _point_marginals(graph, values, tree_keys)
            if cfg.joint_information:
                info_j = _tree_joint_information(graph, values, tree_keys)
        except np.linalg.LinAlgError as exc:  # indeterminant system: leave NaN, say why
            log.warning("iSAM2: marginal covariances unavailable: %s", exc)
    return tree_cov, pose_cov, info_j
