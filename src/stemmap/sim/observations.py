"""Ground truth per scan, and "oracle" stem observations with controlled noise.

Mapping and SLAM can be tested without depending on a trunk detector: :func:`oracle_observations`
reports every tree that a scan actually saw (at least ``min_returns`` beams on it) at its true
sensor-frame position plus Gaussian noise, optionally with false alarms on clutter, in the same
columnar :class:`~stemmap.types.StemObservations` a detector returns.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.scanner import HIT_CLUTTER
from stemmap.sim.trajectory import SimRun
from stemmap.types import FloatArray, StemObservations

__all__ = ["oracle_observations", "returns_per_tree", "trees_in_sensor_frame"]

RngLike = np.random.Generator | int | None


def trees_in_sensor_frame(run: SimRun) -> FloatArray:
    """Every truth tree's centre in every scan's sensor frame, shape (S, T, 2), metres."""
    poses = run.true_poses.poses
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    d = run.stand.trees_xy[None, :, :] - poses[:, None, :2]
    return np.stack((c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]), axis=-1)


def returns_per_tree(run: SimRun) -> NDArray[np.int64]:
    """Number of beams that hit each tree in each scan, shape (S, T)."""
    n_t = run.stand.n_trees
    h = run.hit_ids
    rows = np.repeat(np.arange(h.shape[0]), h.shape[1])
    flat = h.reshape(-1)
    ok = flat >= 0
    counts = np.bincount(rows[ok] * n_t + flat[ok], minlength=h.shape[0] * max(n_t, 1))
    return counts[: h.shape[0] * n_t].reshape(h.shape[0], n_t).astype(np.int64)


def oracle_observations(
    run: SimRun,
    *,
    min_returns: int = 5,
    max_range: float | None = None,
    sigma_xy: float = 0.02,
    sigma_radius: float = 0.005,
    false_alarm_rate: float = 0.0,
    rng: RngLike = None,
) -> tuple[StemObservations, NDArray[np.int64]]:
    """Noisy "perfect detector" observations of a simulated run.

    Parameters
    ----------
    run : SimRun
    min_returns : int
        A tree is observed in a scan if at least this many beams hit it.
    max_range : float, metres, optional
        Trees farther than this from the sensor are not observed.
    sigma_xy : float, metres
        1-sigma Gaussian noise on each centre coordinate (sensor frame).
    sigma_radius : float, metres
        1-sigma Gaussian noise on the radius.
    false_alarm_rate : float, >= 0
        Mean number of false observations per scan (Poisson), placed on beams that hit
        clutter: a 2-8 cm radius "trunk" just behind the return.
    rng : numpy Generator or int seed

    Returns
    -------
    observations : StemObservations
        Sensor frame; ``index`` is the scan index, ``times`` the scan time, ``covs`` the
        simulated noise (diag(sigma_xy², sigma_xy², sigma_radius²)), ``source="sim:oracle"``.
    truth_ids : ndarray of shape (K,), int
        Tree index of each observation, -1 for false alarms.
    """
    if min_returns < 1:
        raise ConfigError(f"min_returns must be >= 1, got {min_returns}.")
    if not (sigma_xy >= 0 and sigma_radius >= 0 and false_alarm_rate >= 0):
        raise ConfigError("sigma_xy, sigma_radius and false_alarm_rate must be >= 0.")
    if run.stand.n_trees == 0 and false_alarm_rate == 0:
        return StemObservations.empty(source="sim:oracle"), np.zeros(0, dtype=np.int64)
    gen = np.random.default_rng(rng)
    local = trees_in_sensor_frame(run)
    seen = returns_per_tree(run) >= min_returns
    if max_range is not None:
        if not max_range > 0:
            raise ConfigError(f"max_range must be > 0 m, got {max_range}.")
        seen &= np.hypot(local[..., 0], local[..., 1]) <= max_range
    si, ti = np.nonzero(seen)
    centers = local[si, ti] + gen.normal(0.0, 1.0, (si.size, 2)) * sigma_xy
    radii = run.stand.radii[ti] + gen.normal(0.0, 1.0, si.size) * sigma_radius
    n_pts = returns_per_tree(run)[si, ti]
    scan_idx = si
    truth = ti.astype(np.int64)

    if false_alarm_rate > 0:
        n_fa = gen.poisson(false_alarm_rate, len(run))
        fa_rows: list[FloatArray] = []
        fa_scan: list[int] = []
        angles = run.scans.angles
        for k in np.flatnonzero(n_fa):
            beams = np.flatnonzero(run.hit_ids[k] == HIT_CLUTTER)
            if beams.size == 0:
                continue
            pick = gen.choice(beams, size=min(int(n_fa[k]), beams.size), replace=False)
            r_fa = gen.uniform(0.02, 0.08, pick.size)
            rng_b = run.scans.ranges[k, pick] + r_fa
            a = angles[pick]
            fa_rows.append(np.column_stack((rng_b * np.cos(a), rng_b * np.sin(a), r_fa)))
            fa_scan.extend([int(k)] * pick.size)
        if fa_rows:
            fa = np.vstack(fa_rows)
            centers = np.vstack((centers, fa[:, :2]))
            radii = np.concatenate((radii, fa[:, 2]))
            n_pts = np.concatenate((n_pts, np.full(fa.shape[0], min_returns)))
            scan_idx = np.concatenate((scan_idx, np.asarray(fa_scan)))
            truth = np.concatenate((truth, np.full(fa.shape[0], -1, dtype=np.int64)))
            order = np.argsort(scan_idx, kind="stable")
            centers, radii, n_pts = centers[order], radii[order], n_pts[order]
            scan_idx, truth = scan_idx[order], truth[order]

    k_obs = scan_idx.size
    radii = np.maximum(radii, 1e-3)
    covs = np.zeros((k_obs, 3, 3))
    covs[:, [0, 1, 2], [0, 1, 2]] = [sigma_xy**2, sigma_xy**2, sigma_radius**2]
    arc = np.full(k_obs, math.nan)
    if k_obs and not np.all(np.isfinite(centers)):
        raise InputError("oracle_observations produced non-finite centres; check the run.")
    obs = StemObservations(
        centers=centers,
        radii=radii,
        covs=covs,
        n_points=n_pts,
        arc_deg=arc,
        widths=np.full(k_obs, math.nan),
        quality=np.ones(k_obs),
        index=scan_idx,
        times=run.scans.times[scan_idx],
        source="sim:oracle",
        frame=run.scans.frame,
    )
    return obs, truth
