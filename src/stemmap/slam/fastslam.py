"""FastSLAM 1.0 with per-particle landmark EKFs, vectorised over particles (Munjer 2025, §3.6).

Munjer et al. localise and map trees with FastSLAM [Montemerlo 2002/2004]: every particle
``S_t^(k) = {state_t^(k), map_t^(k)}`` (their eq. 9) carries a pose hypothesis, predicted with the
motion model ``x_t = f(x_{t-1}, u_t) + ω_t`` (eq. 10), and its own map of independent 2x2 landmark
EKFs updated with ``z_t = h(x_t, t_i) + v_t`` (eq. 11); particle weights follow the consistency of
predicted and observed landmarks. Published parameter: 100 particles (their Table 1).

Implementation choices (recorded in docs/algorithms/slam-frontends.md):

* **FastSLAM 1.0**: the proposal is the motion model (odometry increment between frames from
  :func:`~stemmap.slam.motion.preintegrate`, its covariance sampled per particle); the weight is the
  product of the Gaussian likelihoods of the associated detections.
* **Data association per particle** (maximum likelihood with a new-landmark likelihood ``p0``, as
  in Montemerlo et al. 2004 "unknown data association"): every particle matches every detection
  of the frame against its own ``max_candidates`` nearest landmarks; two detections may not claim
  the same landmark (the less likely one is dropped for that frame).
* Everything is an array over particles: poses ``(P, 3)``, landmark means ``(P, C, 2)``,
  covariances ``(P, C, 2, 2)`` with a capacity ``C`` that doubles when needed and is never
  shrunk. The association and landmark updates of version 1 run particle by particle in a
  compiled kernel (:func:`stemmap.slam._fastslam_kernel.associate_update`); version 2, and
  version 1 with ``_kernel = False``, run the same steps as numpy operations on ``(P, K, M)``
  arrays (``K`` detections, ``M`` candidates) -- the reference the kernel is tested against
  (its element-wise arithmetic, sampling, resampling and the particle set's covariances are in
  :mod:`stemmap.slam._fastslam_particles`, re-exported here).
* Resampling (systematic, seeded) when the effective sample size falls below
  ``resample_threshold * P``, done in place copying only the landmarks in use
  (:func:`~stemmap.slam._fastslam_kernel.resample_inplace`). The trajectory is the ancestry of
  the final best particle (parent indices are stored per frame and back-tracked at the end, no
  path copying).
* Uncertainty (issue 14): ``SlamResult.pose_covs`` is the weighted covariance of the particles'
  poses at every frame (before that frame's resampling), a tree's ``cov`` the mixture over the
  particles that hold it (:func:`particle_landmark_covariance`), both multiplied by a variance
  factor (:data:`POSE_COV_INFLATION`, :data:`TREE_COV_INFLATION`) estimated on the first half
  of Victoria Park: the particle set alone is ~30x too narrow in std because its paths share
  one ancestor a few tens of seconds back (path degeneracy). docs/algorithms/slam.md, "FastSLAM
  covariance", says what the calibrated numbers mean and where they hold.
"""

from __future__ import annotations

import logging
import math
import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from stemmap.errors import ConfigError
from stemmap.slam._fastslam_kernel import associate_update, compact_inplace, resample_inplace
from stemmap.slam._fastslam_particles import (
    _ekf_update,
    _inv2,
    _predict_and_inv,
    _psd_sqrt_stack,
    _sample_batch,
    _wrap_inplace,
    particle_landmark_covariance,
    posterior_mean_path,
    systematic_resample,
    weighted_pose_covariance,
)
from stemmap.slam.treedb import range_bearing_jacobians
from stemmap.types import StemMap, Tree, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem, SlamResult

__all__ = [
    "POSE_COV_INFLATION",
    "PRESETS",
    "SMOOTHED_POSE_COV_INFLATION",
    "SMOOTHED_TREE_COV_INFLATION",
    "TREE_COV_INFLATION",
    "FastSlam",
    "particle_landmark_covariance",
    "systematic_resample",
    "weighted_pose_covariance",
]

log = logging.getLogger(__name__)

#: Variance factor from the particle set's pose covariance (the weighted spread of the particles'
#: poses at each frame, :func:`weighted_pose_covariance`) to the reported ``pose_covs``, and from
#: the landmark mixture covariance (:func:`particle_landmark_covariance`) to the reported tree
#: covariance. The particle set under-represents the path uncertainty (its paths coalesce to one
#: ancestor within ~50 s on Victoria Park: path degeneracy, Bailey et al. 2006), so both are
#: inflated by factors estimated on the FIRST half of the Victoria Park run (t < 775 s, seeds
#: 0-4, defaults; laser-point error against the screened GPS after the ATE's SE(2) alignment,
#: tree error against iSAM2's tree) so that the median z^2 = e^T C^-1 e is 2 ln 2 = 1.386 (the
#: chi-square median for 2 dof), and checked on the SECOND half: pose median z^2 1.72, trees
#: 1.06 (docs/algorithms/slam.md, "FastSLAM covariance"; benchmarks/fastslam_covariance.py
#: --vp-calibration). A std factor of ~30 (pose) and ~41 (trees).
POSE_COV_INFLATION = 930.0
TREE_COV_INFLATION = 1670.0

