"""Pose-covariance scoring shared by ``fastslam_covariance.py``, ``pose_covariance.py`` and
``sim_demo_backends.py``: ``z²`` of errors under covariances, the laser point's lever arm, the
Victoria Park pose terms (laser point vs GPS after the ATE's SE(2) fit), the inflation factor
that makes the median ``z²`` calibrated, and the simulator's per-row pose errors. A helper
module, not a script; each benchmark imports it explicitly (the script's own folder is on
``sys.path`` when it runs, from any working directory)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BACKENDS", "fit_inflation", "lever", "pose_errors", "pose_terms", "z2"]

#: The back-ends whose ``SlamResult.pose_covs`` the covariance benchmarks score.
BACKENDS = ("isam2", "ekf", "fastslam", "treedb", "forestrix")


def lever(poses: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """d(point)/d(x, y, theta) (N, 2, 3) of points ``xy`` rigidly attached to vehicle poses."""
    J = np.zeros((len(xy), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2] = -(xy[:, 1] - poses[:, 1])
    J[:, 1, 2] = xy[:, 0] - poses[:, 0]
    return J


def pose_terms(res: Any, vp: Any, keep: np.ndarray) -> tuple[np.ndarray, ...]:
    """GPS fix times, laser-point errors after the ATE's SE(2) fit and the pose covariances
    carried to the laser point and rotated by the fit (the pose part of
    ``fastslam_covariance._vp_terms``)."""
    from stemmap.eval.trajectory import ate, point_track

    off = vp.model.sensor_offset
    t = res.trajectory.times
    m = keep & (vp.gps_times >= t[0]) & (vp.gps_times <= t[-1])
    gt, gxy = vp.gps_times[m], vp.gps_xy[m]
    al = ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=keep).alignment
    assert al is not None
    est = point_track(res.trajectory, gt, off)
    fi = np.clip(np.searchsorted(t, gt), 0, len(t) - 1)
    J = lever(res.trajectory.interpolate(gt), est)
    C = al.rotation @ (J @ res.pose_covs[fi] @ np.swapaxes(J, 1, 2)) @ al.rotation.T
    return gt, al.apply(est) - gxy, C


def fit_inflation(e: np.ndarray, C: np.ndarray, base: np.ndarray | None = None) -> float:
    """k with median(e^T (k C + base)^-1 e) = 2 ln 2 (bisection on log k)."""
    from scipy.optimize import brentq

    b = np.zeros_like(C) if base is None else base

    def f(lk: float) -> float:
        S = np.exp(lk) * C + b
        return float(np.median(np.einsum("ni,nij,nj->n", e, np.linalg.inv(S), e))) - 2 * np.log(2)

    return float(np.exp(brentq(f, -30.0, 30.0)))


def z2(e: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e)


def pose_errors(run: Any, res: Any) -> dict[str, Any]:
    """Errors of ``res``'s reported poses against the simulated ``run``'s true vehicle poses
    (the first row, fixed with zero covariance, left out) and their ``z²`` under
    ``res.pose_covs``; only ``rows`` / ``rows_with_covariance`` when it has none."""
    from stemmap.types import wrap_angle

    n = len(res.trajectory)
    if res.pose_covs is None:
        return {"rows": n, "rows_with_covariance": 0}
    P = np.asarray(res.pose_covs)
    ok = np.all(np.isfinite(P), axis=(1, 2))
    n_fin = int(ok.sum())
    ok[0] = False  # the fixed start pose
    ok[ok] = np.linalg.eigvalsh(P[ok])[:, 0] > 0
    true = run.vehicle_poses.interpolate(res.trajectory.times)
    e = np.column_stack(
        (
            res.trajectory.poses[:, :2] - true[:, :2],
            wrap_angle(res.trajectory.poses[:, 2] - true[:, 2]),
        )
    )[ok]
    P = P[ok]
    return {
        "rows": n,
        "rows_with_covariance": n_fin,
        "e": e,
        "z2_pos": z2(e[:, :2], P[:, :2, :2]),
        "z2_th": e[:, 2] ** 2 / P[:, 2, 2],
        "nees": z2(e, P),
        "std": np.sqrt(0.5 * np.trace(P[:, :2, :2], axis1=1, axis2=2)),
    }
