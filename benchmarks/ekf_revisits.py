"""Why the EKF's multi-pass Victoria Park ATE is above its single drive's (docs/reliability.md,
"EKF: why 10x is above 1x").

The EKF back-end (``stemmap.slam.ekf``, defaults; ``--set`` overrides) runs on the ACFR
Victoria Park log replayed N times as ``benchmarks/soak.py`` replays it (every second pass
driven backwards, :func:`_soak_common.revisit_drive`), for every N in ``--repeats``. Reported
per run:

* per pass the ATE against the screened GPS (each pass aligned on its own, soak.py's screening
  of the replayed log) of the **filtered** path (the filter's own poses, each from the data up
  to its frame) and of the **smoothed** path (the product: the whole path re-estimated on the
  final map, :func:`stemmap.slam._ekf_smooth.smooth_path`), the NIS per degree of freedom of
  the pass's measurement updates (merges excluded), the smoothed path's ATE on the first pass's
  GPS fixes (a backward pass: the same fixes reversed, as the screening of the reversed log
  keeps a different set) and the median of the filter's pose standard deviation (position,
  heading; after each frame's update);
* from one pass's end to the next, how the filter's map moved: the joint test ``Δᵀ (P_k -
  P_k+1)⁺ Δ`` per degree of freedom over the landmarks in both (about 1 or below for a filter
  whose changes its covariance reduction explains), the median move, and its split into a
  rigid motion (rotation about the map's centre) and the median non-rigid rest;
* the first pass's smoothed error (RMS) per 100 s of the log (where a change comes from);
* with ``--batch`` (GTSAM): the maximum a posteriori path and map of the filter's own model,
  i.e. the same pre-integrated odometry increments and covariances (plus the smoother's 1 mm /
  1e-4 rad floor), every detection the filter associated with a landmark of the final map
  (the smoother's set) with the filter's detection noise and the smoother's Huber width 1.345,
  the first pose fixed; solved jointly (path and map) by Levenberg-Marquardt from the
  filter's estimate. Its ATE per pass, its first-pass error per 100 s, and the RMS distance of
  the EKF's smoothed first pass from it (same frame: both start at the first pose).

The filtered path and the associations are taken from the back-end's call of the smoother
(wrapped for this process only), so one run gives both paths.

With ``--weights``, the optimum also with other weights (a diagnostic, not a setting), and
with ``--batch`` the whitened residuals of the first pass's associations per 100 s at the
optimum and at the EKF's own estimate.

Usage: ``python benchmarks/ekf_revisits.py --json [--repeats 1,2,3,4,10] [--batch] [--weights
ODO:MEAS,...] [--data DIR] [--set KEY=VALUE ...]``. Slow: the 10x run takes ~2-6 min of CPU.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import time
from typing import Any

import numpy as np

from _soak_common import parse_settings, revisit_drive

BIN_S = 100.0  # width of the time bins of the first-pass error (s of the log)


def _binned(err: np.ndarray, t: np.ndarray, t0: float, n_bins: int) -> list[float]:
    """RMS of ``err`` per ``BIN_S`` bin of ``t - t0``."""
    k = np.minimum(((t - t0) // BIN_S).astype(int), n_bins - 1)
    return [round(float(np.sqrt(np.mean(err[k == i] ** 2))), 2) for i in range(n_bins)]


def _map_change(s0: tuple[Any, Any, Any], s1: tuple[Any, Any, Any]) -> dict[str, float]:
    """How the filter's map moved from state ``s0`` to ``s1`` (ids, state, covariance)."""
    common, i0, i1 = np.intersect1d(s0[0], s1[0], return_indices=True)
    r0 = (3 + 2 * i0[:, None] + np.arange(2)).ravel()
    r1 = (3 + 2 * i1[:, None] + np.arange(2)).ravel()
    d = s1[1][r1] - s0[1][r0]
    dp = s0[2][np.ix_(r0, r0)] - s1[2][np.ix_(r1, r1)]
    w, v = np.linalg.eigh(0.5 * (dp + dp.T))
    k = w > 1e-9 * w.max()
    z2 = float(((v[:, k].T @ d) ** 2 / w[k]).sum() / k.sum())
    a, b = s0[1][r0].reshape(-1, 2), s1[1][r1].reshape(-1, 2)
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - cb).T @ (a - ca))
    rot = u @ vt
    rest = b - ((a - ca) @ rot.T + cb)
    return {
        "trees": int(common.size),
        "joint_z2_per_dof": round(z2, 2),
        "move_m_median": round(float(np.median(np.hypot(*(b - a).T))), 3),
        "rigid_rotation_deg": round(float(np.degrees(np.arctan2(rot[1, 0], rot[0, 0]))), 3),
        "non_rigid_m_median": round(float(np.median(np.hypot(*rest.T))), 3),
    }


