"""Localisation mode of the iSAM2 back-end: the tracker localised on the map between updates (ours).

With ``Isam2Config.revisit_factors`` (:mod:`stemmap.slam._graph_revisits`) a keyframe that only
re-observes well-mapped trees stays out of the graph. Then no iSAM2 update follows it, and the
front-end tracker of :mod:`stemmap.slam._isam2_track` would run on alone: its per-scan MAP update
only uses *local* trees (those tied to the current estimate), so trees re-acquired after a gap
(step 4 of the tracker) never corrected the pose, and after the tracker's restart -- which makes
them local, with a tight gate -- a pose a metre off rejected them and started new trees there.
That is how the 10-pass replay lost the path (docs/reliability.md "Soak").

Here, at every restart after a left-out keyframe, the keyframe pose is **localised on the map**
(:func:`localise_on_map`): one small Gauss-Newton problem over the pose of the last left-out
keyframe, with

* every tree measurement of the left-out keyframes since the last restart (their windows'
  merged bearing-range measurements, already associated by the tracker, locals and re-acquired
  alike), moved into that keyframe's sensor frame with the dead-reckoned motion between, as 2D
  points with the covariance of the bearing-range noise plus the tree's own variance plus the
  dead reckoning's drift over that motion (its heading variance through the range: a few
  metres of driving, but in a sharp turn the odometry's heading error over two keyframes is
  ~2.6 degrees (1 sigma; 1.1 m at 25 m), and the 10x Victoria Park soak's turn at 733 s put
  the other keyframes' trees 2-3 m from the map even at the final pose, while the keyframe's
  own fitted to 0.2 m: docs/reliability.md "Soak", tenth session);
* the tracker's pose with its own covariance as the prior (it already holds the trees the
  tracker matched scan by scan: counting them twice only makes the map's pull stronger);
* a Huber weight per point and, after the first step, points beyond ``gate_chi2`` dropped
  (a wrong association must not pull the pose).

Fewer than ``min_trees`` trees measured (a transit, an edge of the stand) is no evidence either
way: the tracker dead-reckons on, as it did before.

The fit is **accepted** (the tracker restarts from it, as from an iSAM2 estimate) when at least
``min_trees`` trees remain and they are the majority of those measured. When they are not the
majority the tracker is **lost** as far as the map can tell, and the caller puts the next
keyframes into the graph (mapping mode: iSAM2 with its wide re-acquisition and the full graph
to restart from) until a fit is accepted again. A majority that fits but is fewer than
``min_trees`` (2 of 3 trees) is no contradiction: the tracker dead-reckons on (on the 10x
soak these were 2 well-mapped trees fitting the tracker's pose and 1-2 young trees
0.5-3 m off: a mis-association, not a lost tracker).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stemmap.types import FloatArray

__all__ = ["MapFix", "localise_on_map", "localise_windows", "restart_covariance"]


@dataclass(frozen=True)
class MapFix:
    """Result of :func:`localise_on_map`.

    ok : the fit is accepted; pose : (x, y, theta) sensor pose (the prior when not ok);
    lost : the trees measured (>= ``min_trees``) do not fit the map (not ok for lack of
    trees: ``lost`` is False);
    cov : (3, 3) its covariance (GN inverse information); n_trees : measured trees;
    n_inliers : trees within the gate at the end; reason : why not ok ("" when ok)
    """

    ok: bool
    lost: bool
    pose: FloatArray
    cov: FloatArray
    n_trees: int
    n_inliers: int
    reason: str = ""


def _points(
    rel: FloatArray, brg: FloatArray, rng: FloatArray, sig: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Measurements (bearing, range; sigmas (m, 2) = (σ_b, σ_r)) taken from sensor poses ``rel``
    (m, 3) given in the target keyframe's frame, as points and covariances in that frame."""
    ang = rel[:, 2] + brg
    ca, sa = np.cos(ang), np.sin(ang)
    pts = np.column_stack((rel[:, 0] + rng * ca, rel[:, 1] + rng * sa))
    vr = sig[:, 1] ** 2
    vt = (rng * sig[:, 0]) ** 2  # tangential
    cov = np.empty((brg.size, 2, 2))
    cov[:, 0, 0] = ca * ca * vr + sa * sa * vt
    cov[:, 1, 1] = sa * sa * vr + ca * ca * vt
    cov[:, 0, 1] = cov[:, 1, 0] = ca * sa * (vr - vt)
    return pts, cov


