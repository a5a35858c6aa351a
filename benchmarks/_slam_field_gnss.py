"""The GNSS part of benchmarks/slam_field.py (``--parts gnss``): Victoria Park, every 10th
screened fix fused, the other screened fixes scored without alignment.

Two estimates, both products of ``stemmap map --gnss`` (docs/outputs.md):

* the **tree-consistent path** (``trajectory.csv``): the command's default (Cauchy, sigma
  1.0 m) scores ``gnss_path_ate_unused_m``; the kernel and sigma chosen by 2-fold CV inside
  the fused fixes ``gnss_path_cv_ate_unused_m``.
* the **GNSS-frame track** (``trajectory_gnss.csv``: the default path + the fused fixes'
  offset, its Gauss-Markov model estimated from the run's own fused fixes,
  :func:`stemmap.slam.gnss_track.fit_gnss_offset_model`, RTS-smoothed):
  ``gnss_ate_unused_m`` (the issue's key: the trajectory the command writes in the GNSS
  frame); ``gnss_track_heldout`` the same with the model fitted on the
  first half's fused fixes only, scored on the second half; ``gnss_track_causal`` the online
  (filter-only) estimate. Older variants: ``gnss_track_rw_cv_ate_unused_m`` (random walk, CV)
  and ``gnss_track_gm_ate_unused_m`` (model from the first half's semivariogram against the
  no-GNSS path).

Each with its first / second half; ``gnss_never_worse_than_without`` compares every estimate
with the no-GNSS path (which needs a best-fit alignment to be scored at all).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

GNSS_GRID = [(k, s) for k in ("cauchy", "huber") for s in (0.2, 0.3, 0.5, 1.0)]
#: (walk_sigma m/sqrt(s), fix_sigma m) of the GNSS-frame offset smoother (gnss_offset)
OFFSET_GRID = [(q, w) for q in (0.05, 0.1, 0.2, 0.5, 1.0) for w in (0.1, 0.3, 1.0)]


def _gnss_cv(vp: Any, fused: Any) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """2-fold cross-validation INSIDE the fused fixes (never the scored ones): fuse the even
    fixes and score the odd ones without alignment, and the other way round. Chosen by the
    lowest mean RMSE: the kernel and sigma of the path, and (kernel, sigma, walk, fix sigma)
    of the GNSS-frame track (path + the training fixes' smoothed offset, ``gnss_offset``)."""
    from stemmap.eval.trajectory import ate
    from stemmap.slam.gnss import gnss_frame_trajectory, gnss_offset
    from stemmap.slam.graph import Isam2Slam

    idx = np.arange(len(fused))
    rows = []
    track_cv: dict[tuple[str, float, float, float], list[float]] = {}
    for kern, sig in GNSS_GRID:
        errs = []
        for fold in (0, 1):
            a, b = fused.select(idx % 2 == fold), fused.select(idx % 2 != fold)
            a = dataclasses.replace(a, sigma=np.full(len(a), sig))
            res = Isam2Slam(gnss_robust=kern).run(dataclasses.replace(vp.problem(), gnss=a))
            r = ate(res.trajectory, b.times, b.xy, offset=vp.model.sensor_offset, align=False)
            errs.append(r.rmse)
            for q, w in OFFSET_GRID:
                off = gnss_offset(res.trajectory, a, walk_sigma=q, fix_sigma=w)
                tr = gnss_frame_trajectory(res.trajectory, off)
                rt = ate(tr, b.times, b.xy, offset=vp.model.sensor_offset, align=False)
                track_cv.setdefault((kern, sig, q, w), []).append(rt.rmse)
        rows.append({"kernel": kern, "sigma_m": sig, "cv_rmse_m": round(float(np.mean(errs)), 3)})
    best = min(rows, key=lambda r: r["cv_rmse_m"])
    (tk, ts, tq, tw), te = min(track_cv.items(), key=lambda kv: float(np.mean(kv[1])))
    chosen = {
        "kernel": str(best["kernel"]),
        "sigma_m": float(best["sigma_m"]),
        "track": {
            "kernel": tk,
            "sigma_m": ts,
            "walk_sigma": tq,
            "fix_sigma": tw,
            "cv_rmse_m": round(float(np.mean(te)), 3),
        },
    }
    return rows, chosen


#: GNSS sigmas (m) of the plain Gaussian (no robust kernel) runs that show what chasing the
#: reference does: the path follows the fused fixes' error at the cost of tree consistency
TIGHT_SIGMAS = (0.05, 0.1)
#: lags (s) of the Gauss-Markov fit of the GPS error (first half; fitted on those <= 60 s)
GM_LAGS = (0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0)
#: lags (s) of the GPS error's semivariogram (fix-to-fix consistency with the no-GNSS path)
FLOOR_LAGS = (0.5, 2.0, 8.0, 15.0, 30.0, 60.0, 120.0)


def _gnss_evidence(vp: Any, fused: Any, unused: Any, res: Any, base: Any) -> dict[str, Any]:
    """Where the unaligned score comes from (docs/algorithms/slam.md "GNSS fusion"): the score
    per half of the run, the GPS's own error (a floor for a correct path: revisits and the
    semivariogram against the no-GNSS iSAM2 path, :mod:`stemmap.eval.gps_noise`), the
    GPS-free consistency of the fused run (chi2 per dof of its odometry and tree factors) and
    the same for plain Gaussian GNSS factors with tight sigmas."""
    from stemmap.eval.gps_noise import gps_revisit_error, gps_variogram
    from stemmap.eval.trajectory import align_se2, ate, point_track
    from stemmap.slam.graph import Isam2Slam

    t, off = vp.gps_times, vp.model.sensor_offset
    half = 0.5 * float(vp.frames.times[0] + vp.frames.times[-1])

    def halves(tr: Any) -> dict[str, float]:
        return {
            lab: round(ate(tr, t, vp.gps_xy, offset=off, keep=unused & m, align=False).rmse, 3)
            for lab, m in (("first_half", t < half), ("second_half", t >= half))
        }

    def chi2(r: Any) -> dict[str, float]:
        return {
            "odometry_chi2_per_dof": round(float(r.stats["odometry_chi2_per_dof"]), 3),
            "measurement_chi2_per_dof": round(float(r.stats["measurement_chi2_per_dof"]), 3),
        }

    # the no-GNSS path at the screened fixes, rotated into the GPS frame by one rigid fit (its
    # displacements are what counts; no score is taken from it)
    k = np.flatnonzero(vp.screened_gps() & (t >= base.trajectory.times[0]))
    k = k[t[k] <= base.trajectory.times[-1]]
    p = point_track(base.trajectory, t[k], off)
    p = align_se2(p, vp.gps_xy[k]).apply(p)
    rv = gps_revisit_error(t[k], vp.gps_xy[k], p)
    vg = gps_variogram(t[k], vp.gps_xy[k], p, FLOOR_LAGS)
    tight = []
    for sig in TIGHT_SIGMAS:
        fx = dataclasses.replace(fused, sigma=np.full(len(fused), sig))
        rt = Isam2Slam(gnss_robust="none").run(dataclasses.replace(vp.problem(), gnss=fx))
        a = ate(rt.trajectory, t, vp.gps_xy, offset=off, keep=unused, align=False)
        tight.append({"sigma_m": sig, "ate_unused_m": round(a.rmse, 3), **halves(rt.trajectory)})
        tight[-1].update(chi2(rt))
    return {
        "gnss_path_cv_ate_unused_halves_m": {"split_s": round(half, 1), **halves(res.trajectory)},
        "gnss_consistency": chi2(res),
        "no_gnss_consistency": chi2(base),
        "gnss_tight_gaussian": tight,
        "gps_error_floor": {
            "revisit_rms_2d_m": round(rv.rms_2d, 3),
            "revisit_pairs": rv.pairs,
            "variogram_lags_s": list(FLOOR_LAGS),
            "variogram_rms_2d_m": [round(float(v), 3) for v in vg.rms_2d],
            "note": "per-fix 2-D RMS error of the screened GPS, from fix pairs > 60 s apart where "
            "the no-GNSS iSAM2 path passes within 1 m (one pair per 10 s x 10 s block) and from "
            "the semivariogram of GPS minus path displacements vs lag; a correct trajectory "
            "scores about this on fixes it did not use",
        },
    }


def _gnss_track_gm(vp: Any, unused: Any, fx: Any, res: Any, base: Any) -> dict[str, Any]:
    """The GNSS-frame track with a first-order Gauss-Markov offset whose parameters come from
    the GPS error's semivariogram against the no-GNSS path over the FIRST half of the run only
    (:func:`stemmap.eval.gps_noise.fit_gauss_markov`; no score chooses anything), on the
    chosen path and fixes; scored on the unused fixes per half and whole, without alignment."""
    from stemmap.eval.gps_noise import fit_gauss_markov, gps_autocorrelation, gps_variogram
    from stemmap.eval.trajectory import align_se2, ate, point_track
    from stemmap.slam.gnss import gnss_frame_trajectory, gnss_offset

    t, g, off = vp.gps_times, vp.gps_xy, vp.model.sensor_offset
    half = 0.5 * float(vp.frames.times[0] + vp.frames.times[-1])
    tb = base.trajectory.times
    k = np.flatnonzero(vp.screened_gps() & (t >= tb[0] + 0.1) & (t <= tb[-1] - 0.1) & (t < half))
    p = point_track(base.trajectory, t[k], off)
    p = align_se2(p, g[k]).apply(p)
    fit = fit_gauss_markov(gps_variogram(t[k], g[k], p, GM_LAGS), 60.0)
    ac = gps_autocorrelation(t[k], g[k], p, GM_LAGS)
    o = gnss_offset(
        res.trajectory,
        fx,
        fix_sigma=fit.white_sigma,
        prior_sigma=fit.bias_sigma,
        time_constant=fit.time_constant,
    )
    tr = gnss_frame_trajectory(res.trajectory, o)
    sc = {
        lab: ate(tr, t, g, offset=off, keep=unused & m, align=False)
        for lab, m in (("all", t >= 0), ("first_half", t < half), ("second_half", t >= half))
    }
    return {
        "gnss_track_gm_ate_unused_m": round(sc["all"].rmse, 3),
        "gnss_track_gm_ate_unused_p95_m": round(sc["all"].p95, 3),
        "gnss_track_gm_ate_unused_halves_m": {
            "first_half": round(sc["first_half"].rmse, 3),
            "second_half": round(sc["second_half"].rmse, 3),
        },
        "gnss_gm_model_first_half": {
            "white_sigma_per_axis_m": round(fit.white_sigma, 3),
            "bias_sigma_per_axis_m": round(fit.bias_sigma, 3),
            "time_constant_s": round(fit.time_constant, 1),
            "lags_s": list(GM_LAGS),
            "autocorrelation": [round(float(v), 3) for v in ac],
        },
    }


def _halves(vp: Any, unused: Any, traj: Any) -> dict[str, float]:
    """Unaligned ATE (m) of ``traj`` on the unused fixes: whole run, first and second half."""
    from stemmap.eval.trajectory import ate

    t, off = vp.gps_times, vp.model.sensor_offset
    half = 0.5 * float(vp.frames.times[0] + vp.frames.times[-1])
    return {
        lab: round(ate(traj, t, vp.gps_xy, offset=off, keep=unused & m, align=False).rmse, 3)
        for lab, m in (("all", t >= 0), ("first_half", t < half), ("second_half", t >= half))
    }


def _gnss_products(
    vp: Any, fused: Any, unused: Any, default: Any, base: Any, chosen: Any
) -> dict[str, Any]:
    """The two estimates ``stemmap map --gnss`` writes, on the default run (Cauchy, sigma
    1.0 m): ``trajectory.csv`` (the tree-consistent path) and ``trajectory_gnss.csv`` (the
    path + the offset with the Gauss-Markov model fitted to the run's own fused fixes,
    smoothed); the same track with the model from the first half's fused fixes only (scored on
    the held-out second half) and the causal (online) track; each next to the no-GNSS path,
    which is aligned to the scored fixes (whole run, and each half on its own)."""
    from stemmap.eval.trajectory import ate
    from stemmap.slam.gnss_track import fit_gnss_offset_model, gnss_frame_trajectory, gnss_offset

    t, off = vp.gps_times, vp.model.sensor_offset
    half = 0.5 * float(vp.frames.times[0] + vp.frames.times[-1])
    tr = default.trajectory
    c0 = time.process_time()
    model = fit_gnss_offset_model(tr, fused)
    track = gnss_frame_trajectory(tr, gnss_offset(tr, fused, model=model))
    cpu = time.process_time() - c0
    first = fused.select(fused.times < half)
    m1 = fit_gnss_offset_model(tr, first)
    held = gnss_frame_trajectory(tr, gnss_offset(tr, fused, model=m1))
    causal = gnss_frame_trajectory(tr, gnss_offset(tr, fused, model=model, causal=True))
    no_gnss = {
        lab: round(ate(base.trajectory, t, vp.gps_xy, offset=off, keep=unused & m).rmse, 3)
        for lab, m in (("all", t >= 0), ("first_half", t < half), ("second_half", t >= half))
    }
    rows = {
        "path_default": _halves(vp, unused, tr),
        "path_cv": _halves(vp, unused, chosen.trajectory),
        "track": _halves(vp, unused, track),
        "track_model_first_half": _halves(vp, unused, held),
        "track_causal": _halves(vp, unused, causal),
    }
    never_worse = {
        name: {
            "whole_run": r["all"] <= no_gnss["all"],
            "each_half": all(r[k] <= no_gnss[k] for k in no_gnss),
        }
        for name, r in rows.items()
    }
    return {
        "gnss_ate_unused_m": rows["track"]["all"],
        "gnss_track_ate_unused_halves_m": rows["track"],
        "gnss_track_model": model.to_dict(),
        "gnss_track_cpu_s": round(cpu, 3),
        "gnss_track_heldout": {
            "model_first_half": m1.to_dict(),
            "ate_unused_m": rows["track_model_first_half"],
            "note": "the Gauss-Markov model fitted on the fused fixes before split_s only; "
            "second_half is held out from every choice",
        },
        "gnss_track_causal": {
            "ate_unused_m": rows["track_causal"],
            "note": "filter only (each moment from the fused fixes up to it), the run's model: "
            "what OnlineMapper-style online use could know",
        },
        "gnss_path_default_ate_unused_halves_m": rows["path_default"],
        "no_gnss_ate_unused_aligned_halves_m": no_gnss,
        "gnss_never_worse_than_without": {
            **never_worse,
            "rule": "unaligned score <= the no-GNSS path's aligned score: on the whole run "
            "(the issue's check), and on each half with the no-GNSS path aligned to that half "
            "on its own (a stricter check: 3 fitted parameters per half for the no-GNSS path)",
        },
    }


def gnss_part(data: str | None, csv_out: str | None) -> dict[str, Any]:
    """The ``gnss`` part of benchmarks/slam_field.py (module docs)."""
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate
    from stemmap.slam.gnss import gnss_frame_trajectory, gnss_offset
    from stemmap.slam.graph import Isam2Slam

    vp = load_victoria_park(data)
    fused, unused = vp.gnss_split(every=10)
    cv_rows, ch = _gnss_cv(vp, fused)
    kern, sig = ch["kernel"], ch["sigma_m"]
    if csv_out:
        with open(csv_out, "w", encoding="utf-8") as fh:
            fh.write("time_s,x,y,sigma\n")
            for t, (x, y), s in zip(fused.times, fused.xy, fused.sigma, strict=True):
                fh.write(f"{float(t)!r},{float(x)!r},{float(y)!r},{float(s)!r}\n")
    off = vp.model.sensor_offset
    default = Isam2Slam().run(dataclasses.replace(vp.problem(), gnss=fused))
    rd = ate(default.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=unused, align=False)
    chosen = dataclasses.replace(fused, sigma=np.full(len(fused), sig))
    c0 = time.process_time()
    res = Isam2Slam(gnss_robust=kern).run(dataclasses.replace(vp.problem(), gnss=chosen))
    cpu = time.process_time() - c0
    r = ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=unused, align=False)
    # the random-walk track of the CV: path (of the track's CV choice) + smoothed offset
    tc = ch["track"]
    fx_t = dataclasses.replace(fused, sigma=np.full(len(fused), tc["sigma_m"]))
    res_t = res
    if (tc["kernel"], tc["sigma_m"]) != (kern, sig):
        res_t = Isam2Slam(gnss_robust=tc["kernel"]).run(
            dataclasses.replace(vp.problem(), gnss=fx_t)
        )
    g_off = gnss_offset(
        res_t.trajectory, fx_t, walk_sigma=tc["walk_sigma"], fix_sigma=tc["fix_sigma"]
    )
    rt = ate(gnss_frame_trajectory(res_t.trajectory, g_off), vp.gps_times, vp.gps_xy,
             offset=off, keep=unused, align=False)  # fmt: skip
    base = Isam2Slam().run(vp.problem())
    rb = ate(base.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=unused)
    evidence = _gnss_evidence(vp, fused, unused, res, base)
    gm = _gnss_track_gm(vp, unused, chosen, res, base)
    products = _gnss_products(vp, fused, unused, default, base, res)
    return {
        "gnss_path_cv_ate_unused_m": round(r.rmse, 3),
        "gnss_path_cv_ate_unused_p95_m": round(r.p95, 3),
        "gnss_path_cv_ate_unused_max_m": round(r.max, 3),
        **products,
        "gnss_track_rw_cv_ate_unused_m": round(rt.rmse, 3),
        "gnss_track_rw_cv_ate_unused_p95_m": round(rt.p95, 3),
        "gnss_track_rw_cv_offset_rms_m": round(float(np.sqrt(np.mean(g_off.offset**2) * 2)), 3),
        "gnss_fixes_fused": len(fused),
        "gnss_fixes_scored": r.n,
        "gnss_fixes_outliers": res.stats.get("gnss_fixes_outliers"),
        "gnss_cpu_s": round(cpu, 2),
        "no_gnss_ate_unused_aligned_m": round(rb.rmse, 3),
        "gnss_chosen_by_cv": ch,
        "gnss_cv": cv_rows,
        "gnss_path_ate_unused_m": round(rd.rmse, 3),
        **gm,
        **evidence,
        "gnss_estimates": {
            "gnss_ate_unused_m": "the trajectory stemmap map --gnss writes in the GNSS frame "
            "(trajectory_gnss.csv, default settings): the path as the receiver reads it, "
            "following its correlated error; model from the run's own fused fixes, smoothed",
            "gnss_path_ate_unused_m": "the tree-consistent path (trajectory.csv of stemmap map "
            "--gnss, default Cauchy 1.0 m): right where the map is, scored against a receiver "
            "whose own ~1 m error is slowly varying",
            "gnss_path_cv_ate_unused_m": "the same path with the kernel/sigma chosen by 2-fold "
            "CV inside the fused fixes (not a command option)",
        },
        "gnss_data": "Victoria Park full run; fused = every 10th screened fix, antenna at the "
        "laser; scored = the other screened fixes, no alignment",
    }
