"""Trajectory relaxation after a loop closure (Öhman et al. 2007 §2.2, solved with GTSAM).

Öhman's Forestrix distributes "the accumulated error evenly e.g. when a large loop is being
closed" with "a simple iterative algorithm that tries to minimize and distribute the tensions"
of the tree graph. Here the tension is held by the *trajectory*: a chain of keyframe poses linked
by the front-end's relative motions (soft, sigma growing with the distance and the turn), plus
one relative-pose constraint per loop closure found by tree-group matching (robust Cauchy
kernel, so one wrong closure cannot bend the whole run). The relaxed keyframes carry the frames
between them rigidly, and the trees are then re-mapped from the relaxed poses
(:func:`remap_trees`). The method is the paper's (distribute the loop error over the loop);
the solver is GTSAM's Levenberg-Marquardt (a maintained nonlinear least-squares library) instead
of the paper's unspecified iteration.

Functions
---------
:func:`relax_trajectory`
    Keyframe pose graph + loop constraints -> relaxed poses of every frame.
:func:`loop_constraint`
    The relative pose a loop closure measures, from the rigid correction of the revisited map.
:func:`remap_trees`
    Tree positions as the mean of their detections projected with the (relaxed) poses.
:func:`fit_rigid_robust`
    Least-squares SE(2) fit of matched points with iterative trimming of outlier pairs.

References
----------
.. [Ohman2007] M. Öhman et al., "Tree Measurement and Simultaneous Localization and Mapping
   System for Forest Harvesters", FSR 2007, §2.2 (tree graph relaxation), Fig. 6 (a path
   traversed twice).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.eval.trajectory import align_se2
from stemmap.slam.motion import between, compose
from stemmap.types import FloatArray, wrap_angle

__all__ = [
    "LoopClosure",
    "RelaxNoise",
    "RigidFit",
    "fit_rigid_robust",
    "loop_constraint",
    "loop_measurements",
    "relax_trajectory",
    "relaxed_pose_covariances",
    "remap_trees",
]

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class LoopClosure:
    """A measured relative pose ``poses[j]^-1 ⊕ poses[i]`` between an older frame ``j`` and a
    newer frame ``i`` (frame indices), with its standard deviations (x, y in m, theta in rad)."""

    j: int
    i: int
    delta: tuple[float, float, float]
    sigmas: tuple[float, float, float] = (0.3, 0.3, math.radians(1.0))


@dataclass(frozen=True)
class RelaxNoise:
    """Noise of the front-end's relative motion between keyframes (the soft chain).

    ``sigma_xy = xy_base + xy_per_m * distance``, ``sigma_theta = theta_base + theta_per_rad *
    |turn| + theta_per_m * distance``. Defaults: scan-to-map odometry drifts ~1-2 % of the distance
    (Victoria Park, Forestrix without closures: 9 m ATE over a ~4 km run, locally 0.6-1.5 m per
    200-s window) -- so 2 % plus 5 cm per keyframe, and 0.2 deg per metre plus 2 % of the turn.
    Loop constraints are an order of magnitude tighter (0.3 m, 1 deg), so the chain bends; they
    carry a Cauchy kernel of width ``loop_robust_k`` whitened units (2.385: 95 % efficiency, the
    value the GNSS priors use) so that a wrong closure cannot bend the run.
    """

    xy_base: float = 0.05
    xy_per_m: float = 0.02
    theta_base: float = math.radians(0.1)
    theta_per_rad: float = 0.02
    theta_per_m: float = math.radians(0.2)
    loop_robust_k: float = 2.385

    def __post_init__(self) -> None:
        vals = (self.xy_base, self.theta_base)
        if (
            not all(v > 0 for v in vals)
            or min(self.xy_per_m, self.theta_per_rad, self.theta_per_m) < 0
        ):
            raise ConfigError("RelaxNoise: base sigmas must be > 0 and growth rates >= 0.")
        if not self.loop_robust_k > 0:
            raise ConfigError(f"RelaxNoise.loop_robust_k must be > 0, got {self.loop_robust_k}.")


def relax_trajectory(
    poses: ArrayLike,
    keyframes: ArrayLike,
    loops: list[LoopClosure],
    *,
    noise: RelaxNoise | None = None,
    max_iterations: int = 50,
    odometry_cov: ArrayLike | None = None,
) -> FloatArray:
    """Relax a trajectory with loop constraints (Öhman 2007 §2.2 relaxation; GTSAM LM solver).

    Parameters
    ----------
    poses : ndarray (F, 3)
        Front-end poses of frames ``0..F-1`` (x, y, theta).
    keyframes : ndarray (N,), int, increasing, starting at 0
        Frames that become graph nodes; every other frame follows its preceding keyframe
        rigidly. Loop endpoints are snapped to the nearest keyframe at or before them.
    loops : list of LoopClosure
    noise : RelaxNoise, optional
    max_iterations : int
    odometry_cov : ndarray (F, 3, 3), optional
        Covariance of the increment into each frame that the map did *not* constrain (frames
        the front-end could not correct: dead reckoning; zeros elsewhere). Summed per keyframe
        edge and added to its noise, so the relaxation puts the loop error where the
        trajectory was least certain instead of spreading it evenly.

    Returns
    -------
    ndarray (F, 3)
        Relaxed poses (the input is not modified). Without loops the input is returned unchanged.

    Raises
    ------
    InputError
        If the keyframes do not start at 0, are not increasing or are out of range.
    """
    p = np.array(poses, dtype=np.float64).reshape(-1, 3)
    kf = _check_keyframes(keyframes, p.shape[0])
    if not loops:
        return p
    graph, init, kp = _relax_graph(p, kf, loops, noise or RelaxNoise(), odometry_cov)
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    result = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    new_kp = np.array([[*_pose_xyt(result.atPose2(k))] for k in range(kp.shape[0])])
    # every frame follows its keyframe rigidly
    owner = np.searchsorted(kf, np.arange(p.shape[0]), side="right") - 1
    local = between(kp[owner], p)
    return compose(new_kp[owner], local)


def _check_keyframes(keyframes: ArrayLike, nf: int) -> IntArray:
    kf = np.asarray(keyframes, dtype=np.int64).reshape(-1)
    if kf.size == 0 or kf[0] != 0 or np.any(np.diff(kf) <= 0) or kf[-1] >= nf:
        raise InputError(
            f"relax_trajectory: keyframes must be increasing frame indices starting at 0 and "
            f"below {nf}, got {kf[:5].tolist()}...{kf[-1:].tolist()}."
        )
    return kf


def _chain_sigmas(rel: FloatArray, nz: RelaxNoise) -> FloatArray:
    """(n, 3) sigmas (x, y, theta) of the soft chain for relative motions ``rel`` (n, 3)."""
    dist = np.hypot(rel[:, 0], rel[:, 1])
    s_xy = nz.xy_base + nz.xy_per_m * dist
    s_th = nz.theta_base + nz.theta_per_rad * np.abs(rel[:, 2]) + nz.theta_per_m * dist
    return np.column_stack((s_xy, s_xy, s_th))


def _relax_graph(
    p: FloatArray,
    kf: IntArray,
    loops: list[LoopClosure],
    nz: RelaxNoise,
    odometry_cov: ArrayLike | None,
) -> tuple[Any, Any, FloatArray]:
    """The pose graph of :func:`relax_trajectory` (keys 0..N-1 = the keyframes) linearised
    about ``p``: (graph, initial values, keyframe poses)."""
    import gtsam

    nf = p.shape[0]
    kp = p[kf]
    rel = between(kp[:-1], kp[1:])
    sig_all = _chain_sigmas(rel, nz)
    extra = None
    if odometry_cov is not None:
        oc = np.asarray(odometry_cov, dtype=np.float64).reshape(-1, 3, 3)
        if oc.shape[0] < nf:
            raise InputError(f"relax_trajectory: odometry_cov has {oc.shape[0]} frames, need {nf}.")
        csum = np.concatenate((np.zeros((1, 3, 3)), np.cumsum(oc[:nf], axis=0)))
        extra = csum[kf[1:] + 1] - csum[kf[:-1] + 1]  # frames kf[k]+1 .. kf[k+1]
    graph = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-4, 1e-4, 1e-6]))
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*kp[0]), prior))
    for k in range(kp.shape[0]):
        init.insert(k, gtsam.Pose2(*kp[k]))
    for k in range(rel.shape[0]):
        sig = sig_all[k]
        if extra is not None and np.any(extra[k]):
            cov = np.diag(sig**2) + 0.5 * (extra[k] + extra[k].T)
            nm = gtsam.noiseModel.Gaussian.Covariance(cov)
        else:
            nm = gtsam.noiseModel.Diagonal.Sigmas(sig)
        graph.add(gtsam.BetweenFactorPose2(k, k + 1, gtsam.Pose2(*rel[k]), nm))
    cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(nz.loop_robust_k)
    for a, b, meas, lc in loop_measurements(p, kf, loops):
        base = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(lc.sigmas, dtype=np.float64))
        robust = gtsam.noiseModel.Robust.Create(cauchy, base)
        graph.add(gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(*meas), robust))
    return graph, init, kp


def loop_measurements(
    p: FloatArray, kf: IntArray, loops: list[LoopClosure]
) -> list[tuple[int, int, FloatArray, LoopClosure]]:
    """The loops as constraints between keyframes ``(a, b, measured kp[a]⁻¹ ⊕ kp[b], loop)``:
    endpoints snapped to the keyframe at or before them, the measured delta carried over the
    sub-keyframe offsets at ``p``; loops within one keyframe dropped."""
    nf = p.shape[0]
    out = []
    for lc in loops:
        if not (0 <= lc.j < nf and 0 <= lc.i < nf):
            raise InputError(f"relax_trajectory: loop {lc} refers to frames outside 0..{nf - 1}.")
        a = int(np.searchsorted(kf, lc.j, side="right")) - 1
        b = int(np.searchsorted(kf, lc.i, side="right")) - 1
        if a == b:
            continue
        off_a = between(p[kf[a]], p[lc.j])
        off_b = between(p[kf[b]], p[lc.i])
        out.append((a, b, compose(compose(off_a, np.asarray(lc.delta)), _inverse(off_b)), lc))
    return out


def relaxed_pose_covariances(
    poses: ArrayLike,
    keyframes: ArrayLike,
    loops: list[LoopClosure],
    *,
    noise: RelaxNoise | None = None,
    odometry_cov: ArrayLike | None = None,
    chain_variance_factor: float = 1.0,
) -> FloatArray:
    """(F, 3, 3) covariance of each frame's pose (x, y, θ in the map frame) in the pose graph
    of :func:`relax_trajectory`, at the final ``poses`` (ours; issue 14).

    The graph is the front-end's odometry between corrections -- the soft chain whose sigma
    grows with the distance and the turn (:class:`RelaxNoise`: the drift of scan-to-map /
    tree-DB odometry, plus the dead-reckoned frames' ``odometry_cov``) -- and the loop
    constraints (robust weights at ``poses``). Its marginals (``gtsam.Marginals``: the inverse
    of the Gauss-Newton information, Kaess et al. 2008) are the odometry covariance propagated
    from the fixed start and pulled in by every loop closure: open stretches grow, closed loops
    shrink. A frame between keyframes carries its keyframe's covariance with the partial
    chain noise of its offset ``r`` from it: ``Ad(r⁻¹) C Ad(r⁻¹)ᵀ + Q(r)`` (GTSAM's right
    perturbation), then rotated to the map frame. ``chain_variance_factor`` scales the
    variances of the :class:`RelaxNoise` chain only (a drift model for weighting the
    relaxation, not a calibrated noise: the factor is chosen per back-end on real data,
    docs/algorithms/slam.md); the dead-reckoned frames' ``odometry_cov`` (the motion model's)
    and the loop constraints keep theirs. Without loops the chain alone: the open-loop drift.
    """
    import gtsam

    from stemmap.slam._graph_revisits import _adjoint_inv

    p = np.array(poses, dtype=np.float64).reshape(-1, 3)
    kf = _check_keyframes(keyframes, p.shape[0])
    r = math.sqrt(chain_variance_factor)
    nz0 = noise or RelaxNoise()
    nz = dataclasses.replace(
        nz0,
        xy_base=r * nz0.xy_base,
        xy_per_m=r * nz0.xy_per_m,
        theta_base=r * nz0.theta_base,
        theta_per_rad=r * nz0.theta_per_rad,
        theta_per_m=r * nz0.theta_per_m,
    )
    graph, init, kp = _relax_graph(p, kf, loops, nz, odometry_cov)
    marg = gtsam.Marginals(graph, init)
    kc = np.array([marg.marginalCovariance(k) for k in range(kp.shape[0])])
    owner = np.searchsorted(kf, np.arange(p.shape[0]), side="right") - 1
    local = between(kp[owner], p)
    A = _adjoint_inv(local)
    q = np.zeros((p.shape[0], 3, 3))
    sub = np.flatnonzero(local.any(axis=1))  # frames off their keyframe
    q[sub] = np.einsum("ni,ij->nij", _chain_sigmas(local[sub], nz) ** 2, np.eye(3))
    if odometry_cov is not None:
        oc = np.asarray(odometry_cov, dtype=np.float64).reshape(-1, 3, 3)[: p.shape[0]]
        csum = np.cumsum(oc, axis=0)
        q += csum - csum[kf[owner]]  # dead-reckoned frames since the keyframe
    C = A @ kc[owner] @ np.swapaxes(A, 1, 2) + q
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    R = np.zeros_like(C)
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    out = R @ C @ np.swapaxes(R, 1, 2)
    return np.asarray(0.5 * (out + np.swapaxes(out, 1, 2)), dtype=np.float64)


def _pose_xyt(pose: object) -> tuple[float, float, float]:
    return (pose.x(), pose.y(), pose.theta())  # type: ignore[attr-defined]


def _inverse(d: FloatArray) -> FloatArray:
    return between(d, np.zeros(3))


def loop_constraint(
    pose_old: ArrayLike,
    pose_new: ArrayLike,
    fit: RigidFit,
) -> tuple[float, float, float]:
    """Relative pose measured by a loop closure.

    ``fit`` moves the newer part of the map onto the older trees it revisits; the newer pose
    moved the same way is where the vehicle really is relative to the older frame, so the
    constraint is ``pose_old^-1 ⊕ (fit ∘ pose_new)``.
    """
    corrected = fit.apply_pose(pose_new)
    d = between(np.asarray(pose_old, dtype=np.float64), corrected)
    return (float(d[0]), float(d[1]), float(d[2]))


@dataclass(frozen=True)
class RigidFit:
    """``p -> R(dtheta) p + t`` in the map frame, from :func:`fit_rigid_robust`.

    Falsy (``reason`` set) when too few pairs agree.
    """

    dtheta: float = 0.0
    t: tuple[float, float] = (0.0, 0.0)
    inliers: IntArray | None = None
    rms: float = math.inf
    reason: str = ""

    def __bool__(self) -> bool:
        return not self.reason

    def apply_points(self, xy: ArrayLike) -> FloatArray:
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.dtheta), math.sin(self.dtheta)
        out: FloatArray = q @ np.array([[c, s], [-s, c]]) + np.asarray(self.t)
        return out

    def apply_pose(self, pose: ArrayLike) -> FloatArray:
        p = np.asarray(pose, dtype=np.float64).reshape(3)
        xy = self.apply_points(p[:2])[0]
        return np.array([xy[0], xy[1], float(wrap_angle(p[2] + self.dtheta))])


def fit_rigid_robust(
    src: ArrayLike,
    dst: ArrayLike,
    *,
    inlier_dist: float = 1.0,
    min_inliers: int = 5,
    max_rms: float = 0.4,
    iterations: int = 5,
) -> RigidFit:
    """Least-squares SE(2) moving ``src`` onto ``dst`` (row pairs), trimming outlier pairs.

    Fit on all pairs and drop pairs whose residual exceeds ``max(inlier_dist, 3 x median)``,
    until stable (at most ``iterations`` times); then keep the pairs within ``inlier_dist``,
    refit and re-select. Falsy if fewer than ``min_inliers`` pairs remain or their RMS residual
    exceeds ``max_rms``.

    Examples
    --------
    >>> src = np.array([[0.0, 0], [4, 0], [0, 3], [5, 5], [2, 7]])
    >>> fit = fit_rigid_robust(src, src + [1.0, 2.0], min_inliers=3)
    >>> bool(fit), [round(v, 6) for v in fit.t]
    (True, [1.0, 2.0])
    >>> bool(fit_rigid_robust(src[:2], src[:2], min_inliers=3))
    False
    """
    a = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    if a.shape != b.shape:
        raise InputError(f"fit_rigid_robust: {a.shape[0]} source but {b.shape[0]} target points.")
    keep = np.arange(a.shape[0])
    need = max(int(min_inliers), 2)
    # trim with a data-driven cut (3 x the median residual, never below inlier_dist) ...
    for _ in range(int(iterations)):
        if keep.size < need:
            return RigidFit(reason=f"{keep.size} agreeing pairs, need {min_inliers}")
        al = align_se2(a[keep], b[keep])
        res = np.hypot(*(al.apply(a) - b).T)
        new = np.flatnonzero(res <= max(inlier_dist, 3.0 * float(np.median(res[keep]))))
        if np.array_equal(new, keep):
            break
        keep = new
    # ... then keep the pairs within inlier_dist, refit once and re-select
    for _ in range(2):
        if keep.size < need:
            return RigidFit(reason=f"{keep.size} agreeing pairs, need {min_inliers}")
        al = align_se2(a[keep], b[keep])
        res = np.hypot(*(al.apply(a) - b).T)
        keep = np.flatnonzero(res <= inlier_dist)
    if keep.size < need:
        return RigidFit(reason=f"{keep.size} agreeing pairs, need {min_inliers}")
    rms = float(np.sqrt(np.mean(res[keep] ** 2)))
    if rms > max_rms:
        return RigidFit(al.theta, al.t, keep, rms, f"rms {rms:.2f} m > {max_rms}")
    return RigidFit(al.theta, al.t, keep, rms)


def remap_trees(
    poses: ArrayLike,
    det_frame: ArrayLike,
    ranges: ArrayLike,
    bearings: ArrayLike,
    det_tree: ArrayLike,
    n_trees: int,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
) -> tuple[FloatArray, FloatArray]:
    """Tree positions as the mean of their detections mapped from ``poses``.

    Parameters
    ----------
    poses : ndarray (F, 3)
    det_frame : ndarray (K,), int -- frame of each detection
    ranges, bearings : ndarray (K,) -- sensor-frame polar detections
    det_tree : ndarray (K,), int -- tree of each detection (-1 = none)
    n_trees : int

    Returns
    -------
    xy : ndarray (n_trees, 2) -- NaN for trees without detections
    count : ndarray (n_trees,) -- detections per tree
    """
    from stemmap.slam.base import observation_to_world

    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    fr = np.asarray(det_frame, dtype=np.int64).reshape(-1)
    tr = np.asarray(det_tree, dtype=np.int64).reshape(-1)
    ok = tr >= 0
    w = observation_to_world(
        p[fr[ok]], np.asarray(ranges)[ok], np.asarray(bearings)[ok], sensor_offset
    )
    cnt = np.bincount(tr[ok], minlength=n_trees).astype(np.float64)
    sx = np.bincount(tr[ok], weights=w[:, 0], minlength=n_trees)
    sy = np.bincount(tr[ok], weights=w[:, 1], minlength=n_trees)
    with np.errstate(invalid="ignore", divide="ignore"):
        xy = np.column_stack((sx / cnt, sy / cnt))
    return xy, cnt
