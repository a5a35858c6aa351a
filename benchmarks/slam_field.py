"""Benchmark: mapping in the field on Victoria Park -- GNSS fusion, relocalisation, online latency.

Prints one JSON object with ``--json``. Parts (``--parts``, default all):

* ``gnss``: iSAM2 fusing every 10th GPS fix kept by ``screen_gps`` (the screening looks only at
  the GPS and the wheel odometry), scored on the screened fixes NOT fused, without any
  alignment (``gnss_ate_unused_m``); the robust kernel and sigma are chosen by 2-fold
  cross-validation inside the fused fixes (``gnss_cv``), the a-priori default's score is
  ``gnss_default_ate_unused_m``; the same run without GNSS scored on the same fixes needs a
  best-fit SE(2) alignment (``no_gnss_ate_unused_aligned_m``). ``gnss_track_ate_unused_m``:
  the GNSS-frame track (the path + the fused fixes' random-walk-smoothed offset,
  :func:`stemmap.slam.gnss.gnss_offset`; it follows the GPS's own slowly varying error), its
  settings chosen by the same CV; ``gnss_track_gm_ate_unused_m``: the same track with a
  first-order Gauss-Markov offset whose parameters are fitted to the GPS error's
  semivariogram against the no-GNSS path over the first half of the run only
  (``gnss_gm_model_first_half``, with the error's autocorrelation; no score chooses them),
  scored per half and whole. Where the score comes from: the chosen run's score on the
  first and second half of the run, the GPS's own error (``gps_error_floor``: revisits and the
  semivariogram of fix-to-fix consistency with the no-GNSS path, ``stemmap.eval.gps_noise``),
  the GPS-free chi2 per dof of the odometry and tree factors, and plain Gaussian GNSS factors
  with tight sigmas (``gnss_tight_gaussian``: lower scores bought by bending the path and map
  to the fixes' own error).
* ``reloc``: map 0-800 s, then relocalise the 800-1549 s session in that map from start
  guesses off by U(-20, 20) m in x and y and U(-30, 30) deg (``--trials``, seed 0); success =
  accepted within 30 s of driving, within 1 m and 2 deg of session 1's end pose carried over
  the gap by odometry (``reloc_success_rate``, ``reloc_time_s_*``). Session 2 is then mapped on
  the prior map (default: each tree held by its own Huber prior on its marginal inflated x4,
  ``Isam2Config.prior_map_inflation``; session 1's odometry calibration carried over) and
  scored on the screened fixes after 800 s with its own alignment, next to the same with the
  trees held jointly by session 1's tree information
  (``session2_prior_map_joint``), on Gaussian per-tree priors without the calibration,
  without the prior map, and to the full single run on the same fixes.
  ``--reloc-per-trial``: session 2 mapped from every accepted trial's pose, joint vs Huber;
  ``--reloc-splits 400,600``: other session pairs (map 0-s, relocalise and map s-1549 s),
  Huber (inflated / not) vs joint vs session 1's saved graph continued (``graph_m``,
  inflation 4; ``graph_f1_m``: 1) vs the full run, the prior's consistency, and the process
  CPU per keyframe step of session 2 for Huber and graph (``*_step``: p50 / p99 / max); per
  split the success rate over ``--trials`` start offsets, false relocalisations, and
  acceptances from guesses whose 30-m search excludes the truth. ``--reloc-splits-only``:
  only those rows (and the full run). The code is in slam_field_reloc.py.
* ``online``: :class:`stemmap.slam.online.OnlineMapper` replaying the log at sensor rate
  (``latency_ms_p50/p99`` per scan, process CPU time per scan) and a 10x-length replay (the
  log driven ten times, each pass shifted in time and placed 1 km apart so the map keeps
  growing) for the peak RSS (``replay10x_peak_rss_mb``), each in a fresh subprocess.

Usage::

    python benchmarks/slam_field.py --json [--data DIR] [--parts gnss,reloc,online]
        [--trials 20] [--write-gnss-csv FILE] [--reloc-diagnosis] [--reloc-per-trial]
        [--reloc-splits 400,600] [--reloc-splits-only]

``--write-gnss-csv`` writes the fused fixes as the CSV ``stemmap map --gnss`` reads (to repeat
the GNSS part from the command line). The machine is shared and loaded: latency is wall time
per scan (the load average is reported).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np

from slam_field_reloc import _reloc

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
        "gnss_ate_unused_halves_m": {"split_s": round(half, 1), **halves(res.trajectory)},
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


def _gnss(data: str | None, csv_out: str | None) -> dict[str, Any]:
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
    # the GNSS-frame track: path (of the track's CV choice) + the fused fixes' smoothed offset
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
    track = gnss_frame_trajectory(res_t.trajectory, g_off)
    rt = ate(track, vp.gps_times, vp.gps_xy, offset=off, keep=unused, align=False)
    base = Isam2Slam().run(vp.problem())
    rb = ate(base.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=unused)
    evidence = _gnss_evidence(vp, fused, unused, res, base)
    gm = _gnss_track_gm(vp, unused, chosen, res, base)
    return {
        "gnss_ate_unused_m": round(r.rmse, 3),
        "gnss_ate_unused_p95_m": round(r.p95, 3),
        "gnss_ate_unused_max_m": round(r.max, 3),
        "gnss_track_ate_unused_m": round(rt.rmse, 3),
        "gnss_track_ate_unused_p95_m": round(rt.p95, 3),
        "gnss_track_offset_rms_m": round(float(np.sqrt(np.mean(g_off.offset**2) * 2)), 3),
        "gnss_fixes_fused": len(fused),
        "gnss_fixes_scored": r.n,
        "gnss_fixes_outliers": res.stats.get("gnss_fixes_outliers"),
        "gnss_cpu_s": round(cpu, 2),
        "no_gnss_ate_unused_aligned_m": round(rb.rmse, 3),
        "gnss_chosen_by_cv": ch,
        "gnss_cv": cv_rows,
        "gnss_default_ate_unused_m": round(rd.rmse, 3),
        **gm,
        **evidence,
        "gnss_data": "Victoria Park full run; fused = every 10th screened fix, antenna at the "
        "laser; kernel and sigma chosen by 2-fold CV inside the fused fixes (default: Cauchy "
        "k 2.385, sigma 1.0 m); scored = the other screened fixes, no alignment. "
        "gnss_ate_unused_m = the tree-consistent path (what stemmap map --gnss writes); "
        "gnss_track_ate_unused_m = that path + the fused fixes' random-walk-smoothed offset "
        "(gnss_offset; the track as the GNSS reports it, following the GPS's own slowly "
        "varying error), its 4 settings also chosen by the CV",
    }


def _online(data: str | None, passes: int) -> dict[str, Any]:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.slam.online import replay

    vp = load_victoria_park(data)
    st = replay(vp.problem(), passes=passes)
    lat = np.asarray(st["latency_s"]) * 1e3
    cpu = np.asarray(st["cpu_s"]) * 1e3
    return {
        "cpu_ms_p50": round(float(np.percentile(cpu, 50)), 3),
        "cpu_ms_p99": round(float(np.percentile(cpu, 99)), 3),
        "passes": passes,
        "scans": int(lat.size),
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 3),
        "latency_ms_p99": round(float(np.percentile(lat, 99)), 3),
        "latency_ms_max": round(float(lat.max()), 3),
        "trees": st["trees"],
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "rss_mb_by_pass": st.get("rss_mb_by_pass"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--parts", default="gnss,reloc,online", help="comma list")
    ap.add_argument("--trials", type=int, default=20, help="relocalisation trials")
    ap.add_argument("--write-gnss-csv", default=None, help="write the fused fixes here")
    ap.add_argument(
        "--reloc-diagnosis",
        action="store_true",
        help="reloc part: also the keyframe-phase spread and the prior-map checks (~10 runs)",
    )
    ap.add_argument(
        "--reloc-per-trial",
        action="store_true",
        help="reloc part: map session 2 from every trial's pose, joint vs Huber prior (~40 runs)",
    )
    ap.add_argument(
        "--reloc-splits",
        default="",
        help="reloc part: also these session splits (s, comma list), the priors of SPLIT_PRIORS",
    )
    ap.add_argument(
        "--reloc-splits-only",
        action="store_true",
        help="reloc part: only the --reloc-splits rows (and the full run they compare to)",
    )
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--passes", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        if args.worker == "gnss":
            r = _gnss(args.data, args.write_gnss_csv)
        elif args.worker == "reloc":
            splits = [float(x) for x in args.reloc_splits.split(",") if x]
            r = _reloc(
                args.data, args.trials, args.reloc_diagnosis, args.reloc_per_trial, splits,
                splits_only=args.reloc_splits_only,
            )  # fmt: skip
        else:
            r = _online(args.data, args.passes)
        print(json.dumps(r))
        return
    parts = [p for p in args.parts.split(",") if p]
    jobs: list[tuple[str, list[str]]] = []
    for p in parts:
        if p == "online":
            jobs += [("online", ["--passes", "1"]), ("online10x", ["--passes", "10"])]
        else:
            jobs.append((p, []))
    results: dict[str, Any] = {}
    for name, extra in jobs:
        cmd = [sys.executable, __file__, "--worker", name.replace("10x", ""), *extra]
        cmd += ["--trials", str(args.trials)]
        if args.data:
            cmd += ["--data", args.data]
        if args.reloc_diagnosis and name == "reloc":
            cmd += ["--reloc-diagnosis"]
        if args.reloc_per_trial and name == "reloc":
            cmd += ["--reloc-per-trial"]
        if args.reloc_splits and name == "reloc":
            cmd += ["--reloc-splits", args.reloc_splits]
        if args.reloc_splits_only and name == "reloc":
            cmd += ["--reloc-splits-only"]
        if args.write_gnss_csv and name == "gnss":
            cmd += ["--write-gnss-csv", args.write_gnss_csv]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            results[name] = {"error": proc.stderr.strip().splitlines()[-3:] or ["failed"]}
            continue
        results[name] = json.loads(proc.stdout.strip().splitlines()[-1])
        results[name]["wall_s"] = round(time.perf_counter() - t0, 1)
    summary: dict[str, Any] = {}
    for key, part in (
        ("gnss_ate_unused_m", "gnss"),
        ("gnss_track_gm_ate_unused_m", "gnss"),
        ("reloc_success_rate", "reloc"),
        ("latency_ms_p99", "online"),
    ):
        summary[key] = results.get(part, {}).get(key)
    summary["replay10x_peak_rss_mb"] = results.get("online10x", {}).get("peak_rss_mb")
    out = {
        "benchmark": "slam_field",
        **summary,
        "results": results,
        "scenario": {
            "dataset": "ACFR Victoria Park (text redistribution), isam2 defaults",
            "cpu_count": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
        },
    }
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k, v in out.items():
            print(k, v)


if __name__ == "__main__":
    main()
