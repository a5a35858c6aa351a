"""First-order error covariance of the tree-map back-ends as they really run (issue 14; ours).

The tree DB (:class:`~stemmap.slam.treedb.TreeDbSlam`) and Forestrix
(:class:`~stemmap.slam.forestrix.ForestrixSlam`) are the same kind of estimator: each frame's
pose is corrected against trees the back-end mapped itself from earlier poses (the map taken as
known), and the frame's detections are then averaged into that map at the corrected pose. A
filter covariance of such an estimator is the pose's error *relative to the map* (centimetres),
while the map carries the error of the poses that mapped it: the pose drifts as the trees in
view are handed over to newly mapped ones. This module tracks the joint error covariance of the
pose, every live map tree and the last keyframe's pose under the gains the back-end actually
used -- the covariance analysis of a suboptimal filter (Gelb 1974, ch. 7 "Suboptimal filter
design and sensitivity analysis": the true error covariance is propagated with the filter's own
gains, not the ones an optimal filter would use). With ``δp`` the pose error, ``δm_e`` tree
``e``'s, ``w`` the odometry noise and ``v`` a detection's noise (range, bearing; covariance
``R``, the back-end's detection noise model), all linear to first order:

* prediction ``p ⊕ u``: ``δp ← F δp + w`` (``F`` the compose Jacobian, ``Cov w`` the
  preintegrated increment's covariance rotated to the map);
* localisation, in the linear form :data:`Localisation` ``δp ← L_p δp + L_m δm_matched +
  L_v v_matched``: the tree DB's pose-only EKF (gain ``K``, Jacobians ``H_x``, ``H_m``;
  :func:`ekf_localisation`: ``L_p = I - K H_x``, ``L_m = -K H_m``, ``L_v = K``), Forestrix's
  rigid fit of the matched echoes onto their trees (the fit's Jacobians,
  :func:`~stemmap.slam._tree_groups.pose_fit_jacobians`; ``L_p`` is zero to first order: the
  fit is equivariant, so the corrected pose is the map's and the detections' alone);
* mapping at the corrected pose (a running mean: eq. 2 of the visual-lidar paper, Forestrix's
  position update; a tree seen ``c`` times becomes ``(c m + x)/(c + 1)``; an unmatched
  detection a new tree ``x``) with ``δx = J_p δp + J_z v``: ``δm_e ← (c δm_e + δx)/(c + 1)``,
  or ``δm_new = δx``.

The same detection noise ``v`` enters the localisation and the mapping of that frame, so the
frame's ``v`` are carried as extra state rows for the two steps. Trees merged by the loop
closure or the duplicate rule become the count-weighted mean of their errors. Trees the
back-end can no longer match (not seen for ``LoopConfig.gap_s`` with recent-only localisation)
are dropped from the state; a later merge with one keeps the live tree's error.

The relaxation after a loop closure is not modelled in the forward recursion (a tree merged
with one already dropped keeps the live tree's error, so the loop's information is not in it).
It enters in :meth:`TreeMapErrors.pose_covariances`: the recorded covariances as a Gauss-Markov
chain over the relaxation's keyframes plus the relaxation's loop constraints, whose marginals
are the reported pose covariances. Without loops they are the forward analysis itself.

Checked against Monte Carlo (tests/slam/test_treedb.py, tests/slam/test_forestrix.py: drives
whose odometry and detection noise follow the back-end's models; tree DB pose NEES mean 3.1
against 3, the chain factor it replaced 4.5-5.0).

References
----------
.. [Gelb1974] A. Gelb (ed.), *Applied Optimal Estimation*, MIT Press 1974, ch. 7
   "Suboptimal filter design and sensitivity analysis".
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.relaxation import LoopClosure

IntArray = NDArray[np.int64]

_POSE = np.arange(3)
_CLONE = np.arange(3, 6)
_TWO = np.arange(2)
#: Sigmas (x, y in m, theta in rad) added to every conditional noise of the chain and used as
#: the start's prior, so the linear graph stays well posed where the analysis gives a
#: (near-)zero increment (at the fixed start): 1 mm / 0.001 deg, far below any measured one.
_FLOOR = np.array([1e-3, 1e-3, math.radians(1e-3)])


#: A frame's localisation as a linear map of the errors (module doc): ``L_p`` (3, 3) on the
#: predicted pose's, ``L_m`` (3, 2m) on the matched trees' (x, y pairs), ``L_v`` (3, 2m) on the
#: matched detections' (range, bearing) noise; the matched detections' indices in the frame
#: and their map trees (m,).
Localisation = tuple[FloatArray, FloatArray, FloatArray, IntArray, IntArray]


def ekf_localisation(
    K: FloatArray, Hx: FloatArray, Hm: FloatArray, kk: IntArray, ent: IntArray
) -> Localisation:
    """:data:`Localisation` of an EKF update ``p + K (z - h(p, m))`` with gain ``K`` (3, 2m)
    and Jacobians ``H_x`` (2m, 3), ``H_m`` (m, 2, 2): ``(I - K H_x, -K H_m, K)``."""
    Kb = K.reshape(3, -1, 2).transpose(1, 0, 2)  # (m, 3, 2) per matched detection
    Lm = -np.einsum("aij,ajk->iak", Kb, Hm).reshape(3, -1)
    return np.eye(3) - K @ Hx, Lm, K, kk, ent


class TreeMapErrors:
    """Joint error covariance of (pose, last keyframe's pose, live map trees); module doc.

    Parameters
    ----------
    n_frames : int
    detection_cov : ndarray (2, 2)
        Covariance of one detection's (range, bearing) noise, m² / rad².
    """

    def __init__(self, n_frames: int, detection_cov: FloatArray) -> None:
        self.R = np.asarray(detection_cov, dtype=np.float64).reshape(2, 2)
        self.S = np.zeros((64, 64))
        self.n = 6  # used rows: pose, clone, then slots
        self.slot = np.full(0, -1, dtype=np.int64)  # map tree -> state row (-1: none)
        self.free: list[int] = []
        self.abs_cov = np.zeros((n_frames, 3, 3))
        self.cross = np.zeros((n_frames, 3, 3))  # Cov(δp_f, δp of the keyframe before f)

    # ---------------------------------------------------------------- state bookkeeping
    def _grow(self, need: int) -> None:
        if need > self.S.shape[0]:
            cap = max(need, 2 * self.S.shape[0])
            S = np.zeros((cap, cap))
            S[: self.n, : self.n] = self.S[: self.n, : self.n]
            self.S = S

    def _new_pairs(self, k: int) -> IntArray:
        """First rows of ``k`` fresh zeroed row pairs (freed pairs first)."""
        take = [self.free.pop() for _ in range(min(k, len(self.free)))]
        extra = k - len(take)
        self._grow(self.n + 2 * extra)
        firsts = np.array(take + list(range(self.n, self.n + 2 * extra, 2)), dtype=np.int64)
        self.n += 2 * extra
        return firsts

    def _release(self, firsts: IntArray) -> None:
        rows = _pairs(firsts)
        self.S[rows, : self.n] = 0.0
        self.S[: self.n, rows] = 0.0
        self.free.extend(int(r) for r in firsts)

    def _entry_rows(self, entries: IntArray) -> IntArray:
        """State rows (2 per tree) of map trees that have a slot."""
        return _pairs(self.slot[entries])

    def _apply(
        self, rows: IntArray, cols: IntArray, M: FloatArray, noise: FloatArray | None = None
    ) -> None:
        """Replace the errors of ``rows`` by ``M @ (errors of cols) + n``, ``Cov n = noise``
        independent of the state (exact; O(len(rows) · used rows))."""
        n = self.n
        A = M @ self.S[cols, :n]
        Srr = A[:, cols] @ M.T
        if noise is not None:
            Srr = Srr + noise
        self.S[rows, :n] = A
        self.S[:n, rows] = A.T
        self.S[rows[:, None], rows] = 0.5 * (Srr + Srr.T)

    # ---------------------------------------------------------------- the back-end's steps
    def predict(self, F: FloatArray, Q: FloatArray) -> None:
        """``δp ← F δp + w``, ``Cov w = Q`` (map frame)."""
        self._apply(_POSE, _POSE, F, Q)

    def frame(
        self,
        pose: FloatArray,
        ranges: FloatArray,
        bearings: FloatArray,
        offset: tuple[float, float],
        loc: Localisation | None,
        entries: IntArray,
        counts_before: IntArray,
    ) -> None:
        """One frame's localisation (``loc``, :data:`Localisation`; None = no correction) and
        mapping of its detections at the corrected ``pose`` into map trees ``entries``
        (``counts_before``: each tree's count before the frame; 0 = a new tree), as one linear
        map of the state and the frame's detection noise ``v`` (which enters both steps)."""
        k = int(ranges.size)
        if self.slot.size < int(entries.max(initial=-1)) + 1:
            grown = np.full(int(entries.max()) + 1, -1, dtype=np.int64)
            grown[: self.slot.size] = self.slot
            self.slot = grown
        if k == 0:
            return
        old = (counts_before > 0) & (self.slot[entries] >= 0)
        new_e = entries[~old]
        self.slot[new_e] = self._new_pairs(new_e.size)
        orows = self._entry_rows(entries[old])
        mrows = np.zeros(0, dtype=np.int64)
        if loc is not None:
            Lp, Lm, Lv, kk, ent = loc
            have = self.slot[ent] >= 0
            mrows = self._entry_rows(ent[have])
        cols = np.unique(np.concatenate((_POSE, mrows, orows)))
        # localisation: δp' = L_p δp + L_m δm_matched + L_v v_matched  (rows 0-2 of Ms, Mv)
        Ms = np.zeros((3 + 2 * k, cols.size))
        Mv = np.zeros((3 + 2 * k, 2 * k))
        Ms[:3, :3] = np.eye(3)  # cols starts with the pose rows 0-2
        if loc is not None:
            Ms[:3, :3] = Lp
            if have.any():
                Ms[:3, np.searchsorted(cols, mrows)] += Lm[:, _pairs(2 * np.flatnonzero(have))]
            Mv[:3, _pairs(2 * kk)] = Lv
        # mapping at the corrected pose: δm' = w (J_p δp' + J_z v) + (1 - w) δm
        c, s = math.cos(pose[2]), math.sin(pose[2])
        sx = pose[0] + offset[0] * c - offset[1] * s
        sy = pose[1] + offset[0] * s + offset[1] * c
        ang = pose[2] + bearings
        ca, sa = np.cos(ang), np.sin(ang)
        w = 1.0 / (counts_before + 1.0)
        JP = np.zeros((2 * k, 3))
        rx, ry = np.arange(0, 2 * k, 2), np.arange(1, 2 * k, 2)  # x, y row of each detection
        JP[rx, 0] = JP[ry, 1] = w
        JP[rx, 2] = -w * (sy + ranges * sa - pose[1])
        JP[ry, 2] = w * (sx + ranges * ca - pose[0])
        Ms[3:] = JP @ Ms[:3]
        Mv[3:] = JP @ Mv[:3]
        Mv[3 + rx, rx] += w * ca  # J_z: d (x, y) / d (range, bearing)
        Mv[3 + rx, ry] -= w * ranges * sa
        Mv[3 + ry, rx] += w * sa
        Mv[3 + ry, ry] += w * ranges * ca
        io = np.flatnonzero(old)  # (1 - w) of the entry's own previous error
        jc = np.searchsorted(cols, orows[0::2])
        Ms[3 + 2 * io, jc] += 1.0 - w[io]
        Ms[4 + 2 * io, jc + 1] += 1.0 - w[io]
        Mv3 = Mv.reshape(Mv.shape[0], k, 2)
        noise = np.einsum("rka,ab,skb->rs", Mv3, self.R, Mv3)
        rows = np.concatenate((_POSE, self._entry_rows(entries)))
        self._apply(rows, cols, Ms, noise)

    def merge(self, src: IntArray, dst: IntArray, counts: IntArray) -> None:
        """Entries ``src`` merged into ``dst``: ``δm_dst ← (c_s δm_s + c_d δm_d) / (c_s + c_d)``."""
        n = self.slot.size
        for a, b in zip(np.asarray(src).tolist(), np.asarray(dst).tolist(), strict=True):
            if a >= n or b >= n:
                continue
            ra, rb = int(self.slot[a]), int(self.slot[b])
            if ra >= 0 and rb >= 0:
                ca, cb = float(counts[a]), float(counts[b])
                t = ca / max(ca + cb, 1.0)
                M = np.hstack(((1 - t) * np.eye(2), t * np.eye(2)))
                rows = np.array([rb, rb + 1])
                self._apply(rows, np.array([rb, rb + 1, ra, ra + 1]), M)
            elif ra >= 0:
                self.slot[b] = ra
                ra = -1
            if ra >= 0:
                self._release(np.array([ra]))
            self.slot[a] = -1

    def drop(self, entries: IntArray) -> None:
        """Forget trees the back-end can no longer match."""
        e = entries[entries < self.slot.size]
        e = e[self.slot[e] >= 0]
        if e.size:
            self._release(self.slot[e])
            self.slot[e] = -1

    # ---------------------------------------------------------------- outputs
    def record(self, f: int, keyframe: bool) -> None:
        """Store frame ``f``'s error covariance and its cross-covariance with the last keyframe
        before it; ``keyframe``: ``f`` becomes the reference of the frames after it."""
        self.abs_cov[f] = self.S[:3, :3]
        self.cross[f] = self.S[:3, 3:6]
        if keyframe:
            self.promote(f)

    def promote(self, f: int) -> None:
        """Frame ``f`` (recorded) is a keyframe: the reference of the frames after it."""
        self._apply(_CLONE, _POSE, np.eye(3))

    def pose_covariances(
        self, poses: FloatArray, keyframes: list[int], loops: list[LoopClosure], robust_k: float
    ) -> FloatArray:
        """(F, 3, 3) pose covariances after the relaxation's loop constraints (module doc).

        The analysis gives each frame's error covariance ``Σ_f`` and its cross-covariance
        ``Σ_fa`` with the keyframe ``a`` before it. As a Gauss-Markov chain over the keyframes
        (``δ_b = A δ_a + w``, ``A = Σ_ba Σ_a⁻¹``, ``Cov w = Σ_b - A Σ_ab``: the linear
        regression of one keyframe's error on the previous one's, exact for the marginals and
        the lag-one covariances) plus one linear constraint per loop closure -- the relative
        pose's right-perturbation error ``ξ_b - Ad(d⁻¹) ξ_a`` in map-frame errors, its sigmas
        and the Cauchy weight of its residual at ``poses``, as in the relaxation -- the
        marginals (``gtsam.Marginals`` of the linear graph) are the covariances after the
        relaxation. Without loops they are the analysis' own ``Σ_f``. A frame between
        keyframes follows its keyframe the same way: ``A_f C_a A_fᵀ + W_f``.
        """
        import gtsam

        from stemmap.slam.relaxation import loop_measurements

        p = np.asarray(poses, dtype=np.float64)
        nf = p.shape[0]
        kf = np.asarray(keyframes, dtype=np.int64)
        ref = kf[np.maximum(np.searchsorted(kf, np.arange(nf), side="left") - 1, 0)]
        A = self.cross @ _pinv(self.abs_cov[ref])
        W = self.abs_cov - A @ np.swapaxes(self.cross, 1, 2)
        W = 0.5 * (W + np.swapaxes(W, 1, 2)) + np.diag(_FLOOR**2)
        g = gtsam.GaussianFactorGraph()
        z3 = np.zeros(3)
        unit = gtsam.noiseModel.Unit.Create(3)
        g.add(gtsam.JacobianFactor(0, np.eye(3), z3, gtsam.noiseModel.Diagonal.Sigmas(_FLOOR)))
        for k in range(1, kf.size):
            f = int(kf[k])
            Li = np.linalg.inv(np.linalg.cholesky(W[f]))  # whitened: JacobianFactor's models
            g.add(gtsam.JacobianFactor(k - 1, -Li @ A[f], k, Li, z3, unit))
        for a, b, meas, lc in loop_measurements(p, kf, loops):
            La, Lb = _between_jacobians(p[kf[a]], p[kf[b]])
            sig = np.asarray(lc.sigmas, dtype=np.float64)
            r = _between_residual(p[kf[a]], p[kf[b]], meas) / sig
            w = 1.0 / (1.0 + float(r @ r) / robust_k**2)  # Cauchy weight at the solution
            nm = gtsam.noiseModel.Diagonal.Sigmas(sig / math.sqrt(w))
            g.add(gtsam.JacobianFactor(a, La, b, Lb, z3, nm))
        vals = gtsam.VectorValues()
        for k in range(kf.size):
            vals.insert(k, z3)
        marg = gtsam.Marginals(g, vals)
        C = np.array([marg.marginalCovariance(k) for k in range(kf.size)])
        owner = np.searchsorted(kf, np.arange(nf), side="right") - 1
        out = A @ C[owner] @ np.swapaxes(A, 1, 2) + W
        out[kf] = C
        return np.asarray(0.5 * (out + np.swapaxes(out, 1, 2)), dtype=np.float64)


def _pinv(C: FloatArray) -> FloatArray:
    """Pseudo-inverse of symmetric (n, 3, 3) blocks (the start's covariance is zero)."""
    return np.asarray(np.linalg.pinv(C, rcond=1e-12, hermitian=True), dtype=np.float64)


def _between_jacobians(pa: FloatArray, pb: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``d ε / d δp_a``, ``d ε / d δp_b``: the right-perturbation error of ``pa⁻¹ ⊕ pb`` as a
    function of map-frame pose errors (``δt``, ``δθ``): ``ε_xy = R_bᵀ (δt_b - δt_a - J (t_b -
    t_a) δθ_a)``, ``ε_θ = δθ_b - δθ_a``."""
    Rb = _rot(pb[2]).T
    d = pb[:2] - pa[:2]
    La = np.zeros((3, 3))
    La[:2, :2] = -Rb
    La[:2, 2] = -Rb @ np.array([-d[1], d[0]])
    La[2, 2] = -1.0
    Lb = np.eye(3)
    Lb[:2, :2] = Rb
    return La, Lb


def _between_residual(pa: FloatArray, pb: FloatArray, meas: FloatArray) -> FloatArray:
    """The loop constraint's residual at the solution (local frame of ``pb``)."""
    from stemmap.slam.motion import between

    e = between(np.asarray(meas, dtype=np.float64), between(pa, pb))
    return np.asarray(e, dtype=np.float64).reshape(3)


def _rot(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def _pairs(firsts: IntArray) -> IntArray:
    """Rows ``f, f + 1`` of each pair start ``f``, interleaved."""
    f = np.asarray(firsts, dtype=np.int64).reshape(-1, 1)
    return (f + _TWO).reshape(-1)