def localise_on_map(
    prior: FloatArray,
    rel: FloatArray,
    trees: np.ndarray,
    brg: FloatArray,
    rng: FloatArray,
    sig: FloatArray,
    tree_xy: FloatArray,
    tree_var: FloatArray,
    prior_cov: FloatArray,
    *,
    rel_var: FloatArray | None = None,
    huber_k: float = 1.345,
    gate_chi2: float = 13.8,
    min_trees: int = 3,
    iterations: int = 6,
) -> MapFix:
    """Sensor pose of one keyframe from its (and its neighbours') tree measurements on the map.

    Parameters
    ----------
    prior : (3,) the tracker's sensor pose of the keyframe (world, m and rad)
    rel : (m, 3) per measurement, the pose of the sensor that took it in the keyframe's frame
        (zeros for the keyframe's own measurements)
    trees : (m,) int, the tree of each measurement (index into ``tree_xy``)
    brg, rng : (m,) bearing (rad) and range (m); sig : (m, 2) their sigmas (σ_b, σ_r)
    tree_xy : (n, 2) tree positions (world, m); tree_var : (n,) their isotropic variances (m²)
    prior_cov : (3, 3) covariance of ``prior`` (the tracker's own, from the trees it tracked)
    rel_var : (m, 2) per measurement, the variances of ``rel`` (m² per axis, rad²: the dead
        reckoning's drift between the two keyframes, ``Isam2Slam``'s ``cum_xy`` / ``cum_th``),
        added to the point's covariance (the heading's through the range); None: exact
    huber_k : Huber width (in sigmas) of each point's Mahalanobis norm
    gate_chi2 : points whose d² exceeds this after the first step are dropped (2 dof;
        13.8 = chi²(0.999, 2))
    min_trees : trees that must remain for the fit to be accepted (and be the majority)

    Returns
    -------
    MapFix
    """
    prior = np.asarray(prior, dtype=np.float64)
    m = int(trees.size)
    lam0 = np.linalg.inv(prior_cov)
    n_trees = int(np.unique(trees).size) if m else 0
    if n_trees < min_trees:  # too little to tell: the caller dead-reckons on
        return MapFix(False, False, prior, prior_cov, n_trees, 0, f"only {n_trees} trees measured")
    pts, cov = _points(rel, brg, rng, sig)
    cov = cov + tree_var[trees][:, None, None] * np.eye(2)[None]
    if rel_var is not None:  # the dead-reckoned motion's drift (module doc)
        ang = rel[:, 2] + brg
        tx, ty = -np.sin(ang), np.cos(ang)  # tangential direction
        vt = rel_var[:, 1] * rng * rng
        cov[:, 0, 0] += rel_var[:, 0] + vt * tx * tx
        cov[:, 1, 1] += rel_var[:, 0] + vt * ty * ty
        cov[:, 0, 1] += vt * tx * ty
        cov[:, 1, 0] += vt * tx * ty
    info = np.linalg.inv(cov)
    lm = tree_xy[trees]
    x = prior.copy()
    use = np.ones(m, dtype=bool)
    lam = lam0
    d2 = np.zeros(m)
    for it in range(iterations):
        c, s = np.cos(x[2]), np.sin(x[2])
        dx, dy = lm[:, 0] - x[0], lm[:, 1] - x[1]
        px, py = c * dx + s * dy, -s * dx + c * dy  # the tree in the keyframe's sensor frame
        e = np.column_stack((pts[:, 0] - px, pts[:, 1] - py))  # measured - predicted
        d2 = np.einsum("mi,mij,mj->m", e, info, e)
        if it == 1:
            use &= d2 <= gate_chi2
        # Huber weight on the Mahalanobis norm
        dn = np.sqrt(d2)
        w = np.where(dn <= huber_k, 1.0, huber_k / np.maximum(dn, 1e-12)) * use
        # d(predicted)/d(x, y, theta): -R^T for the position, (py, -px) for the heading
        H = np.empty((m, 2, 3))
        H[:, 0, 0], H[:, 0, 1], H[:, 0, 2] = -c, -s, py
        H[:, 1, 0], H[:, 1, 1], H[:, 1, 2] = s, -c, -px
        WH = w[:, None, None] * np.einsum("mij,mjk->mik", info, H)
        lam = lam0 + np.einsum("mji,mjk->ik", H, WH)
        eta = np.einsum("mji,mj->i", WH, e) + lam0 @ (prior - x)
        dlt = np.linalg.solve(lam, eta)
        x = x + dlt
        if it >= 2 and abs(dlt[0]) + abs(dlt[1]) < 1e-4 and abs(dlt[2]) < 1e-5:
            break
    n_in = int(np.unique(trees[use & (d2 <= gate_chi2)]).size)
    cov_x = np.linalg.inv(lam)
    if 2 * n_in <= n_trees:  # the map contradicts the tracker
        return MapFix(False, True, prior, cov_x, n_trees, n_in, f"{n_in} of {n_trees} trees fit")
    if n_in < min_trees:  # the majority fits, too few to restart from: dead-reckon on
        return MapFix(False, False, prior, prior_cov, n_trees, n_in, f"only {n_in} trees fit")
    return MapFix(True, False, x, cov_x, n_trees, n_in)


