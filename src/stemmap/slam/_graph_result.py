"""Set-up and read-out steps of :class:`stemmap.slam.graph.Isam2Slam` that need none of its
incremental state: the tracker's parameter vector and dead reckoning, the landmark
bookkeeping arrays, and the map, GNSS and calibration summaries of the result.

Split out of ``Isam2Slam._run`` (which had grown to ~600 lines); the method is described in
:mod:`stemmap.slam.graph` and docs/algorithms/slam.md.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stemmap.slam.gnss import gnss_residuals
from stemmap.types import FloatArray, Tree

__all__ = [
    "LANDMARK_FILL",
    "calibration_stats",
    "gnss_stats",
    "map_trees",
    "new_landmarks",
    "sensor_dead_reckoning",
    "tracker_params",
]

# initial value of each landmark array of new_landmarks, in its order (grow_landmarks)
LANDMARK_FILL = (0, 0, 0, 0, 0, 0, -1, False, 0, 0)


def tracker_params(cfg: Any) -> FloatArray:
    """The ``params`` vector of :func:`stemmap.slam._isam2_track.track_keyframe` from an
    :class:`~stemmap.slam._graph_config.Isam2Config`."""
    return np.array(
        [
            cfg.sigma_range**2,
            cfg.sigma_bearing**2,
            (cfg.sigma_diameter or 1.0) ** 2,
            1.0 if cfg.sigma_diameter is not None else 0.0,
            cfg.gate_chi2,
            cfg.new_chi2,
            cfg.new_min_dist,
            cfg.max_range,
            cfg.max_drift_sigma**2,
            cfg.local_drift_sigma**2,
            cfg.consensus_chi2,
            cfg.drift_scale,
            cfg.min_window_obs,
        ]
    )


def sensor_dead_reckoning(poses: FloatArray, a: float, b: float) -> FloatArray:
    """(N, 3) dead-reckoned sensor poses (continuous heading) from vehicle ``poses`` and the
    mounting offset ``(a, b)``: the tracker's prediction."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    return np.column_stack(
        (poses[:, 0] + c * a - s * b, poses[:, 1] + s * a + c * b, np.unwrap(poses[:, 2]))
    )


def new_landmarks(cap: int) -> tuple[np.ndarray, ...]:
    """Empty landmark bookkeeping for ``cap`` trees: ``(xy, dsum, dn, nobs, first, last, inc,
    in_graph, ref, nfac)`` (filled with :data:`LANDMARK_FILL`; ``inc``: last frame whose
    observation is in iSAM2, ``ref``: iSAM2 updates at the last refresh, ``nfac``: measurement
    factors per tree)."""
    ints = [np.zeros(cap, dtype=np.int64) for _ in range(4)]
    return (
        np.zeros((cap, 2)),
        np.zeros(cap),
        *ints,
        np.full(cap, -1, dtype=np.int64),
        np.zeros(cap, dtype=bool),
        np.zeros(cap, dtype=np.int64),
        np.zeros(cap, dtype=np.int64),
    )


def map_trees(
    keep: np.ndarray,
    pts: FloatArray,
    covs: FloatArray,
    lm: tuple[np.ndarray, ...],
    times: FloatArray,
) -> list[Tree]:
    """The mapped trees ``keep`` with their estimates ``pts`` / ``covs``; ``lm`` = (dsum, dn,
    nobs, first, last) landmark bookkeeping, ``times`` the frame times."""
    lm_dsum, lm_dn, lm_nobs, lm_first, lm_last = lm
    trees = []
    for jk in keep.tolist():
        n_d = int(lm_dn[jk])
        trees.append(
            Tree(
                id=jk,
                x=float(pts[jk, 0]),
                y=float(pts[jk, 1]),
                diameter=float(lm_dsum[jk] / n_d) if n_d else math.nan,
                cov=covs[jk],
                n_obs=int(lm_nobs[jk]),
                first_time=float(times[lm_first[jk]]),
                last_time=float(times[lm_last[jk]]),
            )
        )
    return trees


def gnss_stats(result: Any, gnss_plan: Any, gnss_keys: list[int]) -> dict[str, float | int]:
    """Fused fixes, those the robust loss set aside (normalised residual > 3 at the optimum)
    and the residual RMS (m); empty without GNSS."""
    if gnss_plan is None or not gnss_keys:
        return {}
    ant = np.array([result.atPose2(k_g).translation() for k_g in gnss_keys])
    r_g = gnss_residuals(gnss_plan, ant)
    return {
        "gnss_fixes_fused": len(gnss_keys),
        "gnss_fixes_outliers": int(np.count_nonzero(r_g > 3.0)),
        "gnss_residual_rms_m": float(np.sqrt(np.mean((r_g * gnss_plan.sigma) ** 2))),
    }


def calibration_stats(c_used: FloatArray) -> dict[str, float]:
    """Estimated odometry calibration over the odometry factors (GPS-free diagnostic): offset
    in rad (rad/s for unicycle controls) and speed-scale correction, mean / min / max."""
    stats: dict[str, float] = {}
    for i_c, name_c in enumerate(("calib_offset", "calib_scale")):
        stats[f"{name_c}_mean"] = float(c_used[:, i_c].mean())
        stats[f"{name_c}_min"] = float(c_used[:, i_c].min())
        stats[f"{name_c}_max"] = float(c_used[:, i_c].max())
    return stats
