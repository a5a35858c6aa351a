"""The noise of benchmarks/visual_lidar2023.py's fused filters, from the residuals of the two
odometry sources on a calibration drive that is not scored (:data:`CALIBRATION_LOOP`): the
visual odometry's step noise (constant, and as a function of its PnP inlier count) and the
lidar odometry's pose jitter and drift (:func:`calibrate_noise`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from _visual_lidar2023_diagnostics import increment_errors
from _visual_lidar2023_drive import prepare_loop

#: The calibration drive: a loop the benchmark does not score (around row 1, seed 100), from
#: whose residuals the fused filter's noise is chosen (:func:`calibrate_noise`).
CALIBRATION_LOOP = ("calibration_around_row_1", [(5, -2), (21, -2), (21, 2), (-3, 2), (-3, -2),
                                                 (5, -2)], 100)  # fmt: skip

#: Window (frames, 1.6-4 s at 5 Hz) over which the lidar's increment error has levelled off
#: on the calibration drive (its pose error is jitter about a slowly drifting path there).
LIDAR_PLATEAU_FRAMES = range(8, 21)


def calibrate_noise(cache: Path | None) -> dict[str, Any]:
    """Noise of the fused filter from the residuals of the two sources on the calibration
    drive (never the scored loops):

    * visual: the std of its frame-to-frame forward and heading errors (per frame, at the
      camera rate; the library's :func:`stemmap.odometry.visual.visual_velocity_sigma`, measured
      on other drives, gives 0.0057 m per 5 Hz step, 2.3x smaller than the 0.0128 m here with
      the tracking from the keyframe image, Dec 4);
    * lidar: its scan-to-map poses enter as pose measurements; their sigma is the level of its
      k-frame increment error over :data:`LIDAR_PLATEAU_FRAMES` divided by sqrt 2 (two
      independent pose errors per increment): the jitter of each pose about its slowly
      drifting path. (Its registration covariance, floored at 0.02 m, is 2x smaller.)
    """
    name, wp, seed = CALIBRATION_LOOP
    L = prepare_loop(name, wp, seed, cache)
    truth = L["truth"]
    v1 = np.std(increment_errors(L["visual"], truth, 1), axis=0)
    lid = np.array(
        [np.std(increment_errors(L["lidar"], truth, k), axis=0) for k in LIDAR_PLATEAU_FRAMES]
    )
    lp = np.median(lid, axis=0) / math.sqrt(2.0)
    p, c_m, c_rad = fit_inlier_model(L["vo"], L["visual"], truth)
    jit, drift = fit_lidar_drift(L["lidar"], truth)
    return {
        "drive": f"{name} (seed {seed})",
        "visual_step_sigma_m": float(v1[0]),
        "visual_step_sigma_deg": math.degrees(float(v1[2])),
        "lidar_pose_sigma_m": float(math.hypot(lp[0], lp[1]) / math.sqrt(2.0)),
        "lidar_pose_sigma_deg": math.degrees(float(lp[2])),
        "visual_inlier_exponent": p,
        "visual_step_sigma_at_100_inliers_m": c_m,
        "visual_step_sigma_at_100_inliers_deg": math.degrees(c_rad),
        "lidar_jitter_sigma_m": float(jit[0]),
        "lidar_jitter_sigma_deg": math.degrees(float(jit[1])),
        "lidar_drift_sigma_per_frame_m": float(drift[0]),
        "lidar_drift_sigma_per_frame_deg": math.degrees(float(drift[1])),
    }


def step_inliers(vo: Any) -> Any:
    """Per interval, the fewer PnP inliers of its two frames (a frame without a PnP, the first
    keyframe, does not count), as :func:`stemmap.odometry.visual.visual_odometry_source`."""
    ni = np.where(vo.n_inliers > 0, vo.n_inliers.astype(float), np.inf)
    n = np.minimum(ni[1:], ni[:-1])
    return np.where(np.isfinite(n), n, 100.0)


def fit_inlier_model(vo: Any, visual: Any, truth: Any) -> tuple[float, float, float]:
    """Maximum-likelihood fit of the VO step noise ``sigma = c (n / 100) ** -p`` (``n``:
    :func:`step_inliers`) to its frame-to-frame errors on the calibration drive: ``p`` on a
    0.1 grid (shared by the forward and heading errors), ``c`` in closed form per component.
    Returns ``(p, c_m, c_rad)``."""
    e = increment_errors(visual, truth, 1)
    ok = vo.ok[1:] & vo.ok[:-1]
    e, n = e[ok], step_inliers(vo)[ok] / 100.0
    best = (math.inf, 0.0, 0.0, 0.0)
    for p in np.arange(0.0, 4.01, 0.1):
        w = n ** (2.0 * p)  # 1 / scale**2
        c2 = [float(np.mean(e[:, j] ** 2 * w)) for j in (0, 2)]
        nll = sum(float(np.sum(np.log(c / w) + 1.0)) for c in c2)
        if nll < best[0]:
            best = (nll, float(p), math.sqrt(c2[0]), math.sqrt(c2[1]))
    return best[1], best[2], best[3]


#: Lags (frames, 1.6-12 s at 5 Hz) over which the lidar's increment error variance is fitted
#: as jitter + random walk (:func:`fit_lidar_drift`).
LIDAR_DRIFT_FRAMES = range(8, 61)


def fit_lidar_drift(lidar: Any, truth: Any) -> tuple[Any, Any]:
    """The lidar odometry's pose error as jitter about a drifting path: its k-frame increment
    error variance fitted as ``2 J**2 + k q`` over :data:`LIDAR_DRIFT_FRAMES` (least squares;
    x and y pooled). Returns ``((J_m, J_rad), (sqrt q_m, sqrt q_rad))``: the jitter sigma of
    a pose and the drift sigma per frame (a body-frame increment error, the random walk of
    the lidar's frame offset in :class:`stemmap.odometry.fusion.PoseSource` ``drift``)."""
    ks = np.array(list(LIDAR_DRIFT_FRAMES), dtype=float)
    v = np.array([np.var(increment_errors(lidar, truth, int(k)), axis=0) for k in ks])
    A = np.column_stack((np.ones_like(ks), ks))
    jit, drift = np.zeros(2), np.zeros(2)
    for j, col in enumerate((0.5 * (v[:, 0] + v[:, 1]), v[:, 2])):
        (a, b), *_ = np.linalg.lstsq(A, col, rcond=None)
        jit[j], drift[j] = math.sqrt(max(a, 0.0) / 2.0), math.sqrt(max(b, 0.0))
    return jit, drift