def localise_windows(
    prior: FloatArray,
    prior_cov: FloatArray,
    windows: list[tuple[np.ndarray, FloatArray, FloatArray, FloatArray]],
    kf_rel: FloatArray,
    tree_xy: FloatArray,
    tree_var: FloatArray,
    kf_var: FloatArray | None = None,
) -> MapFix:
    """:func:`localise_on_map` from whole keyframe windows: ``windows[i]`` = ``(trees, bearing,
    range, sigmas)`` measured from the keyframe whose pose in the target keyframe's frame is
    ``kf_rel[i]`` ((len(windows), 3)), with the variances ``kf_var[i]`` = (m², rad²) of that
    relative pose (``rel_var``)."""
    n = [w[0].size for w in windows]
    rel_var = (
        None
        if kf_var is None
        else np.repeat(np.asarray(kf_var, dtype=np.float64).reshape(-1, 2), n, axis=0)
    )
    return localise_on_map(
        prior,
        np.repeat(np.asarray(kf_rel, dtype=np.float64).reshape(-1, 3), n, axis=0),
        np.concatenate([w[0] for w in windows]).astype(np.int64),
        np.concatenate([w[1] for w in windows]),
        np.concatenate([w[2] for w in windows]),
        np.concatenate([w[3] for w in windows]).reshape(-1, 2),
        tree_xy,
        tree_var,
        prior_cov,
        rel_var=rel_var,
    )


def restart_covariance(floor: FloatArray, dx: float, dy: float, dth: float) -> FloatArray:
    """Covariance (3, 3) of the tracker restarting from an estimate ``(dx, dy, dth)`` (m, m,
    rad; world frame) away from its own pose: ``floor`` plus the squared disagreement.

    ``floor`` (``track_floor_sigmas``, or a map fit's covariance) says the estimate is as good
    as the trees just seen make it. That holds when the estimate and the tracker agree; when
    they differ by more, one of them is off by that much, and a gate of the floor alone
    rejects every tree the tracker follows (Victoria Park started at 2.0 s: in the sharp turn
    at 732 s iSAM2's newest keyframe was 0.03 rad from the tracker, the floor is 0.005 rad, at
    20 m range that is 0.6 m against a ~0.1 m gate; no local tree matched, new trees were
    started and the path was lost, 11.6 m ATE). The disagreement widens the first gate just
    enough for the trees to decide; the tracker's MAP update then shrinks it again.
    """
    return np.asarray(floor, dtype=np.float64) + np.diag([dx * dx, dy * dy, dth * dth])
