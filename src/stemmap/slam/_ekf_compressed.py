"""Compressed EKF-SLAM: exact full-EKF results at the cost of a local submap.

Guivant & Nebot, "Optimization of the simultaneous localization and map-building algorithm for
real-time implementation", IEEE T-RA 17(3), 2001, §IV. The state is split into an *active* part
``A`` (vehicle + landmarks near it) and the rest ``B``. While only ``A`` is predicted, observed
and augmented, the full covariance stays the exact function

    P_AB(k) = Φ(k) P_AB(0)                                   (eq. 23 of the paper)
    P_BB(k) = P_BB(0) - P_BA(0) Ψ(k) P_AB(0)                 (eq. 24)
    x_B(k)  = x_B(0) + P_BA(0) θ(k)                          (eq. 25)

of the values ``(0)`` at the start of the local period, with the recursions

    predict    Φ ← F_A Φ                        (Ψ, θ unchanged)
    update     G = L⁻¹ H_A Φ,  Φ ← Φ - W G,  Ψ ← Ψ + Gᵀ G,  θ ← θ + Gᵀ L⁻¹ ν
    augment    new rows of Φ: G_x Φ_v           (a landmark started from the vehicle pose)

in the Cholesky form of :mod:`stemmap.slam.ekf` (``S = L Lᵀ``, ``W = P_AA H_Aᵀ L⁻ᵀ``). Each
step costs O(n_A²) instead of O(n²); leaving the local area (see below) applies the three
equations once ("full update", O(n_B n_A (n_A + r)) with ``Ψ`` kept as the stacked ``G``). The
result equals the full EKF to round-off (tested in ``tests/slam/test_ekf.py``).

When is ``B`` needed? The full EKF gates every landmark within ``search_radius``. A ``B``
landmark can change the outcome of a frame only if some detection's ``d²`` to it is at most
``max(gate, new_landmark_chi2)`` (a larger ``d²`` is neither branched on by JCBB/NN nor decides
the new-landmark test). That ``d²`` is bounded from below without ``P_BB(k)``:
``S_j ≼ 2 J_v P_vv J_vᵀ + 2 J_l P_jj(0) J_lᵀ`` (``Cov(a + b) ≼ 2 Cov(a) + 2 Cov(b)``, and
``P_jj(k) ≼ P_jj(0)`` because updates only subtract), with the exact ``x_B(k)`` from eq. 25.
Only when that bound lets a ``B`` landmark through -- the vehicle has left its local area -- is
the full update applied and a new active set chosen (landmarks within ``local_radius`` of the
sensor plus the ones that triggered it). So the choice of ``local_radius`` changes the run
time, never the result.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dtrtri

from stemmap.slam._ekf_algebra import (
    _blocks,
    _stack_jacobian,
    augment_landmark_covariance,
    block_diag_noise,
    grow_buffers,
)
from stemmap.slam._ekf_merge import close_pairs, decide_merges, inv2_quad
from stemmap.slam._ekf_smooth import ObservationLog, smooth_path
from stemmap.slam._ekf_stream import FrameInputs
from stemmap.slam.association import chi2_gate, jcbb, nearest_neighbour
from stemmap.slam.base import IntArray, SlamProblem, SlamResult, frame_trajectory
from stemmap.slam.motion import preintegrate_spans
from stemmap.slam.residual_noise import residual_noise_stats
from stemmap.types import FloatArray, StemMap, Tree

if TYPE_CHECKING:
    from stemmap.slam.ekf import EkfConfig


class _Compressed:
    """Global state at the last full update plus the active submap and its auxiliaries."""

    def __init__(self, x0: FloatArray) -> None:
        # global (full) state in landmark-id order of the alive landmarks, valid at sync
        self.Pg = np.zeros((3, 3))
        self.xg = np.array(x0, dtype=np.float64)
        self.g_ids = np.zeros(0, dtype=np.int64)
        self.n_sync = 0
        self._start(np.zeros(0, dtype=np.int64))

    # ------------------------------------------------------------------ local period
    def _start(self, a_ids: IntArray) -> None:
        """Begin a local period with active landmarks ``a_ids`` (ids, any order)."""
        pos = {int(i): t for t, i in enumerate(self.g_ids)}
        sel = np.array(sorted(pos[int(i)] for i in a_ids), dtype=np.int64)
        isA = np.zeros(self.g_ids.size, dtype=bool)
        isA[sel] = True
        self.a_ids = self.g_ids[isA].copy()
        self.b_ids = self.g_ids[~isA].copy()
        la = np.flatnonzero(isA)
        lb = np.flatnonzero(~isA)
        self.a0_rows = np.concatenate(([0, 1, 2], np.stack((3 + 2 * la, 4 + 2 * la), 1).ravel()))
        self.b_rows = np.stack((3 + 2 * lb, 4 + 2 * lb), 1).ravel().astype(np.int64)
        na0 = self.a0_rows.size
        self.na0 = na0
        self.nA = na0
        cap = na0 + 64
        self.PA = np.zeros((cap, cap))
        self.PA[:na0, :na0] = self.Pg[np.ix_(self.a0_rows, self.a0_rows)]
        self.xA = np.zeros(cap)
        self.xA[:na0] = self.xg[self.a0_rows]
        self.Phi = np.zeros((cap, na0))
        self.Phi[:na0] = np.eye(na0)
        self.theta = np.zeros(na0)
        # Ψ = Gᵀ G with the rows of every update's G stacked (folded by QR when long)
        self.Gb = np.zeros((max(64, na0), na0))
        self.r_rows = 0
        # B quantities frozen at the start of the period
        self.U = self.Pg[np.ix_(self.b_rows, self.a0_rows)]  # P_BA(0), (2 nB, nA0)
        self.xB0 = self.xg[self.b_rows].reshape(-1, 2)
        bp = self.Pg[np.ix_(self.b_rows, self.b_rows)] if lb.size else np.zeros((0, 0))
        nb = lb.size
        self.PBd0 = np.empty((nb, 2, 2))
        if nb:
            i = np.arange(nb)
            self.PBd0[:, 0, 0] = bp[2 * i, 2 * i]
            self.PBd0[:, 0, 1] = bp[2 * i, 2 * i + 1]
            self.PBd0[:, 1, 0] = bp[2 * i + 1, 2 * i]
            self.PBd0[:, 1, 1] = bp[2 * i + 1, 2 * i + 1]
        self.PBB0 = bp
        self._xB: FloatArray | None = self.xB0
        self.b_alive = np.ones(nb, dtype=bool)

    def _reserve(self, extra: int) -> None:
        grown = grow_buffers(self.nA, self.nA + extra, self.PA, self.xA, self.Phi)
        if grown is not None:
            self.PA, self.xA, self.Phi = grown

    def sync(self, new_a_ids: IntArray | None) -> None:
        """Full update (eqs. 23-25), drop pruned landmarks, start a new period with
        ``new_a_ids`` active (None: keep the global state only, at the end of a run)."""
        nA = self.nA
        alive = np.flatnonzero(self.b_alive)
        brow = np.stack((2 * alive, 2 * alive + 1), 1).ravel()
        U = self.U[brow]
        if self.theta.any():
            xB = self.xB0.reshape(-1)[brow] + U @ self.theta
        else:
            xB = self.xB0.reshape(-1)[brow].copy()
        PAB = self.Phi[:nA] @ U.T
        PBB = self.PBB0[np.ix_(brow, brow)]
        if self.r_rows:
            V = U @ self.Gb[: self.r_rows].T
            PBB -= V @ V.T
        ids = np.concatenate((self.a_ids, self.b_ids[alive]))
        order = np.argsort(ids, kind="stable")
        self.g_ids = ids[order]
        rank = np.empty(ids.size, dtype=np.int64)
        rank[order] = np.arange(ids.size)
        na = self.a_ids.size
        ra, rb = rank[:na], rank[na:]
        posA = np.concatenate(([0, 1, 2], np.stack((3 + 2 * ra, 4 + 2 * ra), 1).ravel()))
        posB = np.stack((3 + 2 * rb, 4 + 2 * rb), 1).ravel().astype(np.int64)
        n = 3 + 2 * ids.size
        P = np.empty((n, n))
        P[np.ix_(posA, posA)] = self.PA[:nA, :nA]
        if posB.size:
            P[np.ix_(posA, posB)] = PAB
            P[np.ix_(posB, posA)] = PAB.T
            P[np.ix_(posB, posB)] = PBB
        x = np.empty(n)
        x[posA] = self.xA[:nA]
        x[posB] = xB
        self.Pg, self.xg = P, x
        self.n_sync += 1
        if new_a_ids is not None:
            self._start(new_a_ids)

    # ------------------------------------------------------------------ queries
    @property
    def pose(self) -> FloatArray:
        return self.xA[:3]

    def a_xy(self) -> FloatArray:
        return self.xA[3 : self.nA].reshape(-1, 2)

    def b_xy_near(self, px: float, py: float, radius: float) -> tuple[IntArray, FloatArray]:
        """Alive B landmarks whose *current* position (eq. 25) is within ``radius`` of (px, py):
        (local B indices, their xy)."""
        if not self.b_alive.size:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        if self._xB is None:  # x_B(k) = x_B(0) + P_BA(0) θ, once per change of θ
            self._xB = self.xB0 + (self.U @ self.theta).reshape(-1, 2)
        xy = self._xB
        dx, dy = xy[:, 0] - px, xy[:, 1] - py
        near = np.flatnonzero(self.b_alive & (dx * dx + dy * dy < radius * radius))
        return near, xy[near]

    def b_cov(self, loc: IntArray) -> tuple[FloatArray, FloatArray]:
        """Current ``P_vj`` (f, 3, 2) and ``P_jj`` (f, 2, 2) of passive landmarks ``loc``
        (eqs. 23-24 for a few rows: O(f n_A0 r))."""
        f = loc.size
        rows = np.stack((2 * loc, 2 * loc + 1), 1).ravel()
        Uf = self.U[rows]
        Pvj = (self.Phi[:3] @ Uf.T).reshape(3, f, 2).transpose(1, 0, 2)
        Pjj = self.PBd0[loc].copy()
        if self.r_rows:
            V = (Uf @ self.Gb[: self.r_rows].T).reshape(f, 2, -1)
            Pjj -= V @ V.transpose(0, 2, 1)
        return Pvj, Pjj

    # ------------------------------------------------------------------ filter steps
    def predict(self, d: FloatArray, cov: FloatArray) -> None:
        th = self.xA[2]
        c, s = math.cos(th), math.sin(th)
        dxw = c * d[0] - s * d[1]
        dyw = s * d[0] + c * d[1]
        self.xA[0] += dxw
        self.xA[1] += dyw
        self.xA[2] = (th + d[2] + math.pi) % (2 * math.pi) - math.pi
        F = np.array([[1.0, 0.0, -dyw], [0.0, 1.0, dxw], [0.0, 0.0, 1.0]])
        Rw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        Q = Rw @ cov @ Rw.T
        n = self.nA
        P = self.PA
        P[:3, :3] = F @ P[:3, :3] @ F.T + Q
        if n > 3:
            P[:3, 3:n] = F @ P[:3, 3:n]
            P[3:n, :3] = P[:3, 3:n].T
        self.Phi[:3] = F @ self.Phi[:3]

    def update(self, cols: IntArray, Hn: FloatArray, v: FloatArray, R: FloatArray) -> float:
        """Joint update of the active state (columns ``cols`` of ``P_AA``); returns the NIS."""
        n = self.nA
        PHt = self.PA[:n, cols] @ Hn.T
        S = Hn @ PHt[cols] + R
        Lc = np.linalg.cholesky(0.5 * (S + S.T))
        # L⁻¹ of the small (2m x 2m) factor once; then W = P Hᵀ L⁻ᵀ etc. are plain products
        Li, info = dtrtri(Lc, lower=1)
        if info != 0:  # pragma: no cover - Cholesky factor of a PD matrix is invertible
            raise np.linalg.LinAlgError("singular innovation covariance")
        W = PHt @ Li.T
        wv = Li @ v
        G = Li @ (Hn @ self.Phi[cols])
        self.xA[:n] += W @ wv
        self.xA[2] = (self.xA[2] + math.pi) % (2 * math.pi) - math.pi
        self.PA[:n, :n] -= W @ W.T
        self.Phi[:n] -= W @ G
        r0, r1 = self.r_rows, self.r_rows + G.shape[0]
        if r1 > self.Gb.shape[0]:
            if r0 > self.na0:
                # keep Ψ = Σ GᵀG as one triangular factor (same product, fewer rows)
                Rq: FloatArray = np.linalg.qr(self.Gb[:r0], mode="r")  # type: ignore[assignment]
                r0, r1 = Rq.shape[0], Rq.shape[0] + G.shape[0]
                self.Gb[:r0] = Rq
            if r1 > self.Gb.shape[0]:
                Gb = np.zeros((2 * r1, self.na0))
                Gb[:r0] = self.Gb[:r0]
                self.Gb = Gb
        self.Gb[r0:r1] = G
        self.r_rows = r1
        self.theta += G.T @ wv
        self._xB = None
        return float(wv @ wv)

    def all_xy(self) -> tuple[IntArray, FloatArray]:
        """(ids, current xy) of every alive landmark: active ones first, in ``a_ids`` order."""
        loc, bxy = self.b_xy_near(0.0, 0.0, math.inf)
        return np.concatenate((self.a_ids, self.b_ids[loc])), np.vstack((self.a_xy(), bxy))

    def fuse(self, ri: int, rj: int) -> None:
        """Constraint ``m_i - m_j = 0`` between the active landmarks at rows ``ri``, ``rj``
        (a noise-free pseudo-measurement; a 1 mm sigma keeps the Cholesky factor regular)."""
        cols = np.array([ri, ri + 1, rj, rj + 1])
        Hn = np.array([[1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, -1.0]])
        v = -(self.xA[[ri, ri + 1]] - self.xA[[rj, rj + 1]])
        self.update(cols, Hn, v, np.eye(2) * 1e-6)

    def add_landmark(
        self, lm_id: int, mx: float, my: float, rng_: float, ang: float, R1: FloatArray,
        a: float, b: float,
    ) -> None:  # fmt: skip
        """Augment the active state (same Jacobians as ``EkfSlam._add_landmark``)."""
        self._reserve(2)
        n = self.nA
        Gx = augment_landmark_covariance(self.PA, n, float(self.xA[2]), a, b, rng_, ang, R1)
        self.Phi[n : n + 2] = Gx @ self.Phi[:3]
        self.xA[n], self.xA[n + 1] = mx, my
        self.nA = n + 2
        self.a_ids = np.append(self.a_ids, lm_id)

    def remove(self, ids: IntArray) -> None:
        """Marginalise landmarks out: active ones leave ``P_AA``/``Φ``; passive ones are only
        flagged (dropping rows of a Gaussian is exact, the full update drops them later)."""
        dead = {int(i) for i in ids}
        keep_a = np.array([int(i) not in dead for i in self.a_ids], dtype=bool)
        if not keep_a.all():
            la = np.flatnonzero(keep_a)
            idx = np.concatenate(([0, 1, 2], np.stack((3 + 2 * la, 4 + 2 * la), 1).ravel()))
            m = idx.size
            self.PA[:m, :m] = self.PA[np.ix_(idx, idx)]
            self.xA[:m] = self.xA[idx]
            self.Phi[:m] = self.Phi[idx]
            self.nA = m
            self.a_ids = self.a_ids[keep_a]
        if self.b_ids.size:
            self.b_alive &= ~np.isin(self.b_ids, ids)


def run_compressed(
    cfg: EkfConfig,
    problem: SlamProblem,
    progress: Callable[[int, int], None] | None,
    name: str,
) -> SlamResult:
    """The per-frame loop of :class:`stemmap.slam.ekf.EkfSlam` on the compressed state.

    Same steps and rules as the full filter (predict, gate within ``search_radius``, JCBB/NN
    with the diameter cue, joint update, new landmarks, pruning); only the state algebra is
    split as in the module docstring. The joint predicted-measurement covariance handed to
    JCBB is built over the individually compatible candidates only (JCBB never looks at the
    others), which is also what makes the gating O(candidates) instead of O(candidates³).
    """
    t_start = time.perf_counter()
    frames = problem.frames
    nf = len(frames)
    a, b = problem.sensor_offset
    pre = preintegrate_spans(problem.motion, problem.controls, frames.times, problem.initial_pose)
    inputs = FrameInputs(pre.deltas, pre.covs)  # (on disk beyond a few thousand frames)
    del pre
    odometry = inputs.odometry()
    R1 = np.diag([cfg.sigma_range**2, cfg.sigma_bearing**2])
    use_d = cfg.sigma_diameter is not None
    sd2 = (cfg.sigma_diameter or 1.0) ** 2
    gate_ind = chi2_gate(cfg.gate_alpha, 3 if use_d else 2)
    thr_relevant = max(gate_ind, cfg.new_landmark_chi2)
    R2 = cfg.search_radius**2
    st = _Compressed(np.asarray(problem.initial_pose, dtype=np.float64))

    # per-landmark bookkeeping, indexed by landmark id (creation order)
    # (a landmark is started from a detection, so there are at most n_detections ids)
    cap = frames.n_detections + 1
    d_sum = np.zeros(cap)
    d_sq = np.zeros(cap)
    d_n = np.zeros(cap, dtype=np.int64)
    nobs = np.zeros(cap, dtype=np.int64)
    first = np.zeros(cap, dtype=np.int64)
    last = np.zeros(cap, dtype=np.int64)
    alive = np.zeros(cap, dtype=bool)
    n_ids = 0
    n_matched = n_new = n_pruned = n_ambiguous = 0
    nis_sum, nis_dof = 0.0, 0
    n_sync_moved = 0
    n_merged = n_fused = 0
    coseen: set[tuple[int, int]] = set()  # landmark pairs matched in one scan
    olog = ObservationLog() if cfg.smooth else None

    def sensor() -> tuple[float, float, float, float, float, float, float]:
        x, y, th = st.xA[0], st.xA[1], st.xA[2]
        c, s = math.cos(th), math.sin(th)
        return x + a * c - b * s, y + a * s + b * c, th, -a * s - b * c, a * c - b * s, c, s

    def jac(xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Range-bearing Jacobians of landmarks ``xy`` (c, 2) at the current pose:
        ``Jv`` (c, 2, 3), ``Jl`` (c, 2, 2), predicted range and bearing."""
        sx, sy, th, dsx, dsy, _c, _s = sensor()
        ex, ey = xy[:, 0] - sx, xy[:, 1] - sy
        q = ex * ex + ey * ey
        rr = np.sqrt(q)
        hb = np.arctan2(ey, ex) - th
        Jv = np.empty((xy.shape[0], 2, 3))
        Jv[:, 0, 0], Jv[:, 0, 1] = -ex / rr, -ey / rr
        Jv[:, 0, 2] = -(ex * dsx + ey * dsy) / rr
        Jv[:, 1, 0], Jv[:, 1, 1] = ey / q, -ex / q
        Jv[:, 1, 2] = (-ex * dsy + ey * dsx) / q - 1.0
        Jl = np.empty((xy.shape[0], 2, 2))
        Jl[:, 0, 0], Jl[:, 0, 1] = ex / rr, ey / rr
        Jl[:, 1, 0], Jl[:, 1, 1] = -ey / q, ex / q
        return Jv, Jl, rr, hb

    def innovations(r: FloatArray, bear: FloatArray, rr: FloatArray, hb: FloatArray) -> FloatArray:
        nu = np.empty((r.size, rr.size, 2))
        nu[:, :, 0] = r[:, None] - rr[None, :]
        nu[:, :, 1] = (bear[:, None] - hb[None, :] + math.pi) % (2 * math.pi) - math.pi
        return nu

    def diameter_d2(diam: FloatArray, ids: IntArray) -> FloatArray | None:
        """The diameter cue ``(d_obs - d_lm)² / (σ² + σ²/n)`` (0 where undefined)."""
        if not use_d:
            return None
        cn = d_n[ids]
        with np.errstate(invalid="ignore", divide="ignore"):
            dd = diam[:, None] - (d_sum[ids] / cn)[None, :]
            extra = dd * dd / (sd2 + (sd2 / cn)[None, :])
        out: FloatArray = np.where(np.isfinite(extra), extra, 0.0)
        return out

    def may_gate(
        r: FloatArray, bear: FloatArray, xy: FloatArray, Pjj: FloatArray
    ) -> NDArray[np.bool_]:
        """Per landmark (xy, covariance bound Pjj): True if a detection's d² to it may be
        <= max(gate, new-landmark threshold) (lower bound of d², module docstring)."""
        Jv, Jl, rr, hb = jac(xy)
        T = 2.0 * (Jv @ st.PA[:3, :3] @ Jv.transpose(0, 2, 1))
        T += 2.0 * (Jl @ Pjj @ Jl.transpose(0, 2, 1))
        T += R1
        nu = innovations(r, bear, rr, hb)
        lb = inv2_quad(T[None], nu[..., 0], nu[..., 1])
        return np.asarray((lb <= thr_relevant).any(axis=0), dtype=bool)

    def passive_d2(r: FloatArray, bear: FloatArray, diam: FloatArray) -> FloatArray | None:
        """Exact d² (k, f) of the detections to the passive landmarks within the search radius
        that pass the cheap bound (None if none do)."""
        sx, sy = sensor()[:2]
        loc, xy = st.b_xy_near(sx, sy, cfg.search_radius)
        if not loc.size:
            return None
        flag = may_gate(r, bear, xy, st.PBd0[loc])
        if not flag.any():
            return None
        loc, xy = loc[flag], xy[flag]
        Pvj, Pjj = st.b_cov(loc)
        Jv, Jl, rr, hb = jac(xy)
        JlT = Jl.transpose(0, 2, 1)
        X = Jv @ Pvj @ JlT
        S = Jv @ st.PA[:3, :3] @ Jv.transpose(0, 2, 1)
        S += X + X.transpose(0, 2, 1)
        S += Jl @ Pjj @ JlT
        nu = innovations(r, bear, rr, hb)
        d2 = inv2_quad(S[None] + R1, nu[..., 0], nu[..., 1])
        extra = diameter_d2(diam, st.b_ids[loc])
        return d2 if extra is None else d2 + extra

    center = np.array(sensor()[:2])

    def resync(r: FloatArray, bear: FloatArray, extra_ids: IntArray | None = None) -> None:
        """Full update; the new active set is every landmark within ``local_radius`` plus every
        one within the search radius that may gate with this frame's detections (plus
        ``extra_ids``)."""
        sx, sy = sensor()[:2]
        center[:] = (sx, sy)
        st.sync(None)
        L = st.xg[3:].reshape(-1, 2)
        d2s = (L[:, 0] - sx) ** 2 + (L[:, 1] - sy) ** 2
        act = d2s < cfg.local_radius**2
        far = np.flatnonzero(~act & (d2s < R2))
        if far.size and r.size:
            rows = 3 + 2 * far
            Pjj = np.empty((far.size, 2, 2))
            Pjj[:, 0, 0] = st.Pg[rows, rows]
            Pjj[:, 0, 1] = st.Pg[rows, rows + 1]
            Pjj[:, 1, 0] = st.Pg[rows + 1, rows]
            Pjj[:, 1, 1] = st.Pg[rows + 1, rows + 1]
            act[far[may_gate(r, bear, L[far], Pjj)]] = True
        if extra_ids is not None:
            act |= np.isin(st.g_ids, extra_ids)
        st._start(st.g_ids[act])

    for f in range(nf):
        if f > 0:
            st.predict(*next(odometry))
        r, bear, diam = frames.frame(f)
        k = r.shape[0]
        if k:
            # ---------------- leave the local area when a passive landmark may be matched
            sx, sy = sensor()[:2]
            d2b = None
            if math.hypot(sx - center[0], sy - center[1]) > cfg.local_move:
                n_sync_moved += 1
                resync(r, bear)
            else:
                d2b = passive_d2(r, bear, diam)
                if d2b is not None and (d2b < gate_ind).any():
                    resync(r, bear)
                    d2b = None
            sx, sy = sensor()[:2]
            assign_c = np.full(k, -1, dtype=np.int64)  # index into cand
            d2min = np.full(k, np.inf)
            if d2b is not None:  # passive landmarks between the gate and the new-landmark test
                d2min = d2b.min(axis=1)
            nlA = (st.nA - 3) // 2
            cand = np.zeros(0, dtype=np.int64)
            if nlA:
                LA = st.a_xy()
                ddx, ddy = LA[:, 0] - sx, LA[:, 1] - sy
                cand = np.flatnonzero(ddx * ddx + ddy * ddy < R2)
            if cand.size:
                Jv, Jl, rr, hb = jac(LA[cand])
                nc = cand.size
                crow = np.stack((3 + 2 * cand, 4 + 2 * cand), 1)  # (nc, 2) rows in P_AA
                PA = st.PA
                Pvv = PA[:3, :3]
                Pvl = PA[:3][:, crow].transpose(1, 0, 2)  # (nc, 3, 2)
                Pll = np.empty((nc, 2, 2))
                Pll[:, 0, 0] = PA[crow[:, 0], crow[:, 0]]
                Pll[:, 0, 1] = PA[crow[:, 0], crow[:, 1]]
                Pll[:, 1, 0] = PA[crow[:, 1], crow[:, 0]]
                Pll[:, 1, 1] = PA[crow[:, 1], crow[:, 1]]
                JlT = Jl.transpose(0, 2, 1)
                X = Jv @ Pvl @ JlT
                Sd = Jv @ Pvv @ Jv.transpose(0, 2, 1)
                Sd += X + X.transpose(0, 2, 1)
                Sd += Jl @ Pll @ JlT
                nu = innovations(r, bear, rr, hb)
                extra = diameter_d2(diam, st.a_ids[cand])
                d2 = inv2_quad(Sd[None] + R1, nu[..., 0], nu[..., 1])
                if extra is not None:
                    d2 = d2 + extra
                d2min = np.minimum(d2min, d2.min(axis=1))
                gated = np.flatnonzero((d2 < gate_ind).any(axis=0))
                if gated.size:
                    # joint covariance of the gated candidates' predicted measurements
                    Jg = _stack_jacobian(Jv[gated], Jl[gated])
                    sc = np.concatenate(([0, 1, 2], crow[gated].ravel()))
                    C = Jg @ PA[np.ix_(sc, sc)] @ Jg.T
                    eg = None if extra is None else extra[:, gated]
                    if cfg.association == "jcbb":
                        ag = jcbb(
                            nu[:, gated], C, R1, alpha=cfg.gate_alpha, extra_d2=eg,
                            extra_dof=int(use_d),
                        )  # fmt: skip
                    else:
                        ag = nearest_neighbour(d2[:, gated], gate_ind)
                    assign_c = np.where(ag >= 0, gated[np.maximum(ag, 0)], -1)
                # ---------------- update with all matched detections at once
                mi = np.flatnonzero(assign_c >= 0)
                if mi.size:
                    mj = assign_c[mi]
                    m = mi.size
                    Hn = _stack_jacobian(Jv[mj], Jl[mj])
                    cols = np.concatenate(([0, 1, 2], crow[mj].ravel()))
                    v = nu[mi, mj].reshape(-1)
                    nis_sum += st.update(cols, Hn, v, block_diag_noise(m, R1))
                    nis_dof += v.size
                    n_matched += m
                    jid = st.a_ids[cand[mj]]  # distinct (one-to-one association)
                    if cfg.merge_radius > 0 and m > 1:
                        # landmarks matched in the same scan are different trees
                        pxy = LA[cand[mj]]
                        dd = np.hypot(*(pxy[:, None, :] - pxy[None, :, :]).transpose(2, 0, 1))
                        uu, ww = np.nonzero(np.triu(dd < 2 * cfg.merge_radius, 1))
                        for u, w in zip(uu.tolist(), ww.tolist(), strict=True):
                            a_, b_ = int(jid[u]), int(jid[w])
                            coseen.add((a_, b_) if a_ < b_ else (b_, a_))
                    nobs[jid] += 1
                    last[jid] = f
                    if olog is not None:
                        olog.add(f, jid, r[mi], bear[mi])
                    dm_ = diam[mi]
                    fin = np.isfinite(dm_)
                    d_sum[jid[fin]] += dm_[fin]
                    d_sq[jid[fin]] += dm_[fin] ** 2
                    d_n[jid[fin]] += 1
            # ---------------- new landmarks
            new = np.flatnonzero((assign_c < 0) & (r <= cfg.max_new_range))
            amb = new[d2min[new] <= cfg.new_landmark_chi2]
            n_ambiguous += amb.size
            new = new[d2min[new] > cfg.new_landmark_chi2]
            if new.size:
                sx, sy, th = sensor()[:3]
                ang = th + bear[new]
                mx, my = sx + r[new] * np.cos(ang), sy + r[new] * np.sin(ang)
                if n_ids and alive[:n_ids].any():
                    # every landmark (active exact, passive by eq. 25) near the new points
                    _, bxy = st.b_xy_near(sx, sy, cfg.max_new_range + cfg.new_landmark_min_dist)
                    Lall = np.vstack((st.a_xy(), bxy))
                    if Lall.shape[0]:
                        dd2 = (Lall[None, :, 0] - mx[:, None]) ** 2 + (
                            Lall[None, :, 1] - my[:, None]
                        ) ** 2
                        km = dd2.min(axis=1) >= cfg.new_landmark_min_dist**2
                        n_ambiguous += int((~km).sum())
                        new, mx, my, ang = new[km], mx[km], my[km], ang[km]
            for t_, i in enumerate(new):
                lm_id = n_ids
                n_ids += 1
                st.add_landmark(
                    lm_id, float(mx[t_]), float(my[t_]), float(r[i]), float(ang[t_]), R1, a, b
                )
                fin_i = math.isfinite(diam[i])
                if fin_i:
                    d_sum[lm_id] = float(diam[i])
                    d_sq[lm_id] = float(diam[i]) ** 2
                    d_n[lm_id] = 1
                nobs[lm_id] = 1
                first[lm_id] = f
                last[lm_id] = f
                alive[lm_id] = True
                n_new += 1
        # ---------------- landmark quality pruning (batched as in the full filter)
        if cfg.prune_after > 0 and n_ids and (f % cfg.prune_every == 0 or f == nf - 1):
            bad = np.flatnonzero(
                alive[:n_ids]
                & (first[:n_ids] <= f - cfg.prune_after)
                & (nobs[:n_ids] < cfg.min_obs)
            )
            if bad.size:
                st.remove(bad)
                alive[bad] = False
                n_pruned += bad.size
        # ---------------- duplicate merging (same pass)
        if cfg.merge_radius > 0 and n_ids and (f % cfg.prune_every == 0 or f == nf - 1):
            recent = alive[:n_ids] & (last[:n_ids] > f - cfg.prune_every)
            ids_all, xy_all = st.all_xy()
            pi, pj = close_pairs(xy_all, recent[ids_all], cfg.merge_radius)
            if pi.size:
                members = ids_all[np.union1d(pi, pj)]
                if not np.isin(members, st.a_ids).all():
                    resync(r, bear, members)
                    ids_all, xy_all = st.all_xy()
                    pi, pj = close_pairs(xy_all, recent[ids_all], cfg.merge_radius)
                # all members are active: ids_all[:na] = st.a_ids, rows 3 + 2t of P_AA
                ri, rj = 3 + 2 * pi, 3 + 2 * pj
                PA = st.PA
                pid = ids_all  # landmark id per combined index
                with np.errstate(invalid="ignore", divide="ignore"):
                    dmean = d_sum[pid] / d_n[pid]
                Pii, Pjj, Pij = _blocks(PA, ri, ri), _blocks(PA, rj, rj), _blocks(PA, ri, rj)
                gi, gj = pid[pi], pid[pj]
                together = np.array(
                    [
                        (min(u, w), max(u, w)) in coseen
                        for u, w in zip(gi.tolist(), gj.tolist(), strict=True)
                    ],
                    dtype=bool,
                )
                plan = decide_merges(
                    pi, pj, xy_all, Pii, Pjj, Pij, dmean, d_n[pid], nobs[pid], together,
                    sd2=sd2 if use_d else None, alpha=cfg.gate_alpha,
                )  # fmt: skip
                drops = []
                for keep, drop, compatible in plan:
                    n_fused += int(compatible)
                    if compatible or cfg.merge_constraint:
                        st.fuse(3 + 2 * keep, 3 + 2 * drop)
                    ki, di = int(pid[keep]), int(pid[drop])
                    if olog is not None:
                        olog.merged(di, ki)
                    nobs[ki] += nobs[di]
                    d_sum[ki] += d_sum[di]
                    d_sq[ki] += d_sq[di]
                    d_n[ki] += d_n[di]
                    first[ki] = min(first[ki], first[di])
                    last[ki] = max(last[ki], last[di])
                    drops.append(di)
                if drops:
                    dr = np.array(drops, dtype=np.int64)
                    st.remove(dr)
                    alive[dr] = False
                    n_merged += dr.size
        inputs.add_pose(st.xA[:3])
        if progress is not None and (f % 50 == 0 or f == nf - 1):
            progress(f + 1, nf)

    st.sync(None)
    trees = []
    L = st.xg[3:].reshape(-1, 2)
    for t_, j_ in enumerate(st.g_ids):
        j = int(j_)
        cov = st.Pg[3 + 2 * t_ : 5 + 2 * t_, 3 + 2 * t_ : 5 + 2 * t_].copy()
        dn = int(d_n[j])
        dm = float(d_sum[j]) / dn if dn else math.nan
        dstd = math.sqrt(max(d_sq[j] / dn - dm * dm, 0.0)) if dn > 1 else math.nan
        trees.append(
            Tree(
                id=t_,
                x=float(L[t_, 0]),
                y=float(L[t_, 1]),
                diameter=dm,
                cov=0.5 * (cov + cov.T),
                n_obs=int(nobs[j]),
                first_time=float(frames.times[first[j]]),
                last_time=float(frames.times[last[j]]),
                diameter_std=dstd,
            )
        )
    nl = len(trees)
    smooth_stats: dict[str, float | int] = {}
    pose_covs = None
    if olog is not None:
        lm_cov = np.array([t.cov for t in trees]).reshape(-1, 2, 2)
        poses, pose_covs, smooth_stats = smooth_path(
            inputs.poses, inputs.deltas, inputs.covs, olog.stream(st.g_ids), L.copy(), lm_cov,
            (a, b), R1, map_cov=st.Pg[3:, 3:].copy(), map_cov_inflation=cfg.map_cov_inflation,
        )  # fmt: skip
        smooth_stats |= residual_noise_stats(poses, olog.stream(st.g_ids).arrays(), L, (a, b))
        olog.close()  # (its temporary file, if it spilled)
    else:
        poses = inputs.path()
    inputs.close()
    runtime = time.perf_counter() - t_start
    stats: dict[str, float | int | str] = {
        "backend": name,
        "association": cfg.association,
        "update": "compressed",
        "frames": nf,
        "detections": frames.n_detections,
        "matched": n_matched,
        "new_landmarks": n_new,
        "pruned": n_pruned,
        "ambiguous_discarded": n_ambiguous,
        "landmarks": nl,
        "merged": n_merged,
        "merged_compatible": n_fused,
        "full_updates": st.n_sync,
        "full_updates_moved": n_sync_moved,
        "nis_per_dof": nis_sum / nis_dof if nis_dof else math.nan,
        **smooth_stats,
        "runtime_s": runtime,
    }
    return SlamResult(
        frame_trajectory(frames.times, poses), StemMap(tuple(trees)), stats, pose_covs=pose_covs
    )