def _map_estimate(
    cap: dict[str, Any], n_frames: int, odo_scale: float = 1.0, meas_scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The joint MAP path (N, 3) and map (L, 2) of the filter's own model (module docstring;
    ``odo_scale`` multiplies the odometry covariances, ``meas_scale`` the detection sigmas: a
    diagnostic of the weights, 1 = the model's own); LM iterations and CPU s."""
    import gtsam
    from gtsam.symbol_shorthand import L as LK
    from gtsam.symbol_shorthand import X as XK

    from stemmap.slam._ekf_smooth import _ODO_FLOOR

    a, b = cap["offset"]
    T = gtsam.Pose2(a, b, 0.0)  # the sensor in the vehicle frame: variables are sensor poses
    Ti = T.inverse()
    ad = Ti.AdjointMap()  # increment of S = X T: T⁻¹ δ T, its noise mapped by Ad(T⁻¹)
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    filt = cap["filtered"]
    for k in range(n_frames):
        v.insert(XK(k), gtsam.Pose2(*filt[k]).compose(T))
    g.add(
        gtsam.PriorFactorPose2(
            XK(0), gtsam.Pose2(*filt[0]).compose(T), gtsam.noiseModel.Isotropic.Sigma(3, 1e-5)
        )
    )
    deltas, covs = cap["deltas"], cap["covs"]
    for k in range(n_frames - 1):
        m = Ti.compose(gtsam.Pose2(*deltas[k])).compose(T)
        c = odo_scale * (ad @ (covs[k] + _ODO_FLOOR) @ ad.T)
        noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (c + c.T))
        g.add(gtsam.BetweenFactorPose2(XK(k), XK(k + 1), m, noise))
    r1 = cap["R1"]
    sig = meas_scale * np.sqrt([r1[1, 1], r1[0, 0]])  # GTSAM's order: bearing, range
    meas = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345), gtsam.noiseModel.Diagonal.Sigmas(sig)
    )
    for j, xy in enumerate(cap["lm_xy"]):
        v.insert(LK(j), np.asarray(xy, dtype=np.float64))
    fr, lm, rng, brg = cap["obs"]
    for i in range(fr.size):
        g.add(
            gtsam.BearingRangeFactor2D(
                XK(int(fr[i])), LK(int(lm[i])), gtsam.Rot2(float(brg[i])), float(rng[i]), meas
            )
        )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(30)
    params.setRelativeErrorTol(1e-6)
    c0 = time.process_time()
    opt = gtsam.LevenbergMarquardtOptimizer(g, v, params)
    res = opt.optimize()
    cpu = time.process_time() - c0
    veh = np.array(
        [
            [q.x(), q.y(), q.theta()]
            for q in (res.atPose2(XK(k)).compose(Ti) for k in range(n_frames))
        ]
    )
    lm_xy = np.array([res.atPoint2(LK(j)) for j in range(len(cap["lm_xy"]))]).reshape(-1, 2)
    return veh, lm_xy, int(opt.iterations()), cpu


def _whitened_z2(cap: dict[str, Any], veh: np.ndarray, lm_xy: np.ndarray) -> np.ndarray:
    """Whitened squared residual (range and bearing, the model's noise) of every association
    at the path ``veh`` and map ``lm_xy``."""
    a, b = cap["offset"]
    fr, lm, rng, brg = cap["obs"]
    x, y, t = veh[fr].T
    ex = lm_xy[lm, 0] - (x + a * np.cos(t) - b * np.sin(t))
    ey = lm_xy[lm, 1] - (y + a * np.sin(t) + b * np.cos(t))
    er = rng - np.hypot(ex, ey)
    eb = (brg - (np.arctan2(ey, ex) - t) + np.pi) % (2 * np.pi) - np.pi
    out: np.ndarray = er**2 / cap["R1"][0, 0] + eb**2 / cap["R1"][1, 1]
    return out


