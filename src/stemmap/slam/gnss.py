"""GNSS fixes for the graph back-end: reading, frame initialisation, robust prior factors (ours).

A GNSS fix measures the position of the **antenna**, a fixed point of the vehicle (the lever
arm ``(l_x, l_y)`` in the vehicle frame: forward, left). In :class:`stemmap.slam.graph.Isam2Slam`
each fix at time ``t`` becomes

* an auxiliary :class:`gtsam.Pose2` variable ``Z(i)``, the antenna pose at ``t``;
* a ``BetweenFactorPose2(X(k), Z(i))`` from the keyframe ``k`` before ``t``: the sensor pose
  ``X(k)`` composed with the dead-reckoned motion from the keyframe to ``t`` and the lever arm,
  ``T_sv ∘ δ(t_k, t) ∘ (l_x, l_y, 0)``, with the odometry covariance of that stretch (the
  keyframe increment's covariance scaled by the fraction of the keyframe interval);
* a ``PoseTranslationPrior2D(Z(i))`` on the fix's position with a **robust** noise model
  (Cauchy by default, or Huber): under canopy fixes jump by metres between outages and a
  quadratic cost would follow them (docs/algorithms/slam.md "GNSS fusion").

The graph then lives in the GNSS frame: the run's initial pose is replaced by the dead-reckoned
start aligned to the first fixes (:func:`gnss_initial_pose`) and held only by a weak prior, so the
trajectory and the map come out in the frame of the fixes. With a prior map the relocalised
initial pose is kept (:func:`with_gnss_frame`): the map must be in the fixes' frame.

Why an auxiliary variable and not a custom factor: the lever arm and the sub-keyframe timing are
exact this way with GTSAM's compiled factors; a Python ``CustomFactor`` made the iSAM2 run 3-4x
slower on Victoria Park (see :mod:`stemmap.slam.graph`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import InputError
from stemmap.slam.motion import between, compose, preintegrate
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.slam.base import SlamProblem

__all__ = [
    "GnssFixes",
    "GnssOffset",
    "GnssOffsetModel",
    "GnssPlan",
    "fit_gnss_offset_model",
    "gnss_factors",
    "gnss_frame_trajectory",
    "gnss_initial_pose",
    "gnss_offset",
    "gnss_residuals",
    "plan_gnss",
    "read_gnss_csv",
    "robust_kernel",
    "with_gnss_frame",
]

log = logging.getLogger(__name__)

#: Columns of the GNSS CSV (``sigma`` optional), in order.
GNSS_CSV_COLUMNS = ("time_s", "x", "y", "sigma")


@dataclass(frozen=True, eq=False)
class GnssFixes:
    """GNSS position fixes in a projected (metric) frame.

    Attributes
    ----------
    times : ndarray (N,), s, on the odometry's time base, non-decreasing
    xy : ndarray (N, 2), m, antenna positions (easting, northing or any metric frame)
    sigma : ndarray (N,), m, 1-sigma horizontal error per axis (> 0)
    lever_arm : (l_x, l_y), m, antenna position in the vehicle frame (forward, left)
    """

    times: FloatArray
    xy: FloatArray
    sigma: FloatArray
    lever_arm: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64).reshape(-1)
        xy = np.asarray(self.xy, dtype=np.float64)
        s = np.broadcast_to(np.asarray(self.sigma, dtype=np.float64), t.shape).copy()
        if xy.ndim != 2 or xy.shape != (t.shape[0], 2):
            raise InputError(f"GNSS: {t.shape[0]} times need an (N, 2) xy array, got {xy.shape}.")
        if t.shape[0] == 0:
            raise InputError("GNSS: no fixes.")
        if not (np.isfinite(t).all() and np.isfinite(xy).all()):
            raise InputError("GNSS: times and positions must be finite numbers.")
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise InputError("GNSS: every sigma must be a positive number (m).")
        if np.any(np.diff(t) < 0):
            k = int(np.argmax(np.diff(t) < 0))
            raise InputError(
                f"GNSS: fix times must not decrease (fix {k + 1} at {t[k + 1]} s after {t[k]} s); "
                "sort the file by time."
            )
        lx, ly = (float(v) for v in self.lever_arm)
        if not (math.isfinite(lx) and math.isfinite(ly)):
            raise InputError(f"GNSS: lever arm must be finite, got {self.lever_arm}.")
        for name, v in (("times", t), ("xy", xy), ("sigma", s)):
            v.setflags(write=False)
            object.__setattr__(self, name, v)
        object.__setattr__(self, "lever_arm", (lx, ly))

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def select(self, mask: ArrayLike) -> GnssFixes:
        """The fixes where ``mask`` (bool or index array) selects."""
        m = np.asarray(mask)
        return GnssFixes(self.times[m], self.xy[m], self.sigma[m], self.lever_arm)


def read_gnss_csv(
    path: Any, *, lever_arm: tuple[float, float] = (0.0, 0.0), default_sigma: float = 1.0
) -> GnssFixes:
    """Read a GNSS CSV ``time_s,x,y[,sigma]`` (header required, ``time`` accepted for
    ``time_s``; ``#`` comments allowed).

    ``x, y`` are metric coordinates (a projected CRS such as UTM); ``sigma`` (m) defaults to
    ``default_sigma`` where the column or a value is missing. Raises :class:`InputError` naming
    the file and line of a bad row.
    """
    from stemmap.io._util import existing_file, parse_numeric_csv, read_text, require_finite

    what = "GNSS CSV"
    p = existing_file(path, what)
    table = parse_numeric_csv(p, read_text(p, what), GNSS_CSV_COLUMNS[:3], ("sigma",), what)
    for name in GNSS_CSV_COLUMNS[:3]:
        require_finite(p, what, table, name)
    t = table.columns["time_s"]
    if t.shape[0] == 0:
        raise InputError(f"{what} file {str(p)!r} has no fixes.")
    sig = table.columns.get("sigma")
    if sig is None:
        sig = np.full(t.shape[0], float(default_sigma))
    else:
        bad = np.isfinite(sig) & ~(sig > 0)
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(
                f"{what} file {str(p)!r} line {table.lines[k]}: sigma {sig[k]} must be > 0 (m)."
            )
        sig = np.where(np.isfinite(sig), sig, float(default_sigma))
    if np.any(np.diff(t) < 0):
        k = int(np.argmax(np.diff(t) < 0)) + 1
        raise InputError(
            f"{what} file {str(p)!r} line {table.lines[k]}: time {t[k]} goes back in time; sort "
            "the fixes by time."
        )
    xy = np.column_stack((table.columns["x"], table.columns["y"]))
    return GnssFixes(t, xy, sig, lever_arm)


def _antenna(poses: FloatArray, lever: tuple[float, float]) -> FloatArray:
    """(N, 2) antenna positions of vehicle poses (N, 3)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    lx, ly = lever
    return np.column_stack((poses[:, 0] + c * lx - s * ly, poses[:, 1] + s * lx + c * ly))


def gnss_initial_pose(
    problem: SlamProblem, fixes: GnssFixes, *, min_travel: float = 30.0
) -> tuple[float, float, float]:
    """The run's initial vehicle pose in the GNSS frame (the graph's linearisation point).

    Dead-reckons the antenna from ``problem.initial_pose`` to the fixes made while the vehicle
    drives its first ``min_travel`` metres (all fixes if it never does), and aligns that track
    to them (closed-form SE(2), :func:`stemmap.eval.trajectory.align_se2`); fixes farther than
    ``max(3 sigma, 3 x median)`` from the aligned track are dropped and the alignment is
    repeated once (a jump in the first fixes must not rotate the whole start). With less than
    5 m of travel the heading is unobservable: the dead-reckoned heading is kept and only the
    translation is fitted. The back-end's weak prior on this pose and the robust fixes decide
    the final frame; this only sets where the optimisation starts.
    """
    from stemmap.eval.trajectory import align_se2

    t0, t1 = float(problem.frames.times[0]), float(problem.frames.times[-1])
    use = (fixes.times >= t0) & (fixes.times <= t1)
    if not use.any():
        raise InputError(
            f"GNSS: no fix between the run's first and last scan ({t0:.3f}-{t1:.3f} s); are the "
            "fix times on the same clock as the odometry?"
        )
    tf, gxy, sg = fixes.times[use], fixes.xy[use], fixes.sigma[use]
    pre = preintegrate(
        problem.motion,
        problem.controls,
        np.concatenate(([t0], tf)),
        problem.initial_pose,
        with_covariance=False,
    )
    dist = np.cumsum(pre.distance)
    n = max(2, int(np.searchsorted(dist, min_travel, side="right")) + 1)
    n = min(n, tf.shape[0])
    ant = _antenna(pre.poses[1 : n + 1], fixes.lever_arm)
    g = gxy[:n]
    p0 = np.asarray(problem.initial_pose, dtype=np.float64)
    keep = np.ones(n, dtype=bool)
    travel = float(dist[n - 1]) if n else 0.0
    for _ in range(2):
        if travel >= 5.0 and keep.sum() >= 2:
            al = align_se2(ant[keep], g[keep])
            th, tr = al.theta, np.asarray(al.t)
        else:
            th, tr = 0.0, (g[keep] - ant[keep]).mean(axis=0)
        c, s = math.cos(th), math.sin(th)
        fit = ant @ np.array([[c, s], [-s, c]]) + tr
        r = np.hypot(*(fit - g).T)
        lim = np.maximum(3.0 * sg[:n], 3.0 * float(np.median(r)))
        if (r <= lim).all() or (r <= lim).sum() < 2:
            break
        keep = r <= lim
    c, s = math.cos(th), math.sin(th)
    x0 = c * p0[0] - s * p0[1] + tr[0]
    y0 = s * p0[0] + c * p0[1] + tr[1]
    th0 = math.atan2(math.sin(p0[2] + th), math.cos(p0[2] + th))
    log.info(
        "GNSS: initial pose (%.2f, %.2f, %.2f deg) from %d fixes over %.1f m",
        x0,
        y0,
        math.degrees(th0),
        int(keep.sum()),
        travel,
    )
    return (float(x0), float(y0), float(th0))


@dataclass(frozen=True, eq=False)
class GnssPlan:
    """The GNSS factors of one run, per fix inside the run (from :func:`plan_gnss`).

    kf : (M,) keyframe each fix hangs from (the last keyframe at or before its time)
    rel : (M, 3) antenna pose at the fix time in the keyframe's SENSOR frame
    rel_cov : (M, 3, 3) covariance of ``rel`` (GTSAM tangent, odometry over the stretch)
    xy : (M, 2) measured antenna positions; sigma : (M,) m
    """

    kf: np.ndarray
    rel: FloatArray
    rel_cov: FloatArray
    xy: FloatArray
    sigma: FloatArray

    def __len__(self) -> int:
        return int(self.kf.shape[0])


def plan_gnss(
    problem: SlamProblem,
    fixes: GnssFixes,
    kf_times: FloatArray,
    kf_veh_poses: FloatArray,
    kf_cov: FloatArray,
) -> GnssPlan:
    """Attach every fix inside the run to the keyframe before it (see the module docs).

    ``kf_veh_poses`` are the dead-reckoned vehicle poses at ``kf_times`` from the same
    pre-integration the odometry factors use, ``kf_cov`` (K-1, 3, 3) the sensor-frame covariances
    of the keyframe increments. Fixes before the first keyframe or after the last scan are left
    out (logged).
    """
    t0, t1 = float(kf_times[0]), float(problem.frames.times[-1])
    inside = (fixes.times >= t0) & (fixes.times <= t1)
    if (~inside).any():
        n_out = int((~inside).sum())
        log.info("GNSS: %d of %d fixes outside the run's time span", n_out, len(fixes))
    tf = fixes.times[inside]
    nk = kf_times.shape[0]
    kf = np.clip(np.searchsorted(kf_times, tf, side="right") - 1, 0, nk - 1).astype(np.int64)
    # dead reckoning from the first keyframe (preintegrate starts at its first query time)
    pv = preintegrate(
        problem.motion,
        problem.controls,
        np.concatenate((kf_times[:1], tf)),
        problem.initial_pose,
        with_covariance=False,
    ).poses[1:]
    rel_v = between(kf_veh_poses[kf], pv)  # vehicle motion keyframe -> fix time
    a, b = problem.sensor_offset
    m = tf.shape[0]
    t_sv = np.tile(np.array([-a, -b, 0.0]), (m, 1))  # T_vs⁻¹ (no rotation)
    lever = np.tile(np.array([fixes.lever_arm[0], fixes.lever_arm[1], 0.0]), (m, 1))
    rel = compose(compose(t_sv, rel_v), lever)
    # odometry covariance of the stretch: the keyframe increment's, scaled by the time fraction
    if nk > 1:
        dt_k = np.diff(kf_times)
        kk = np.minimum(kf, nk - 2)
        frac = np.clip((tf - kf_times[kf]) / np.maximum(dt_k[kk], 1e-9), 0.0, 1.0)
        cov = kf_cov[kk] * frac[:, None, None]
    else:
        cov = np.zeros((m, 3, 3))
    cov = cov + np.diag([1e-3**2, 1e-3**2, 1e-4**2])[None]
    return GnssPlan(kf, rel, cov, fixes.xy[inside], fixes.sigma[inside])


def with_gnss_frame(problem: SlamProblem) -> SlamProblem:
    """``problem`` with its initial pose moved into the GNSS frame (no-op without GNSS).

    Also a no-op with a ``prior_map``: its trees pin the graph in the map's frame and the
    initial pose is the relocalised one in that frame (:func:`stemmap.slam.relocalise.
    continue_session`), which the fixes must then share -- the caller's to check (``stemmap
    map`` refuses a prior map not made in the GNSS frame, docs/algorithms/slam.md "Prior map
    and GNSS"). Replacing the relocalised pose by the one aligned to the first fixes would
    throw away the map's (tighter) start for a dead-reckoned fit to a few metres-noisy fixes.
    """
    if problem.gnss is None or problem.prior_map is not None:
        return problem
    return dataclasses.replace(problem, initial_pose=gnss_initial_pose(problem, problem.gnss))


def robust_kernel(gtsam: Any, kind: str, k: float) -> Any:
    """GTSAM m-estimator ``kind`` ("huber", "cauchy"; "none" -> None) of width ``k`` sigmas."""
    if kind == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(k)
    if kind == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    return None


def gnss_factors(
    plan: GnssPlan, i: int, x_key: int, x_est: Any, kernel: Any, key: int | None = None
) -> tuple[list[Any], int, Any]:
    """Factors, key and initial value of fix ``i`` of ``plan`` (see the module docs).

    ``x_key`` / ``x_est`` are the key and current estimate of the fix's keyframe pose; ``key``
    the antenna pose's key (default ``Z(i)``). Returns
    ``([BetweenFactorPose2(X, Z), PoseTranslationPrior2D(Z)], Z key, Z initial pose)``; the
    prior's noise is isotropic ``sigma`` wrapped in ``kernel`` (robust) when given.
    """
    import gtsam
    from gtsam.symbol_shorthand import Z as ZK

    r = plan.rel[i]
    rel = gtsam.Pose2(float(r[0]), float(r[1]), float(r[2]))
    key = ZK(i) if key is None else key
    between_f = gtsam.BetweenFactorPose2(
        x_key, key, rel, gtsam.noiseModel.Gaussian.Covariance(plan.rel_cov[i])
    )
    base = gtsam.noiseModel.Isotropic.Sigma(2, float(plan.sigma[i]))
    noise = base if kernel is None else gtsam.noiseModel.Robust.Create(kernel, base)
    xy = plan.xy[i]
    prior_f = gtsam.PoseTranslationPrior2D(key, gtsam.Point2(float(xy[0]), float(xy[1])), noise)
    return [between_f, prior_f], key, x_est.compose(rel)


def gnss_residuals(plan: GnssPlan, antenna_xy: FloatArray) -> FloatArray:
    """(M,) normalised residuals ``|antenna - fix| / sigma`` at the estimated antenna poses."""
    return np.asarray(np.hypot(*(antenna_xy - plan.xy).T) / plan.sigma, dtype=np.float64)


# the GNSS-frame track lives in its own module; its names stay importable from here
from stemmap.slam.gnss_track import (  # noqa: E402
    GnssOffset,
    GnssOffsetModel,
    fit_gnss_offset_model,
    gnss_frame_trajectory,
    gnss_offset,
)