#: The same for the jointly smoothed output (``smooth=True``, the default): variance factors
#: from the smoothed pose's covariance given the smoothed map (the EKF smoother's chain
#: marginals, :func:`stemmap.slam._ekf_smooth.chain_marginals`) and from each tree's joint
#: marginal (:func:`stemmap.slam._fastslam_smooth.smooth_joint`), chosen the same way (first
#: half of Victoria Park, seeds 0-4, checked on the second half; docs/algorithms/slam.md,
#: "FastSLAM joint smoothing"; benchmarks/fastslam_covariance.py --vp-calibration, re-run on
#: branch fslam18b with the re-association and the map term that ``smooth_path`` now adds:
#: second half median z^2 1.10 (pose) / 1.14 (trees)). A std factor of ~4.6 (pose) and ~3.5
#: (trees).
SMOOTHED_POSE_COV_INFLATION = 21.4
SMOOTHED_TREE_COV_INFLATION = 12.5

#: Published parameter sets: ``"munjer2025"`` = 100 particles (Munjer et al. 2025, Table 1).
PRESETS: dict[str, dict[str, float | int]] = {"munjer2025": {"n_particles": 100}}


@dataclass
class FastSlam:
    """FastSLAM 1.0 back-end (Munjer et al. 2025 §3.6; Montemerlo et al. 2002).

    Parameters
    ----------
    preset : str, optional
        ``"munjer2025"`` (100 particles).
    n_particles : int
        P (paper: 100).
    sigma_range : float, m
    sigma_bearing : float, rad
        Detection noise R = diag(σ_r², σ_φ²). Defaults 0.5 m / 2° (issue 18): the weight
        multiplies the likelihoods of all detections of a frame, and a trunk centre's
        viewpoint-dependent error persists over many scans; with 0.3 m / 1° the weights
        collapsed (resampling in 61 % of the Victoria Park frames, 36 % now).
    new_landmark_chi2 : float
        A detection starts a new landmark when its best candidate's log-likelihood is below that
        of a detection at squared Mahalanobis distance ``new_landmark_chi2`` from a landmark whose
        innovation covariance is 2R (a freshly initialised one) -- Montemerlo's ``p0``.
    resample_threshold : float in (0, 1]
        Resample when ESS < threshold * P.
    max_candidates : int
        Landmarks per particle considered for association: among those within the frame's
        maximum detection range + ``window_margin`` of the sensor, the ones closest to any of
        the frame's detections (mapped with the particle's pose).
    window_margin : float, m
    min_observations : int
        Landmarks of the best particle seen fewer times are left out of the output map (and
        tentative ones are pruned, see ``tentative_timeout_s``). Default 5 (was 3): on
        Victoria Park 3 kept ~505 trees against iSAM2's 392 and the EKF's 414, 5 keeps ~397.
    min_new_separation : float, m
        Ours: a detection that matches no landmark but lies closer than this to one of the
        particle's landmarks is skipped for the frame rather than starting a new landmark (two
        trunks closer than 1 m are rare; such a detection is far more often the same tree seen
        with a slightly wrong pose). 0 disables.
    version : {1, 2}
        1 = FastSLAM 1.0 (motion-model proposal; Munjer cites Montemerlo's FastSLAM), 2 = ours:
        the FastSLAM 2.0 proposal (pose sampled from the motion prediction fused with this
        frame's matched detections, batch form), for odometry much noisier than the laser.
    smooth : bool
        Ours (docs/algorithms/slam.md, "FastSLAM joint smoothing"): after the filter, the path
        and the trees are re-estimated jointly by least squares on the odometry and on the
        detections the best particle's lineage associated with a mapped tree
        (:mod:`stemmap.slam._fastslam_smooth`), so that a loop closure corrects the trees and
        poses of the stretch before it; trees the smoothing brings within ``merge_dist`` are
        merged and the problem solved again (up to ``merge_rounds`` times). The raw filter
        path is in ``diagnostics["raw_trajectory"]`` with ``record_diagnostics``. False: the
        filter's output (Munjer's pipeline, :mod:`stemmap.slam.munjer`).
    merge_dist, merge_ddiam : float, m
        With ``smooth``: smoothed trees closer than ``merge_dist`` with diameters within
        ``merge_ddiam`` (or overlapping trunks) are one tree (iSAM2's rule and values,
        :func:`stemmap.slam._graph_marginals._merge_duplicates`). 0 disables.
    merge_rounds : int
        Rounds of merging and (with ``reassociate``) re-association, each followed by a new
        solve, after the first smoothing; they stop early when a round changes nothing.
        Default 4 (was 2 before the re-association), chosen on Victoria Park seeds 0-4 by a
        GPS-free score (docs/algorithms/slam.md, "FastSLAM joint smoothing").
    reassociate : bool
        Ours, with ``smooth``: after each solve, every detection of the run is re-assigned to
        the smoothed tree it fits best under ``R`` within the ``new_landmark_chi2`` gate
        (:func:`stemmap.slam._fastslam_smooth.nearest_tree_association`) and the problem
        solved again (docs/algorithms/slam.md, "FastSLAM joint smoothing").
    pose_cov_inflation, tree_cov_inflation : float or None
        Variance factors to ``SlamResult.pose_covs`` and each tree's ``cov``: without
        ``smooth``, from the particle set's pose covariance and the landmark mixture
        covariance (defaults :data:`POSE_COV_INFLATION`, :data:`TREE_COV_INFLATION`); with
        ``smooth``, from the smoothed pose's covariance given the smoothed map and the trees'
        joint marginals (defaults :data:`SMOOTHED_POSE_COV_INFLATION`,
        :data:`SMOOTHED_TREE_COV_INFLATION`). All chosen on the first half of Victoria Park;
        1 gives the raw covariances.
    record_diagnostics : bool
        Keep per-frame diagnostics in ``self.diagnostics`` after ``run`` (effective sample
        size, resampling flags, parent indices, particle poses, association counts, raw pose
        covariance; ~3 P floats per frame) for benchmarks and analysis.
    detection_noise : bool
        Ours: each detection's own noise (``problem.frames.noise``, e.g. DAIM's depth-noise
        model) is added to R, ``R_k = diag(σ_r² + σ_r,k², σ_φ² + σ_φ,k²)`` (NaN: none added), in
        the association, the landmark updates and initialisation and the weights; ``R`` stays
        the floor for what the detector's model leaves out (pose, association, the trunk
        centre's viewpoint error). Needs ``version=1`` and ``smooth=False``. False: R for
        every detection (the frames' noise ignored).
    path : {"best", "mean"}
        The output path: the best particle's lineage ("best", Montemerlo's usual output; the
        map is always the best particle's), or the posterior mean over the final particles'
        lineages ("mean", ours: :func:`~stemmap.slam._fastslam_particles.posterior_mean_path`),
        which does not depend on which near-equal weight happens to be the largest. "mean"
        needs ``smooth=False``.
    tentative_timeout_s : float, s
        Ours (standard FastSLAM landmark-existence practice, not in Munjer): a landmark seen
        fewer than ``min_observations`` times and not re-seen for this long is deleted from the
        particle's map (checked every 25 frames; 0 disables). Keeps clutter from piling up.
    seed : int
    """

    preset: str | None = None
    n_particles: int = 100
    sigma_range: float = 0.5
    sigma_bearing: float = math.radians(2.0)
    new_landmark_chi2: float = 13.8
    resample_threshold: float = 0.5
    max_candidates: int = 24
    window_margin: float = 3.0
    min_observations: int = 5
    tentative_timeout_s: float = 5.0
    min_new_separation: float = 1.0
    version: int = 1
    smooth: bool = True
    merge_dist: float = 1.0
    merge_ddiam: float = 0.42
    merge_rounds: int = 4
    reassociate: bool = True
    pose_cov_inflation: float | None = None
    tree_cov_inflation: float | None = None
    record_diagnostics: bool = False
    detection_noise: bool = False
    path: Literal["best", "mean"] = "best"
    seed: int = 0
    name: str = "fastslam"
    #: filled by ``run`` when ``record_diagnostics`` is set
    diagnostics: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)
    #: version 1 runs the compiled per-particle kernel (:mod:`stemmap.slam._fastslam_kernel`);
    #: False runs the same steps as numpy array operations (the reference the tests compare to)
    _kernel = True

    def __post_init__(self) -> None:
        if self.preset is not None:
            if self.preset not in PRESETS:
                raise ConfigError(
                    f"unknown FastSlam preset {self.preset!r}; choose from {sorted(PRESETS)}."
                )
            self.n_particles = int(PRESETS[self.preset]["n_particles"])
        if int(self.n_particles) < 1:
            raise ConfigError(f"FastSlam.n_particles must be >= 1, got {self.n_particles}.")
        if not (self.sigma_range > 0 and self.sigma_bearing > 0):
            raise ConfigError("FastSlam: sigma_range and sigma_bearing must be > 0.")
        if not 0 < self.resample_threshold <= 1:
            raise ConfigError(
                f"FastSlam.resample_threshold must be in (0, 1], got {self.resample_threshold}."
            )
        if int(self.max_candidates) < 1 or int(self.min_observations) < 1:
            raise ConfigError("FastSlam: max_candidates and min_observations must be >= 1.")
        if self.version not in (1, 2):
            raise ConfigError(f"FastSlam.version must be 1 or 2, got {self.version}.")
        if self.detection_noise and (self.version != 1 or self.smooth):
            raise ConfigError(
                "FastSlam.detection_noise needs version=1 and smooth=False (per-detection R is "
                "carried by the compiled FastSLAM 1.0 filter only)."
            )
        if self.path not in ("best", "mean") or (self.path == "mean" and self.smooth):
            raise ConfigError(
                f"FastSlam.path must be 'best' or 'mean' (with smooth=False), got {self.path!r}."
            )
        if not self.new_landmark_chi2 > 0:
            raise ConfigError("FastSlam.new_landmark_chi2 must be > 0.")
        if self.pose_cov_inflation is None:
            self.pose_cov_inflation = (
                SMOOTHED_POSE_COV_INFLATION if self.smooth else POSE_COV_INFLATION
            )
        if self.tree_cov_inflation is None:
            self.tree_cov_inflation = (
                SMOOTHED_TREE_COV_INFLATION if self.smooth else TREE_COV_INFLATION
            )
        if not (self.pose_cov_inflation > 0 and self.tree_cov_inflation > 0):
            raise ConfigError("FastSlam: pose_cov_inflation and tree_cov_inflation must be > 0.")

    # ----------------------------------------------------------------------------------------
    def run(
        self, problem: SlamProblem, *, progress: Callable[[int, int], None] | None = None
    ) -> SlamResult:
        """Run the particle filter over ``problem``; see the module docstring."""
        from stemmap.slam._fastslam_smooth import smooth_fastslam
        from stemmap.slam.base import SlamResult, frame_trajectory
        from stemmap.slam.motion import compose, preintegrate_spans

        t_start = _time.perf_counter()
        rng = np.random.default_rng(self.seed)
        frames = problem.frames
        nf = len(frames)
        P = int(self.n_particles)
        off = problem.sensor_offset
        pre = preintegrate_spans(
            problem.motion, problem.controls, frames.times, np.asarray(problem.initial_pose)
        )
        R = np.diag([self.sigma_range**2, self.sigma_bearing**2])
        _, det_new = _inv2(2.0 * R)
        log_p0 = -0.5 * self.new_landmark_chi2 - 0.5 * math.log((2 * math.pi) ** 2 * det_new)
        # per detection: R's diagonal and the new-landmark log-likelihood (constant without
        # detection_noise)
        kk = frames.n_detections
        r_diag = np.tile(np.diag(R), (kk, 1))
        if self.detection_noise and frames.noise is not None:
            r_diag = r_diag + np.nan_to_num(frames.noise) ** 2
        per_det = self.detection_noise and frames.noise is not None
        lp0 = -0.5 * self.new_landmark_chi2 - 0.5 * np.log(
            (2 * math.pi) ** 2 * 4.0 * r_diag[:, 0] * r_diag[:, 1]
        )
        if not per_det:
            lp0[:] = log_p0
        if per_det and not self._kernel:
            raise ConfigError("FastSlam.detection_noise needs the compiled filter (_kernel).")
        r00_all = np.ascontiguousarray(r_diag[:, 0])
        r11_all = np.ascontiguousarray(r_diag[:, 1])

        X = np.tile(np.asarray(problem.initial_pose, dtype=np.float64), (P, 1))
        cap = 64
        mu = np.zeros((P, cap, 2))
        Sig = np.zeros((P, cap, 2, 2))
        nobs = np.zeros((P, cap), dtype=np.int64)
        dsum = np.zeros((P, cap))
        dcnt = np.zeros((P, cap), dtype=np.int64)
        tfirst = np.zeros((P, cap))
        tlast = np.zeros((P, cap))
        nlm = np.zeros(P, dtype=np.int64)
        # smoothing: a landmark id per slot (inherited through resampling, kept by compaction)
        # and per frame the id each particle's detections went to (-1: none)
        lid = np.full((P, cap), -1, dtype=np.int64)
        next_lid = 0
        obs_lid: dict[int, np.ndarray] = {}
        logw = np.zeros(P)
        pose_hist = np.empty((nf, P, 3))
        parents = np.empty((nf, P), dtype=np.int64)
        # per frame: effective sample size after the weight update (NaN: no detection) and the
        # weighted particle covariance of the vehicle pose (the filter's marginal, before any
        # resampling of that frame)
        ess_hist = np.full(nf, np.nan)
        pose_cov = np.zeros((nf, 3, 3))
        w_cur = np.full(P, 1.0 / P)
        # per frame, mean over particles: detections matched / starting a landmark / skipped
        assoc_counts = np.zeros((nf, 3))
        resampled = np.zeros(nf, dtype=bool)
        ident = np.arange(P, dtype=np.int64)
        n_resample = 0
        n_pruned = 0
        rows = np.arange(P)[:, None]
        sep2 = self.min_new_separation**2 if self.min_new_separation > 0 else 0.0
        # square roots of the motion covariances (version 1 samples them every frame)
        sq_motion = _psd_sqrt_stack(np.asarray(pre.covs)) if nf > 1 else np.zeros((0, 3, 3))

        for f in range(nf):
            parents[f] = ident
            r, b, d = frames.frame(f)
            k = r.shape[0]
            rows_f = slice(int(frames.ptr[f]), int(frames.ptr[f + 1]))
            lp0_f = lp0[rows_f]
            tf = float(frames.times[f])
            v2 = self.version == 2 and k > 0 and f > 0
            if f > 0:
                if v2:
                    # FastSLAM 2.0: keep the predicted mean; the pose is sampled below from the
                    # proposal that includes this frame's detections
                    X = compose(X, pre.deltas[f - 1][None, :])
                    G = np.zeros((P, 3, 3))
                    cth, sth = np.cos(X[:, 2]), np.sin(X[:, 2])
                    G[:, 0, 0], G[:, 0, 1], G[:, 1, 0], G[:, 1, 1] = cth, -sth, sth, cth
                    G[:, 2, 2] = 1.0
                    Qw = G @ np.nan_to_num(pre.covs[f - 1]) @ np.swapaxes(G, 1, 2)
                else:
                    # = _sample_gaussian(pre.covs[f - 1], P, rng), square roots precomputed
                    noise = rng.standard_normal((P, 3)) @ sq_motion[f - 1].T
                    X = compose(X, pre.deltas[f - 1][None, :] + noise)
                    v2 = False
            if k:
                M = min(int(self.max_candidates), int(nlm.max()))
                if self.version == 1 and self._kernel:
                    # the numpy block below, particle by particle (same operations, compiled)
                    ll_best = np.empty((P, k))
                    assoc = np.empty((P, k), dtype=np.int64)
                    rmax = float(r.max()) + self.window_margin
                    associate_update(
                        X, mu, Sig, nlm, nobs, tlast, dsum, dcnt, r, b, d,
                        float(off[0]), float(off[1]), r00_all[rows_f], r11_all[rows_f], lp0_f,
                        int(self.max_candidates), rmax * rmax, sep2, tf, assoc, ll_best,
                    )  # fmt: skip
                    M = 0
                else:
                    ll_best = np.full((P, k), -np.inf)
                    assoc = np.full((P, k), -1, dtype=np.int64)
                if M > 0:
                    # candidates: the M nearest existing landmarks of each particle
                    c_all = mu.shape[1]
                    valid = np.arange(c_all)[None, :] < nlm[:, None]
                    sx = X[:, 0] + off[0] * np.cos(X[:, 2]) - off[1] * np.sin(X[:, 2])
                    sy = X[:, 1] + off[0] * np.sin(X[:, 2]) + off[1] * np.cos(X[:, 2])
                    ddx = mu[:, :, 0] - sx[:, None]
                    ddy = mu[:, :, 1] - sy[:, None]
                    dist2 = ddx * ddx + ddy * ddy
                    # window of this frame: range and bearing span of its detections + margin
                    rmax = float(r.max()) + self.window_margin
                    near = valid & (dist2 <= rmax * rmax)
                    pp, cc = np.nonzero(near)
                    # rank landmarks by their distance to the nearest detection of this frame
                    # (as predicted by the particle): far trees are not crowded out by near ones
                    ang_o = X[:, 2][:, None] + b[None, :]
                    ox = sx[:, None] + r[None, :] * np.cos(ang_o)  # (P, K)
                    oy = sy[:, None] + r[None, :] * np.sin(ang_o)
                    mu_near = mu[near]  # (N, 2), the order of (pp, cc)
                    oxp, oyp = ox[pp], oy[pp]
                    gx = np.subtract(mu_near[:, 0][:, None], oxp, out=oxp)
                    gy = np.subtract(mu_near[:, 1][:, None], oyp, out=oyp)
                    gx *= gx
                    gy *= gy
                    gx += gy
                    dist2 = np.full(near.shape, np.inf)
                    dist2[pp, cc] = np.min(gx, axis=1)
                    if c_all > M:
                        cand = np.argpartition(dist2, M - 1, axis=1)[:, :M]
                    else:
                        cand = np.broadcast_to(np.arange(c_all), (P, c_all))[:, :M]
                    cvalid = np.take_along_axis(dist2, cand, axis=1) < np.inf  # (P, M)
                    m_mu = mu[rows, cand]  # (P, M, 2)
                    m_S = Sig[rows, cand]  # (P, M, 2, 2)
                    if v2:  # association and weight use the predicted pose's uncertainty too
                        zp, Hx, Hm = range_bearing_jacobians(X[:, None, :], m_mu, off)
                        S = Hm @ m_S @ np.swapaxes(Hm, -1, -2) + R
                        S_full = S + Hx @ Qw[:, None] @ np.swapaxes(Hx, -1, -2)
                        Sinv, detS = _inv2(S_full)
                        zp0, zp1 = zp[..., 0], zp[..., 1]
                        i00, i01 = Sinv[..., 0, 0], Sinv[..., 0, 1]
                        i10, i11 = Sinv[..., 1, 0], Sinv[..., 1, 1]
                    else:
                        zp0, zp1, i00, i01, i10, i11, detS = _predict_and_inv(
                            X, m_mu, m_S, off, R[0, 0], R[1, 1]
                        )
                    # innovations (P, K, M) per component
                    nu0 = r[None, :, None] - zp0[:, None, :]
                    nu1 = b[None, :, None] - zp1[:, None, :]
                    _wrap_inplace(nu1)
                    # d2 = nu^T S^-1 nu, summed in einsum's order (i outer, j inner)
                    d2 = nu0 * i00[:, None, :] * nu0
                    d2 += nu0 * i01[:, None, :] * nu1
                    d2 += nu1 * i10[:, None, :] * nu0
                    d2 += nu1 * i11[:, None, :] * nu1
                    ll = -0.5 * d2
                    ll -= 0.5 * np.log((2 * math.pi) ** 2 * detS)[:, None, :]
                    ll[~np.broadcast_to(cvalid[:, None, :], ll.shape)] = -np.inf
                    jbest = np.argmax(ll, axis=2)  # (P, K)
                    ll_best = np.take_along_axis(ll, jbest[..., None], axis=2)[..., 0]
                    is_match = ll_best >= log_p0
                    if self.min_new_separation > 0:
                        # a detection that fails the likelihood test but lies within
                        # min_new_separation of one of the particle's landmarks is ambiguous:
                        # drop it for this frame instead of starting a duplicate (ours)
                        ex = m_mu[:, None, :, 0] - ox[:, :, None]  # (P, K, M)
                        ey = m_mu[:, None, :, 1] - oy[:, :, None]
                        close = np.any(
                            cvalid[:, None, :] & (ex * ex + ey * ey < self.min_new_separation**2),
                            axis=2,
                        )
                        assoc[~is_match & close] = -2
                    # resolve conflicts: one detection per landmark per particle
                    pk_p, pk_k = np.nonzero(is_match)
                    if pk_p.size:
                        key = pk_p * M + jbest[pk_p, pk_k]
                        order = np.lexsort((-ll_best[pk_p, pk_k], key))
                        first = np.r_[True, key[order][1:] != key[order][:-1]]
                        win = order[first]
                        lose = order[~first]
                        wp, wk = pk_p[win], pk_k[win]
                        wm = jbest[wp, wk]
                        lm = cand[wp, wm]
                        assoc[wp, wk] = lm
                        if v2:
                            # proposal N(mu_x, Sig_x): Sig_x^-1 = Q^-1 + sum Hx^T S^-1 Hx,
                            # mu_x = x_pred + Sig_x sum Hx^T S^-1 nu (batch over the detections)
                            Sm_inv, _ = _inv2(S[wp, wm])
                            HxT = np.swapaxes(Hx[wp, wm], 1, 2)
                            A = HxT @ Sm_inv @ Hx[wp, wm]
                            nu_w = np.column_stack((nu0[wp, wk, wm], nu1[wp, wk, wm]))
                            bvec = np.einsum("nij,nj->ni", HxT @ Sm_inv, nu_w)
                            info = np.linalg.inv(Qw + 1e-12 * np.eye(3))
                            np.add.at(info, wp, A)
                            rhs = np.zeros((P, 3))
                            np.add.at(rhs, wp, bvec)
                            Sx = np.linalg.inv(info)
                            Sx = 0.5 * (Sx + np.swapaxes(Sx, 1, 2))
                            mx = X + np.einsum("pij,pj->pi", Sx, rhs)
                            X = mx + _sample_batch(Sx, rng)
                            X[:, 2] = wrap_angle(X[:, 2])
                            v2 = False  # sampled
                        # EKF update of the matched landmarks (unique (p, lm) pairs) at the
                        # (sampled) pose
                        z = np.column_stack((r[wk], b[wk]))
                        _ekf_update(mu, Sig, wp, lm, X[wp], z, off, R[0, 0], R[1, 1])
                        nobs[wp, lm] += 1
                        tlast[wp, lm] = tf
                        dd = d[wk]
                        okd = np.isfinite(dd)
                        dsum[wp[okd], lm[okd]] += dd[okd]
                        dcnt[wp[okd], lm[okd]] += 1
                        # losers of a conflict: dropped for this frame (weight as p0)
                        assoc[pk_p[lose], pk_k[lose]] = -2
                if v2:  # no detection matched in any particle: sample the motion model
                    X = X + _sample_batch(Qw, rng)
                    X[:, 2] = wrap_angle(X[:, 2])
                # weights: matched -> likelihood, otherwise p0
                logw += np.sum(np.where(assoc >= 0, ll_best, lp0_f if per_det else log_p0), axis=1)
                # new landmarks
                new = assoc == -1
                assoc_counts[f] = (
                    np.count_nonzero(assoc >= 0) / P,
                    np.count_nonzero(new) / P,
                    np.count_nonzero(assoc == -2) / P,
                )
                n_new = new.sum(axis=1)
                if self.smooth:
                    rec = np.full((P, k), -1, dtype=np.int32)
                    mt = assoc >= 0
                    rec[mt] = lid[np.nonzero(mt)[0], assoc[mt]]
                    obs_lid[f] = rec
                if np.any(n_new):
                    need = int((nlm + n_new).max())
                    if need > mu.shape[1]:
                        grow = max(need, 2 * mu.shape[1]) - mu.shape[1]
                        mu = np.concatenate((mu, np.zeros((P, grow, 2))), axis=1)
                        Sig = np.concatenate((Sig, np.zeros((P, grow, 2, 2))), axis=1)
                        nobs = np.concatenate((nobs, np.zeros((P, grow), np.int64)), axis=1)
                        dsum = np.concatenate((dsum, np.zeros((P, grow))), axis=1)
                        dcnt = np.concatenate((dcnt, np.zeros((P, grow), np.int64)), axis=1)
                        tfirst = np.concatenate((tfirst, np.zeros((P, grow))), axis=1)
                        tlast = np.concatenate((tlast, np.zeros((P, grow))), axis=1)
                        lid = np.concatenate((lid, np.full((P, grow), -1, np.int64)), axis=1)
                    np_, nk = np.nonzero(new)
                    slot = nlm[np_] + (np.cumsum(new, axis=1) - 1)[np_, nk]
                    Xp = X[np_]
                    c, s = np.cos(Xp[:, 2]), np.sin(Xp[:, 2])
                    sxn = Xp[:, 0] + off[0] * c - off[1] * s
                    syn = Xp[:, 1] + off[0] * s + off[1] * c
                    ang = Xp[:, 2] + b[nk]
                    mxy = np.column_stack((sxn + r[nk] * np.cos(ang), syn + r[nk] * np.sin(ang)))
                    _, _, Hn = range_bearing_jacobians(Xp, mxy, off)
                    Hinv, _ = _inv2(Hn)
                    mu[np_, slot] = mxy
                    if per_det:
                        Rn = np.zeros((nk.size, 2, 2))
                        Rn[:, 0, 0], Rn[:, 1, 1] = r00_all[rows_f][nk], r11_all[rows_f][nk]
                        Sig[np_, slot] = Hinv @ Rn @ np.swapaxes(Hinv, 1, 2)
                    else:
                        Sig[np_, slot] = Hinv @ R @ np.swapaxes(Hinv, 1, 2)
                    nobs[np_, slot] = 1
                    dd = d[nk]
                    okd = np.isfinite(dd)
                    dsum[np_, slot] = np.where(okd, dd, 0.0)
                    dcnt[np_, slot] = okd.astype(np.int64)
                    tfirst[np_, slot] = tf
                    tlast[np_, slot] = tf
                    if self.smooth:
                        ids = next_lid + np.arange(np_.size)
                        next_lid += np_.size
                        lid[np_, slot] = ids
                        obs_lid[f][np_, nk] = ids
                    nlm = nlm + n_new
                # resample on low effective sample size
                logw -= logw.max()
                w = np.exp(logw)
                w /= w.sum()
                ess = 1.0 / float(np.sum(w * w))
                ess_hist[f] = ess
                pose_cov[f] = weighted_pose_covariance(X, w)
                w_cur = w
                if ess < self.resample_threshold * P:
                    idx = systematic_resample(w, rng)
                    parents[f] = idx
                    X = X[idx]
                    # in place, landmarks in use only; the capacity is kept (no regrowth)
                    resample_inplace(idx, nlm, mu, Sig, nobs, dsum, dcnt, tfirst, tlast)
                    if self.smooth:
                        ch = idx != ident
                        lid[ch] = lid[idx[ch]]
                    logw = np.zeros(P)
                    n_resample += 1
                    resampled[f] = True
                    w_cur = np.full(P, 1.0 / P)
                else:
                    logw = np.log(np.maximum(w, 1e-300))
            if self.tentative_timeout_s > 0 and f % 25 == 24 and int(nlm.max()) > 0:
                # drop tentative landmarks (seen < min_observations times) not re-seen within
                # the timeout: clutter and one-off false detections (compaction per particle)
                top = int(nlm.max())
                slots = np.arange(top)[None, :]
                keep = (slots < nlm[:, None]) & (
                    (nobs[:, :top] >= self.min_observations)
                    | (tlast[:, :top] > tf - self.tentative_timeout_s)
                )
                if not np.all(keep == (slots < nlm[:, None])):
                    n_pruned += int(nlm.sum() - keep.sum())
                    if self.smooth:
                        for p_ in range(P):
                            kp = keep[p_, : nlm[p_]]
                            lid[p_, : int(kp.sum())] = lid[p_, : nlm[p_]][kp]
                    compact_inplace(keep, nlm, mu, Sig, nobs, dsum, dcnt, tfirst, tlast)
            if not k:
                pose_cov[f] = weighted_pose_covariance(X, w_cur)
            pose_hist[f] = X
            if progress is not None and (f % 200 == 0 or f == nf - 1):
                progress(f + 1, nf)

        best = int(np.argmax(logw))
        # back-track the ancestry of the best particle
        traj = np.empty((nf, 3))
        cur = best
        lineage_ids: list[tuple[int, np.ndarray]] = []  # (frame, landmark id per detection)
        for f in range(nf - 1, -1, -1):
            traj[f] = pose_hist[f, cur]
            cur = int(parents[f, cur])
            if f in obs_lid:  # the associations of the particle before this frame's resampling
                lineage_ids.append((f, obs_lid[f][cur]))
        if self.path == "mean":
            traj = posterior_mean_path(pose_hist, parents, logw)
        n_best = int(nlm[best])
        mapped = np.flatnonzero(nobs[best, :n_best] >= self.min_observations)
        w_final = np.exp(logw - logw.max())
        # the filter's own covariances (replaced by the smoothed ones with ``smooth``)
        pf_fac = float(POSE_COV_INFLATION if self.smooth else self.pose_cov_inflation or 1.0)
        tf_fac = float(TREE_COV_INFLATION if self.smooth else self.tree_cov_inflation or 1.0)
        trees = []
        for new_id, j in enumerate(mapped):
            dia = dsum[best, j] / dcnt[best, j] if dcnt[best, j] > 0 else math.nan
            trees.append(
                Tree(
                    id=new_id,
                    x=float(mu[best, j, 0]),
                    y=float(mu[best, j, 1]),
                    diameter=float(dia),
                    cov=tf_fac * particle_landmark_covariance(mu, Sig, nlm, w_final, best, int(j)),
                    n_obs=int(nobs[best, j]),
                    first_time=float(tfirst[best, j]),
                    last_time=float(tlast[best, j]),
                )
            )
        pose_covs = pf_fac * pose_cov
        raw_traj = traj.copy()
        smooth_stats: dict[str, float | int] = {}
        if self.smooth and trees:
            traj, trees, pose_covs, smooth_stats = smooth_fastslam(
                self, problem, pre, traj, trees, lid[best, mapped], lineage_ids, R
            )
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "n_particles": P,
            "landmarks_best_particle": n_best,
            "landmarks_mapped": len(trees),
            "resamples": n_resample,
            "ess_median": float(np.nanmedian(ess_hist)) if np.any(np.isfinite(ess_hist)) else P,
            "tentative_pruned_total": n_pruned,
            **smooth_stats,
            "runtime_s": float(_time.perf_counter() - t_start),
        }
        if self.record_diagnostics:
            self.diagnostics = {
                "ess": ess_hist,
                "resampled": resampled,
                "parents": parents,
                "pose_hist": pose_hist,
                "best": best,
                "assoc_counts": assoc_counts,
                "pose_cov_spread": pose_cov,
                "raw_trajectory": raw_traj,
            }
        return SlamResult(
            frame_trajectory(frames.times, traj),
            StemMap(tuple(trees)),
            stats,
            pose_covs=pose_covs,
        )
