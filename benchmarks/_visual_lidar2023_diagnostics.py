"""Diagnostics of benchmarks/visual_lidar2023.py against the truth (used by no estimate):
increment errors, scale and yaw-rate biases, and the z^2 checks of each source's noise."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def increment_errors(est: Any, truth: Any, k: int) -> Any:
    """(n, 3) errors (forward m, lateral m, heading rad) of the estimate's k-frame increments."""
    from stemmap.slam.motion import between

    ep, tp = est.poses, truth.poses
    e = between(ep[:-k], ep[k:]) - between(tp[:-k], tp[k:])
    e[:, 2] = np.remainder(e[:, 2] + math.pi, 2 * math.pi) - math.pi
    return e


def scale_and_yaw_bias(est: Any, truth: Any) -> tuple[float, float]:
    """Speed-scale error (%) and mean yaw-rate error (deg/s) of an odometry against the truth."""
    from stemmap.slam.motion import between

    ep, tp = est.poses, truth.poses
    de, dt_ = between(ep[:-1], ep[1:]), between(tp[:-1], tp[1:])
    mv = dt_[:, 0] > 0.05
    scale = float(np.sum(de[mv, 0]) / np.sum(dt_[mv, 0]) - 1.0)
    e = increment_errors(est, truth, 1)[:, 2]
    return 100.0 * scale, math.degrees(float(np.sum(e)) / float(truth.times[-1] - truth.times[0]))


def consistency(
    L: dict[str, Any], noise: dict[str, Any], src_const: Any, src_inl: Any, fused: dict[str, Any]
) -> dict[str, float]:
    """Diagnostics against the truth (used by no estimate): mean z^2 per degree of freedom
    (1 = the noise given to the EKF is calibrated) of the VO's frame-to-frame forward error
    under the constant and the inlier noise, of the lidar's increments under its registration
    covariance, of the lidar's poses as absolute measurements (first and last quarter of the
    drive), and of each fused path's position under its own covariance."""
    from stemmap.slam.motion import between

    truth, vo, lres = L["truth"], L["vo"], L["lres"]
    e = increment_errors(L["visual"], truth, 1)[vo.ok[1:] & vo.ok[:-1], 0]
    dt = float(np.median(np.diff(truth.times)))
    out = {
        "nees.vo_step_constant": float(np.mean((e / (src_const.sigma_speed * dt)) ** 2)),
        "nees.vo_step_inliers": float(np.mean((e / (src_inl.sigma_speed * dt)) ** 2)),
    }
    sens = L["run"].true_poses.poses
    el = between(lres.planar[:-1], lres.planar[1:]) - between(sens[:-1], sens[1:])
    el[:, 2] = np.remainder(el[:, 2] + math.pi, 2 * math.pi) - math.pi
    C = lres.increment_cov[1:]
    g = np.isfinite(C[:, 0, 0])
    z2 = np.einsum("ni,nij,nj->n", el[g], np.linalg.inv(C[g]), el[g])
    out["nees.lidar_increment_registration"] = float(np.mean(z2) / 3.0)
    s2 = noise["lidar_pose_sigma_m"] ** 2
    d2 = np.sum((L["lidar"].poses[:, :2] - truth.poses[:, :2]) ** 2, axis=1) / (2.0 * s2)
    q = len(d2) // 4
    out["nees.lidar_pose_absolute_first_quarter"] = float(np.mean(d2[:q]))
    out["nees.lidar_pose_absolute_last_quarter"] = float(np.mean(d2[-q:]))
    for key, f in fused.items():
        tr = f.trajectory
        i = np.clip(np.searchsorted(truth.times, tr.times - 1e-9), 0, len(truth) - 1)
        ef = tr.poses[:, :2] - truth.poses[i, :2]
        Cf = f.covariances[:, :2, :2] + 1e-12 * np.eye(2)
        zf = np.einsum("ni,nij,nj->n", ef, np.linalg.inv(Cf), ef) / 2.0
        out[f"nees.{key}_position"] = float(np.mean(zf[len(zf) // 10 :]))
    return out


def true_displacement(truth: Any, est: Any) -> tuple[float, float]:
    """True end-minus-start displacement over the estimate's time span, in its start frame."""
    tp = truth.poses
    i, j = np.searchsorted(truth.times, est.times[[0, -1]] - 1e-9)
    c, s = math.cos(tp[i, 2]), math.sin(tp[i, 2])
    d = tp[j, :2] - tp[i, :2]
    return (c * d[0] + s * d[1], -s * d[0] + c * d[1])
