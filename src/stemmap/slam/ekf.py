"""EKF-SLAM with range-bearing tree landmarks, Mahalanobis gating and JCBB association.

State ``[x, y, theta, m1x, m1y, ...]`` with one full covariance (Dissanayake et al. 2001;
Guivant & Nebot 2001 for Victoria Park). Per laser frame:

1. **Predict** with the odometry pre-integrated between frames
   (:func:`stemmap.slam.motion.preintegrate`): ``x ← x ⊕ δ``, ``P_vv ← F P_vv Fᵀ + Q``,
   ``P_vm ← F P_vm`` (O(n), the map block is untouched).
2. **Associate** the frame's detections with the landmarks near the vehicle: individual
   Mahalanobis gate, then JCBB (:mod:`stemmap.slam.association`) or greedy nearest neighbour;
   the trunk diameter is an extra independent cue (``(d_obs - d_lm)² / (σ²_obs + σ²_lm)``,
   one more degree of freedom per pair).
3. **Update** with all matched detections at once. Only the columns of the pose and the matched
   landmarks enter ``H``, so ``P Hᵀ`` is O(n·m) and the covariance update one rank-2m
   correction (``P ← P - K S Kᵀ``, symmetric form).
4. **Initialise** new landmarks from unmatched detections that are clearly not an existing
   landmark (individual ``d²`` above ``new_landmark_chi2`` and farther than
   ``new_landmark_min_dist`` from every landmark).
5. **Prune** (optional landmark quality): a landmark that is still seen fewer than
   ``min_obs`` times ``prune_after`` frames after its creation is removed from the state.

6. **Merge** duplicates (same pass): landmarks closer than ``merge_radius`` that are one tree
   (Mahalanobis-compatible, overlapping trunks, or never matched in the same scan) are joined
   by the constraint ``m_i = m_j`` and the less-observed one is marginalised
   (:func:`stemmap.slam._ekf_merge.decide_merges`).

7. **Smooth** the path (``smooth=True``, after the last frame): every pose is re-estimated on
   the final map from the odometry and the associations the filter made
   (:func:`stemmap.slam._ekf_smooth.smooth_path`), so that a loop closure corrects the poses
   before it as well, not only the map and the current pose.

The default ``update="compressed"`` runs the same steps on the compressed filter of Guivant &
Nebot 2001 (:mod:`stemmap.slam._ekf_compressed`): per frame only the local submap is updated,
the rest once on leaving the area; the result equals this full filter (``update="full"``,
below) to round-off. In the full filter the covariance lives in a preallocated buffer that
grows geometrically, so adding a landmark does not copy the whole matrix every time.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import solve_triangular

from stemmap.errors import ConfigError
from stemmap.slam._ekf_algebra import (
    _blocks,
    augment_landmark_covariance,
    block_diag_noise,
    grow_buffers,
)
from stemmap.slam._ekf_compressed import run_compressed
from stemmap.slam._ekf_merge import close_pairs, decide_merges
from stemmap.slam._ekf_smooth import ObservationLog, smooth_path
from stemmap.slam._ekf_stream import FrameInputs
from stemmap.slam.association import chi2_gate, individual_compatibility, jcbb, nearest_neighbour
from stemmap.slam.base import SlamProblem, SlamResult, frame_trajectory, single_threaded_blas
from stemmap.slam.motion import preintegrate_spans
from stemmap.slam.residual_noise import residual_noise_stats
from stemmap.types import FloatArray, StemMap, Tree

__all__ = ["EkfConfig", "EkfSlam"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EkfConfig:
    """EKF-SLAM settings (defaults justified in docs/algorithms/slam.md).

    sigma_range : m, range noise of a tree-centre detection (default 0.3 m, as the other
        filters: the centre error of a trunk depends on the viewpoint and persists over many
        scans, so the scan-to-scan scatter, ~0.03 m, would make the filter over-confident)
    sigma_bearing : rad, bearing noise (default 1°, same reason)
    sigma_diameter : m, scatter of one diameter measurement (None/inf disables the cue)
    association : "jcbb" or "nn"
    gate_alpha : individual/joint gate probability
    new_landmark_chi2 : an unmatched detection starts a landmark only if its smallest d² to any
        landmark exceeds this (detections between the gate and this value are discarded as
        ambiguous)
    new_landmark_min_dist : m, and only if it is at least this far from every landmark
    max_new_range : m, no landmarks are started from detections farther than this (default
        85 m = ``search_radius``: a landmark is started wherever it can later be associated;
        the earlier 40 m left 8 % of the Victoria Park detections unused, see
        docs/algorithms/slam.md)
    prune_after, min_obs : landmark quality (prune_after = 0 disables pruning): a landmark is
        confirmed when seen ``min_obs`` times within ``prune_after`` frames of its start,
        otherwise removed (default 4 in 10 frames; 3 until Dec 2: on Victoria Park the 79
        landmarks that 3 keeps and 4 removes explained 0.85 detections each, see
        docs/algorithms/slam.md)
    prune_every : frames between pruning passes (each pass copies the covariance once)
    search_radius : m, landmarks farther than this from the sensor are not association candidates
    update : "compressed" (default; Guivant & Nebot 2001 compressed filter, exact) or "full"
        (the reference: every step updates the whole covariance)
    local_radius : m, compressed filter: landmarks within this distance of the sensor form the
        active submap at each full update (run time only; the result does not depend on it)
    merge_radius : m, landmark pairs closer than this (one of them seen since the last pass)
        are tested for being one tree every ``prune_every`` frames (0 disables merging)
    merge_constraint : a merge applies the constraint ``m_i = m_j`` (a loop closure) also
        when the pair is not Mahalanobis-compatible; False: such pairs are only marginalised
    local_move : m, compressed filter: a full update also happens when the sensor is this far
        from where the current local period began (run time only)
    smooth : the trajectory returned is the whole path re-estimated on the final map
        (:mod:`stemmap.slam._ekf_smooth`: the filter's odometry and associations, the map
        fixed), so that the poses before a loop closure get its correction too; False returns
        the filtered poses (each from the data up to its own frame)
    map_cov_inflation : factor (>= 0) on the map's share of the smoothed path's covariance
        (``smooth``; :func:`stemmap.slam._ekf_smooth.smooth_path`), the path and the map
        themselves unchanged. Default 1, the model's own. On Victoria Park the second half's
        pose covariance is overconfident (z² median 2.59, the GPS's error counted); 80, the
        factor putting 86.5 % of the first half inside 2 sigma, gives 0.49 on the held-out
        second half, but the maximum-likelihood factor on the first half is 0 and the
        simulator's covariance is already wide, so it is offered, not applied (docs/outputs.md
        "A factor on the EKF's map term"; ``benchmarks/pose_covariance.py
        --vp-ekf-map-factor``)
    noise_from_residuals : ours, default False (offered; docs/algorithms/slam.md "The EKF's
        detection noise measured from its residuals"): run the filter and smoother once with
        ``sigma_range`` / ``sigma_bearing``, measure the detection noise from the residuals of
        the detections it associated (:func:`stemmap.slam.residual_noise.residual_noise`: the
        *long-run* std, which counts the correlation of one tree's consecutive detections),
        and where it is larger than the configured sigma run again with it (a floor: the part
        of a tree's error shared by all its detections is absorbed by the map and invisible
        in residuals, so the estimate is a lower bound of the noise that matters; on Victoria
        Park both are raised, 0.42 m / 1.5 deg, on the simulator neither). Up to twice the
        CPU; needs ``smooth``. The stats name the values used (``noise_from_residuals_*``)
    """

    sigma_range: float = 0.30
    sigma_bearing: float = math.radians(1.0)
    sigma_diameter: float | None = 0.10
    association: str = "jcbb"
    gate_alpha: float = 0.99
    new_landmark_chi2: float = 25.0
    new_landmark_min_dist: float = 1.0
    max_new_range: float = 85.0
    prune_after: int = 10
    prune_every: int = 20
    min_obs: int = 4
    search_radius: float = 85.0
    update: str = "compressed"
    local_radius: float = 60.0
    local_move: float = 20.0
    merge_radius: float = 1.0
    merge_constraint: bool = True
    smooth: bool = True
    map_cov_inflation: float = 1.0
    noise_from_residuals: bool = False

    def __post_init__(self) -> None:
        if self.association not in ("jcbb", "nn"):
            raise ConfigError(
                f"EkfConfig.association must be 'jcbb' or 'nn', got {self.association!r}."
            )
        if self.update not in ("compressed", "full"):
            raise ConfigError(
                f"EkfConfig.update must be 'compressed' or 'full', got {self.update!r}."
            )
        for name in (
            "sigma_range",
            "sigma_bearing",
            "new_landmark_chi2",
            "search_radius",
            "local_radius",
            "local_move",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"EkfConfig.{name} must be a positive number, got {v}.")
        if self.prune_every < 1:
            raise ConfigError(f"EkfConfig.prune_every must be >= 1, got {self.prune_every}.")
        if not (math.isfinite(self.map_cov_inflation) and self.map_cov_inflation >= 0):
            raise ConfigError(
                f"EkfConfig.map_cov_inflation must be a number >= 0, got {self.map_cov_inflation}."
            )
        if self.noise_from_residuals and not self.smooth:
            raise ConfigError(
                "EkfConfig.noise_from_residuals needs smooth=True (the residuals are taken at "
                "the smoothed path)."
            )
        if self.sigma_diameter is not None and not self.sigma_diameter > 0:
            raise ConfigError(
                f"EkfConfig.sigma_diameter must be > 0 or None, got {self.sigma_diameter}."
            )


class EkfSlam:
    """EKF-SLAM back-end (registered as ``"ekf"``); keyword config as in :class:`EkfConfig`."""

    name = "ekf"
    _cap0 = 256
    P: FloatArray
    x: FloatArray
    n: int

    def __init__(self, config: EkfConfig | None = None, **kwargs: object) -> None:
        if config is not None and kwargs:
            raise ConfigError("pass either an EkfConfig or keyword settings, not both.")
        try:
            self.config = config or EkfConfig(**kwargs)  # type: ignore[arg-type]
        except TypeError as exc:
            raise ConfigError(f"bad EKF-SLAM setting: {exc}.") from exc

    # ------------------------------------------------------------------ state buffer helpers
    def _reserve(self, extra: int) -> None:
        grown = grow_buffers(self.n, self.n + extra, self.P, self.x)
        if grown is not None:
            self.P, self.x = grown

    def run(
        self, problem: SlamProblem, *, progress: Callable[[int, int], None] | None = None
    ) -> SlamResult:
        # The per-frame matrices are small: multi-threaded BLAS only adds overhead (measured
        # 25x slower on a loaded 2-core machine), so the filter runs single-threaded.
        with single_threaded_blas():
            res = self._run_once(self.config, problem, progress)
            if not self.config.noise_from_residuals:
                return res
            st = res.stats
            if "residual_sigma_range_long_run" not in st:  # too few associations to measure
                log.warning("EKF: too few associated detections to measure their noise.")
                return res
            sr = max(self.config.sigma_range, float(st["residual_sigma_range_long_run"]))
            sb = max(self.config.sigma_bearing, float(st["residual_sigma_bearing_long_run"]))
            if (sr, sb) != (self.config.sigma_range, self.config.sigma_bearing):
                cfg = dataclasses.replace(
                    self.config, sigma_range=sr, sigma_bearing=sb, noise_from_residuals=False
                )
                res = self._run_once(cfg, problem, progress)
            res.stats |= {
                "noise_from_residuals_sigma_range": sr,
                "noise_from_residuals_sigma_bearing": sb,
            }
            return res

    def _run_once(
        self,
        cfg: EkfConfig,
        problem: SlamProblem,
        progress: Callable[[int, int], None] | None,
    ) -> SlamResult:
        if cfg.update == "compressed":
            return run_compressed(cfg, problem, progress, self.name)
        return self._run(cfg, problem, progress)

    def _run(
        self,
        cfg: EkfConfig,
        problem: SlamProblem,
        progress: Callable[[int, int], None] | None,
    ) -> SlamResult:
        t_start = time.perf_counter()
        frames = problem.frames
        nf = len(frames)
        a, b = problem.sensor_offset
        pre = preintegrate_spans(
            problem.motion, problem.controls, frames.times, problem.initial_pose
        )
        inputs = FrameInputs(pre.deltas, pre.covs)  # (on disk beyond a few thousand frames)
        del pre
        odometry = inputs.odometry()
        R1 = np.diag([cfg.sigma_range**2, cfg.sigma_bearing**2])
        use_d = cfg.sigma_diameter is not None
        sd2 = (cfg.sigma_diameter or 1.0) ** 2
        gate_ind = chi2_gate(cfg.gate_alpha, 3 if use_d else 2)

        self.n = 3
        self.P = np.zeros((self._cap0, self._cap0))
        self.x = np.zeros(self._cap0)
        self.x[:3] = problem.initial_pose
        # per-landmark bookkeeping (index = landmark slot, state rows 3+2s, 4+2s)
        lm_d_sum: list[float] = []
        lm_d_sq: list[float] = []
        lm_d_n: list[int] = []
        lm_nobs: list[int] = []
        lm_first: list[int] = []
        lm_last: list[int] = []
        lm_id: list[int] = []  # permanent id (slots shift when landmarks are removed)
        coseen: set[tuple[int, int]] = set()  # ids of landmark pairs matched in one scan
        olog = ObservationLog() if cfg.smooth else None
        n_merged = n_fused = 0
        n_matched = n_new = n_pruned = n_ambiguous = 0

        def compact(kl: list[bool]) -> None:
            lists: tuple[list[Any], ...] = (
                lm_d_sum, lm_d_sq, lm_d_n, lm_nobs, lm_first, lm_last, lm_id
            )  # fmt: skip
            for lst in lists:
                lst[:] = [v for v, kk in zip(lst, kl, strict=True) if kk]

        nis_sum, nis_dof = 0.0, 0

        for f in range(nf):
            # ---------------- predict
            if f > 0:
                d, d_cov = next(odometry)
                th = self.x[2]
                c, s = math.cos(th), math.sin(th)
                dxw = c * d[0] - s * d[1]
                dyw = s * d[0] + c * d[1]
                self.x[0] += dxw
                self.x[1] += dyw
                self.x[2] = (th + d[2] + math.pi) % (2 * math.pi) - math.pi
                F = np.array([[1.0, 0.0, -dyw], [0.0, 1.0, dxw], [0.0, 0.0, 1.0]])
                Rw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                Q = Rw @ d_cov @ Rw.T
                n = self.n
                P = self.P
                P[:3, :3] = F @ P[:3, :3] @ F.T + Q
                if n > 3:
                    P[:3, 3:n] = F @ P[:3, 3:n]
                    P[3:n, :3] = P[:3, 3:n].T

            r, bear, diam = frames.frame(f)
            k = r.shape[0]
            nl = (self.n - 3) // 2
            if k:
                x, y, th = self.x[0], self.x[1], self.x[2]
                c, s = math.cos(th), math.sin(th)
                sx, sy = x + a * c - b * s, y + a * s + b * c
                dsx_dth, dsy_dth = -a * s - b * c, a * c - b * s
                assign = np.full(k, -1, dtype=np.int64)
                d2min = np.full(k, np.inf)
                cand = np.zeros(0, dtype=np.int64)
                if nl:
                    L = self.x[3 : self.n].reshape(-1, 2)
                    ddx, ddy = L[:, 0] - sx, L[:, 1] - sy
                    cand = np.flatnonzero(ddx * ddx + ddy * ddy < cfg.search_radius**2)
                if cand.size:
                    # predicted measurements and Jacobians of the candidates
                    ex, ey = ddx[cand], ddy[cand]
                    q = ex * ex + ey * ey
                    rr = np.sqrt(q)
                    hb = np.arctan2(ey, ex) - th
                    nc = cand.size
                    J = np.zeros((2 * nc, 3 + 2 * nc))
                    ir, ib = 2 * np.arange(nc), 2 * np.arange(nc) + 1
                    J[ir, 0], J[ir, 1] = -ex / rr, -ey / rr
                    J[ir, 2] = -(ex * dsx_dth + ey * dsy_dth) / rr
                    J[ib, 0], J[ib, 1] = ey / q, -ex / q
                    J[ib, 2] = (-ex * dsy_dth + ey * dsx_dth) / q - 1.0
                    cols_l = 3 + 2 * np.arange(nc)
                    J[ir, cols_l], J[ir, cols_l + 1] = ex / rr, ey / rr
                    J[ib, cols_l], J[ib, cols_l + 1] = -ey / q, ex / q
                    sc = np.concatenate(
                        ([0, 1, 2], np.stack((3 + 2 * cand, 4 + 2 * cand), 1).ravel())
                    )
                    Psub = self.P[np.ix_(sc, sc)]
                    C = J @ Psub @ J.T
                    nu = np.empty((k, nc, 2))
                    nu[:, :, 0] = r[:, None] - rr[None, :]
                    nu[:, :, 1] = (bear[:, None] - hb[None, :] + math.pi) % (2 * math.pi) - math.pi
                    extra = None
                    if use_d:
                        cand_n = np.array([lm_d_n[j] for j in cand])
                        cand_mean = np.array([lm_d_sum[j] for j in cand]) / cand_n
                        var_lm = sd2 / cand_n
                        dd = diam[:, None] - cand_mean[None, :]
                        extra = dd * dd / (sd2 + var_lm[None, :])
                        extra = np.where(np.isfinite(extra), extra, 0.0)
                    d2 = individual_compatibility(nu, C, R1, extra)
                    d2min = d2.min(axis=1)
                    if cfg.association == "jcbb":
                        assign = jcbb(
                            nu, C, R1, alpha=cfg.gate_alpha, extra_d2=extra, extra_dof=int(use_d)
                        )
                    else:
                        assign = nearest_neighbour(d2, gate_ind)
                    # ---------------- update with all matched detections at once
                    mi = np.flatnonzero(assign >= 0)
                    if mi.size:
                        mj = assign[mi]
                        rows = np.stack((2 * mj, 2 * mj + 1), 1).ravel()
                        Hs = J[rows]  # (2m, 3 + 2nc) over the sub-state sc
                        nz = np.concatenate(
                            ([0, 1, 2], np.stack((3 + 2 * mj, 4 + 2 * mj), 1).ravel())
                        )
                        Hn = Hs[:, nz]
                        cols = sc[nz]
                        v = nu[mi, mj].reshape(-1)
                        nis_sum += self._update(cols, Hn, v, block_diag_noise(mi.size, R1))
                        nis_dof += v.size
                        n_matched += mi.size
                        if cfg.merge_radius > 0 and mi.size > 1:
                            # landmarks matched in the same scan are different trees
                            ms = cand[mj]
                            pxy = self.x[3 : self.n].reshape(-1, 2)[ms]
                            dd = np.hypot(*(pxy[:, None, :] - pxy[None, :, :]).transpose(2, 0, 1))
                            uu, ww = np.nonzero(np.triu(dd < 2 * cfg.merge_radius, 1))
                            for u, w in zip(uu.tolist(), ww.tolist(), strict=True):
                                a_, b_ = lm_id[ms[u]], lm_id[ms[w]]
                                coseen.add((a_, b_) if a_ < b_ else (b_, a_))
                        if olog is not None:
                            olog.add(f, np.array([lm_id[j] for j in cand[mj]]), r[mi], bear[mi])
                        for i, j in zip(mi, cand[mj], strict=True):
                            lm_nobs[j] += 1
                            lm_last[j] = f
                            if math.isfinite(diam[i]):
                                lm_d_sum[j] += float(diam[i])
                                lm_d_sq[j] += float(diam[i]) ** 2
                                lm_d_n[j] += 1
                # ---------------- new landmarks
                new = np.flatnonzero((assign < 0) & (r <= cfg.max_new_range))
                amb = new[d2min[new] <= cfg.new_landmark_chi2]
                n_ambiguous += amb.size
                new = new[d2min[new] > cfg.new_landmark_chi2]
                if new.size:
                    x, y, th = self.x[0], self.x[1], self.x[2]
                    c, s = math.cos(th), math.sin(th)
                    sx, sy = x + a * c - b * s, y + a * s + b * c
                    ang = th + bear[new]
                    mx, my = sx + r[new] * np.cos(ang), sy + r[new] * np.sin(ang)
                    if nl:
                        L = self.x[3 : self.n].reshape(-1, 2)
                        keep = []
                        for t_ in range(new.size):
                            dd2 = (L[:, 0] - mx[t_]) ** 2 + (L[:, 1] - my[t_]) ** 2
                            keep.append(bool(dd2.min() >= cfg.new_landmark_min_dist**2))
                        km = np.array(keep)
                        n_ambiguous += int((~km).sum())
                        new, mx, my, ang = new[km], mx[km], my[km], ang[km]
                for t_, i in enumerate(new):
                    self._add_landmark(
                        float(mx[t_]), float(my[t_]), float(r[i]), float(ang[t_]), R1, a, b
                    )
                    lm_d_sum.append(float(diam[i]) if math.isfinite(diam[i]) else 0.0)
                    lm_d_sq.append(float(diam[i]) ** 2 if math.isfinite(diam[i]) else 0.0)
                    lm_d_n.append(1 if math.isfinite(diam[i]) else 0)
                    lm_nobs.append(1)
                    lm_first.append(f)
                    lm_last.append(f)
                    lm_id.append(n_new)
                    n_new += 1
            # ---------------- landmark quality pruning
            # (batched every prune_every frames: each removal copies P, O(n²))
            if cfg.prune_after > 0 and lm_first and (f % cfg.prune_every == 0 or f == nf - 1):
                nl = (self.n - 3) // 2
                first = np.asarray(lm_first)
                nobs = np.asarray(lm_nobs)
                bad = np.flatnonzero((first <= f - cfg.prune_after) & (nobs < cfg.min_obs))
                if bad.size:
                    keep_l = np.ones(nl, dtype=bool)
                    keep_l[bad] = False
                    self._remove_landmarks(keep_l)
                    compact(keep_l.tolist())
                    n_pruned += bad.size
            # ---------------- duplicate merging (same pass; see _ekf_compressed.decide_merges)
            if cfg.merge_radius > 0 and lm_first and (f % cfg.prune_every == 0 or f == nf - 1):
                xy = self.x[3 : self.n].reshape(-1, 2)
                recent = np.asarray(lm_last) > f - cfg.prune_every
                pi, pj = close_pairs(xy, recent, cfg.merge_radius)
                if pi.size:
                    ri, rj = 3 + 2 * pi, 3 + 2 * pj
                    dn_ = np.asarray(lm_d_n)
                    with np.errstate(invalid="ignore", divide="ignore"):
                        dmean = np.asarray(lm_d_sum) / dn_
                    together = np.array(
                        [
                            (min(lm_id[u], lm_id[w]), max(lm_id[u], lm_id[w])) in coseen
                            for u, w in zip(pi.tolist(), pj.tolist(), strict=True)
                        ],
                        dtype=bool,
                    )
                    plan = decide_merges(
                        pi, pj, xy.copy(), _blocks(self.P, ri, ri), _blocks(self.P, rj, rj),
                        _blocks(self.P, ri, rj), dmean, dn_, np.asarray(lm_nobs), together,
                        sd2=sd2 if use_d else None, alpha=cfg.gate_alpha,
                    )  # fmt: skip
                    keep_l = np.ones(len(lm_id), dtype=bool)
                    for kp, dr, compatible in plan:
                        n_fused += int(compatible)
                        if compatible or cfg.merge_constraint:
                            self._fuse(3 + 2 * kp, 3 + 2 * dr)
                        if olog is not None:
                            olog.merged(lm_id[dr], lm_id[kp])
                        lm_nobs[kp] += lm_nobs[dr]
                        lm_d_sum[kp] += lm_d_sum[dr]
                        lm_d_sq[kp] += lm_d_sq[dr]
                        lm_d_n[kp] += lm_d_n[dr]
                        lm_first[kp] = min(lm_first[kp], lm_first[dr])
                        lm_last[kp] = max(lm_last[kp], lm_last[dr])
                        keep_l[dr] = False
                    if plan:
                        self._remove_landmarks(keep_l)
                        compact(keep_l.tolist())
                        n_merged += len(plan)
            inputs.add_pose(self.x[:3])
            if progress is not None and (f % 50 == 0 or f == nf - 1):
                progress(f + 1, nf)

        # ---------------- products
        nl = (self.n - 3) // 2
        trees = []
        L = self.x[3 : self.n].reshape(-1, 2)
        for j in range(nl):
            cov = self.P[3 + 2 * j : 5 + 2 * j, 3 + 2 * j : 5 + 2 * j].copy()
            dn = lm_d_n[j]
            dm = lm_d_sum[j] / dn if dn else math.nan
            dstd = math.sqrt(max(lm_d_sq[j] / dn - dm * dm, 0.0)) if dn > 1 else math.nan
            trees.append(
                Tree(
                    id=j,
                    x=float(L[j, 0]),
                    y=float(L[j, 1]),
                    diameter=dm,
                    cov=0.5 * (cov + cov.T),
                    n_obs=lm_nobs[j],
                    first_time=float(frames.times[lm_first[j]]),
                    last_time=float(frames.times[lm_last[j]]),
                    diameter_std=dstd,
                )
            )
        smooth_stats: dict[str, float | int] = {}
        pose_covs = None
        if olog is not None:
            lm_cov = np.array([t.cov for t in trees]).reshape(-1, 2, 2)
            poses, pose_covs, smooth_stats = smooth_path(
                inputs.poses, inputs.deltas, inputs.covs,
                olog.stream(np.asarray(lm_id, dtype=np.int64)), L.copy(), lm_cov, (a, b), R1,
                map_cov=self.P[3 : self.n, 3 : self.n].copy(),
                map_cov_inflation=cfg.map_cov_inflation,
            )  # fmt: skip
            smooth_stats |= residual_noise_stats(
                poses, olog.stream(np.asarray(lm_id, dtype=np.int64)).arrays(), L, (a, b)
            )
            olog.close()  # (its temporary file, if it spilled)
        else:
            poses = inputs.path()
        inputs.close()
        runtime = time.perf_counter() - t_start
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "association": cfg.association,
            "frames": nf,
            "detections": frames.n_detections,
            "matched": n_matched,
            "new_landmarks": n_new,
            "pruned": n_pruned,
            "merged": n_merged,
            "merged_compatible": n_fused,
            "ambiguous_discarded": n_ambiguous,
            "landmarks": nl,
            # normalised innovation squared per degree of freedom: ~1 for a consistent filter
            "nis_per_dof": nis_sum / nis_dof if nis_dof else math.nan,
            **smooth_stats,
            "runtime_s": runtime,
        }
        log.info("EKF-SLAM: %s", stats)
        return SlamResult(
            frame_trajectory(frames.times, poses), StemMap(tuple(trees)), stats, pose_covs=pose_covs
        )

    def _add_landmark(
        self, mx: float, my: float, rng_: float, ang: float, R1: FloatArray, a: float, b: float
    ) -> None:
        """Augment the state with landmark (mx, my) observed at range ``rng_``, world angle
        ``ang`` (= theta + bearing) from the current pose."""
        self._reserve(2)
        n = self.n
        # m = s(x) + r [cos(th + b), sin(th + b)]
        augment_landmark_covariance(self.P, n, float(self.x[2]), a, b, rng_, ang, R1)
        self.x[n], self.x[n + 1] = mx, my
        self.n = n + 2

    def _fuse(self, ri: int, rj: int) -> None:
        """Constraint ``m_i - m_j = 0`` between the landmarks at rows ``ri``, ``rj`` (a
        noise-free pseudo-measurement; a 1 mm sigma keeps the Cholesky factor regular)."""
        cols = np.array([ri, ri + 1, rj, rj + 1])
        Hn = np.array([[1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, -1.0]])
        v = -(self.x[[ri, ri + 1]] - self.x[[rj, rj + 1]])
        self._update(cols, Hn, v, np.eye(2) * 1e-6)

    def _update(self, cols: np.ndarray, Hn: FloatArray, v: FloatArray, R: np.ndarray) -> float:
        """Joint EKF update with ``H`` nonzero only in the state columns ``cols``; returns the NIS.

        ``S = L Lᵀ``; ``W = P Hᵀ L⁻ᵀ``; ``x += W L⁻¹ν``; ``P -= W Wᵀ`` (exactly symmetric, which
        keeps P positive semi-definite over thousands of updates). ``P Hᵀ`` is O(n·m).
        """
        n = self.n
        PHt = self.P[:n, cols] @ Hn.T  # (n, 2m)
        S = Hn @ PHt[cols] + R
        Lc = np.linalg.cholesky(0.5 * (S + S.T))
        W = solve_triangular(Lc, PHt.T, lower=True).T
        wv = solve_triangular(Lc, v, lower=True)
        self.x[:n] += W @ wv
        self.x[2] = (self.x[2] + math.pi) % (2 * math.pi) - math.pi
        self.P[:n, :n] -= W @ W.T
        return float(wv @ wv)

    def _remove_landmarks(self, keep: np.ndarray) -> None:
        kept = 3 + 2 * np.flatnonzero(keep)
        idx = np.concatenate(([0, 1, 2], np.stack((kept, kept + 1), 1).ravel()))
        m = idx.size
        self.P[:m, :m] = self.P[np.ix_(idx, idx)]
        self.x[:m] = self.x[idx]
        self.n = m