def _run(
    vp: Any, n: int, settings: dict[str, Any], batch: bool, scales: list[tuple[float, float]]
) -> dict[str, Any]:
    import stemmap.slam._ekf_compressed as ec
    from stemmap.eval.trajectory import ate
    from stemmap.slam.base import frame_trajectory, make_backend

    rep, spans = revisit_drive(vp, n)
    keep = rep.screened_gps()
    times = rep.frames.times
    cap: dict[str, Any] = {}
    upd: list[tuple[int, float, int]] = []  # (frame, NIS, dof) per measurement update
    snaps: list[tuple[Any, Any, Any]] = []  # (ids, state, covariance) at every pass's end
    states: list[Any] = []  # the run's filter state (synced at its end)
    pass_ends = {int(e) for e in np.searchsorted(times, [b for _, b in spans], side="right")}
    pose_var: list[tuple[float, float]] = []  # (position, heading) variance per frame
    smooth, compressed = ec.smooth_path, ec._Compressed

    def smooth_path(poses: Any, deltas: Any, covs: Any, obs: Any, *a: Any, **k: Any) -> Any:
        cap["filtered"] = np.asarray(poses[0 : len(poses)]).copy()
        if batch:
            cap.update(deltas=np.asarray(deltas[0 : len(deltas)]), obs=obs.arrays())
            cap.update(covs=np.asarray(covs[0 : len(covs)]), lm_xy=a[0].copy())
            cap.update(offset=a[2], R1=a[3])
        return smooth(poses, deltas, covs, obs, *a, **k)

    class State(compressed):  # type: ignore[misc, valid-type]
        def update(self, cols: Any, Hn: Any, v: Any, R: Any) -> float:
            nis = super().update(cols, Hn, v, R)
            if R[0, 0] > 1e-5:  # not a merge's constraint (1 mm)
                upd.append((len(pose_var), nis, int(v.size)))
            return nis

        def predict(self, d: Any, cov: Any) -> None:
            # the previous frame's posterior; at a pass's last frame also the whole state
            pose_var.append((float(self.PA[0, 0] + self.PA[1, 1]), float(self.PA[2, 2])))
            if len(pose_var) in pass_ends:
                self._snapshot()
            super().predict(d, cov)

        def __init__(self, x0: Any) -> None:
            super().__init__(x0)
            states.append(self)

        def _snapshot(self) -> None:
            c = copy.deepcopy(self)
            c.sync(None)  # the global state now (read-only for the run: a copy)
            snaps.append((c.g_ids, c.xg, c.Pg))

    ec.smooth_path, ec._Compressed = smooth_path, State  # type: ignore[misc]
    try:
        c0 = time.process_time()
        res = make_backend("ekf", **settings).run(rep.problem())
        cpu = time.process_time() - c0
        snaps.append((states[-1].g_ids, states[-1].xg, states[-1].Pg))
    finally:
        ec.smooth_path, ec._Compressed = smooth, compressed  # type: ignore[misc]
    off = rep.model.sensor_offset
    paths = {"filtered": frame_trajectory(times, cap["filtered"]), "smoothed": res.trajectory}
    if batch:
        veh, lm_map, iters, bcpu = _map_estimate(cap, len(times))
        paths["map_estimate"] = frame_trajectory(times, veh)
    ends = np.searchsorted(times, [b for _, b in spans], side="right")
    starts = np.r_[0, ends[:-1]]
    u = np.array(upd, dtype=np.float64).reshape(-1, 3)
    pv = np.array(pose_var).reshape(-1, 2)
    per_pass = []
    for p, (a, b) in enumerate(spans):
        inp = keep & (rep.gps_times >= a) & (rep.gps_times <= b)
        row: dict[str, Any] = {"direction": "forward" if p % 2 == 0 else "backward"}
        for name, tr in paths.items():
            row[f"ate_{name}_m"] = round(
                float(ate(tr, rep.gps_times, rep.gps_xy, offset=off, keep=inp).rmse), 3
            )
        # the smoothed path on the first pass's GPS fixes (a backward pass: the same fixes in
        # reverse order; the screening of the reversed log keeps a different set)
        ng = len(vp.gps_times)
        same = np.zeros_like(keep)
        same[p * ng : (p + 1) * ng] = keep[:ng] if p % 2 == 0 else keep[:ng][::-1]
        row["ate_smoothed_first_pass_fixes_m"] = round(
            float(ate(res.trajectory, rep.gps_times, rep.gps_xy, offset=off, keep=same).rmse), 3
        )
        m = (u[:, 0] >= starts[p]) & (u[:, 0] < ends[p])
        row["nis_per_dof"] = round(float(u[m, 1].sum() / u[m, 2].sum()), 3)
        q = pv[starts[p] : max(ends[p] - 1, starts[p] + 1)]
        row["pose_sd_m_median"] = round(float(np.sqrt(np.median(q[:, 0]))), 3)
        row["heading_sd_deg_median"] = round(float(np.degrees(np.sqrt(np.median(q[:, 1])))), 3)
        per_pass.append(row)
    for p in range(1, len(snaps)):
        per_pass[p]["map_change_from_previous_pass_end"] = _map_change(snaps[p - 1], snaps[p])
    # the first pass's error per 100 s of the log (GPS fixes inside the 1x path's time span)
    a, b = spans[0]
    first = keep & (rep.gps_times >= times[0]) & (rep.gps_times <= min(b, times[ends[0] - 1]))
    n_bins = int(np.ceil((b - a) / BIN_S))
    bins = {}
    for name, tr in paths.items():
        r = ate(tr, rep.gps_times, rep.gps_xy, offset=off, keep=first)
        bins[name] = _binned(r.errors, rep.gps_times[first], a, n_bins)
    out: dict[str, Any] = {
        "repeats": n,
        "cpu_s": round(cpu, 1),
        "n_trees": len(res.stem_map),
        "merged": res.stats.get("merged"),
        "ate_smoothed_one_alignment_m": round(
            float(ate(res.trajectory, rep.gps_times, rep.gps_xy, offset=off, keep=keep).rmse), 3
        ),
        "per_pass": per_pass,
        "first_pass_rms_per_100s": bins,
    }
    if batch:
        nf = int(ends[0])
        dxy = res.trajectory.poses[:nf, :2] - paths["map_estimate"].poses[:nf, :2]
        out["map_estimate"] = {
            "lm_iterations": iters,
            "cpu_s": round(bcpu, 1),
            "smoothed_first_pass_to_map_estimate_rms_m": round(
                float(np.sqrt(np.mean(np.sum(dxy**2, 1)))), 3
            ),
        }
        # the associations' fit per 100 s of the log (first pass): outliers would show here
        fr = cap["obs"][0]
        first_obs = fr < nf
        ft = times[fr[first_obs]]
        for name, pth, lmx in (
            ("map_estimate", veh, lm_map),
            ("smoothed", res.trajectory.poses, cap["lm_xy"]),
        ):
            z2 = _whitened_z2(cap, pth, lmx)[first_obs]
            k = np.minimum(((ft - spans[0][0]) // BIN_S).astype(int), n_bins - 1)
            out["map_estimate"][f"residual_z2_mean_per_100s_{name}"] = [
                round(float(z2[k == i].mean()), 2) if (k == i).any() else None
                for i in range(n_bins)
            ]
            out["map_estimate"][f"residual_z2_share_above_9_{name}"] = round(
                float((z2 > 9).mean()), 4
            )
        for odo, meas in scales:  # the weights' diagnostic: the optimum with other weights
            v2 = _map_estimate(cap, len(times), odo, meas)[0]
            tr = frame_trajectory(times, v2)
            out["map_estimate"][f"ate_first_pass_odo_x{odo:g}_meas_x{meas:g}_m"] = round(
                float(ate(tr, rep.gps_times, rep.gps_xy, offset=off, keep=first).rmse), 3
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--repeats", default="1,2,3,4,10", help="comma list of pass counts")
    ap.add_argument("--batch", action="store_true", help="also the MAP of the filter's model")
    ap.add_argument(
        "--weights",
        default="",
        help="with --batch: comma list ODO:MEAS of factors on the odometry covariances and "
        "the detection sigmas for extra optima (a diagnostic of the weights; e.g. 4:1,1:0.5)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an EkfConfig setting (repeatable; value parsed as JSON)",
    )
    args = ap.parse_args()
    settings = parse_settings(ap, args.set)
    from stemmap.datasets.victoria_park import load_victoria_park

    vp = load_victoria_park(args.data)
    scales = [tuple(float(x) for x in w.split(":")) for w in args.weights.split(",") if w]
    runs = [
        _run(vp, int(n), settings, args.batch, scales)  # type: ignore[arg-type]
        for n in args.repeats.split(",")
        if n
    ]
    out = {
        "benchmark": "ekf_revisits",
        "settings": settings,
        "runs": runs,
        "scenario": {
            "dataset": "ACFR Victoria Park (text redistribution), soak.py's revisit drive",
            "load_avg_1min": round(os.getloadavg()[0], 2),
        },
    }
    print(json.dumps(out, indent=1) if args.json else out)


if __name__ == "__main__":
    main()
