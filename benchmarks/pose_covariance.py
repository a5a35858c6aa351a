"""Calibration of every back-end's pose covariance (trajectory.csv, ``SlamResult.pose_covs``).

Issue 14: every back-end writes a pose covariance on every row; this measures what it is worth.

``--sim`` (the ``stemmap demo`` scenario, ``--seeds``; the map frame is the true frame: the
run starts at the true initial pose): each reported vehicle pose against the true one, the
first row (fixed, zero covariance) left out. Position ``z² = eᵀ C⁻¹ e`` (2 dof: calibrated
mean 2, median 1.386, 86.5 % inside the 2-sigma ellipse ``z² < 4``), the full pose's NEES
(x, y, θ; calibrated mean 3) and the heading's ``z²`` (median 0.455). These test the code: the
simulator is not used to choose any factor.

``--vp`` (the full Victoria Park run, every back-end at its defaults): the laser point at every
screened GPS fix after the ATE's SE(2) fit against the fix (the pose covariance carried to the
laser point and rotated by the fit, ``_pose_cov.pose_terms``). The GPS has an error
of its own: its RMS is estimated from the fixes' disagreement with themselves at revisits of
the iSAM2 path (:func:`stemmap.eval.gps_noise.gps_revisit_error`) and added to the reported
covariance as an isotropic ``G = rms² / 2 I``. Per half of the run (split at its middle time):
median / mean ``z²`` of ``e`` under ``C + G`` and the share inside 2 sigma; and the variance
factor ``k`` that makes the first half's median ``z²`` under ``k C + G`` equal 2 ln 2 (the
factor a back-end would need; the second half checks the factor in the code), and the
maximum-likelihood factor of ``e ~ N(0, k C + G)`` on the first half (defined also where the
GPS's error alone explains the median) with the second half scored at it.

Usage: python benchmarks/pose_covariance.py --sim --seeds 1 2 3
       python benchmarks/pose_covariance.py --vp [--backends isam2 treedb online]
       (``online``: the realtime iSAM2 mapper of ``stemmap map --realtime``)
       python benchmarks/pose_covariance.py --vp-gnss
       python benchmarks/pose_covariance.py --vp-ekf-map-factor
       python benchmarks/pose_covariance.py --vp-ekf-residual-noise
Prints JSON. The machine is shared; times are not reported.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from _pose_cov import BACKENDS, pose_errors
from _pose_cov import fit_inflation as _fit_inflation
from _pose_cov import lever as _lever
from _pose_cov import pose_terms as _pose_terms
from _pose_cov import z2 as _z2


def _stats(z2: np.ndarray, dof: int) -> dict[str, float]:
    from scipy.stats import chi2

    return {
        "z2_mean": round(float(np.mean(z2)), 3),
        "z2_median": round(float(np.median(z2)), 3),
        "calibrated_median": round(float(chi2.ppf(0.5, dof)), 3),
        "share_in_2sigma": round(float(np.mean(z2 < 4.0)), 3),
        "calibrated_share_in_2sigma": round(float(chi2.cdf(4.0, dof)), 3),
    }


def _run(backend: str, problem: Any) -> Any:
    """``backend`` on ``problem``; ``online``: the realtime iSAM2 mapper (``--realtime``)."""
    from stemmap.slam.base import SlamResult, make_backend

    if backend != "online":
        return make_backend(backend).run(problem)
    from stemmap.slam.online import replay

    st = replay(problem)
    return SlamResult(st["trajectory"], st["stem_map"], pose_covs=st["pose_covs"])


def sim_rows(seed: int, backend: str) -> dict[str, Any]:
    """One simulated run: (position error, covariance, heading error, full-pose NEES) per row."""
    from stemmap.cli._demo import _stand_and_run
    from stemmap.cli._map import sim_problem
    from stemmap.scan.detect import ScanTrunkDetector

    run = _stand_and_run(seed, 120)
    # the motion noise `stemmap demo` hands this back-end (iSAM2: the white part only)
    problem, _ = sim_problem(
        run,
        ScanTrunkDetector().detect_batch(run.scans),
        backend=backend,
    )
    return pose_errors(run, _run(backend, problem))


def sim(seeds: list[int], backends: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {"scenario": "stemmap demo, 120 trees", "seeds": seeds}
    for b in backends:
        runs = [sim_rows(s, b) for s in seeds]
        row: dict[str, Any] = {
            "rows": sum(r["rows"] for r in runs),
            "rows_with_covariance": sum(r["rows_with_covariance"] for r in runs),
        }
        if all("e" in r for r in runs):
            cat = {k: np.concatenate([r[k] for r in runs]) for k in ("e", "z2_pos", "z2_th")}
            nees = np.concatenate([r["nees"] for r in runs])
            std = np.concatenate([r["std"] for r in runs])
            row |= {
                "median_position_error_m": round(float(np.median(np.hypot(*cat["e"][:, :2].T))), 3),
                "median_position_std_m": round(float(np.median(std)), 3),
                "position": _stats(cat["z2_pos"], 2),
                "position_z2_median_per_seed": [
                    round(float(np.median(r["z2_pos"])), 3) for r in runs
                ],
                "heading": _stats(cat["z2_th"], 1),
                "pose_nees_mean (calibrated 3)": round(float(np.mean(nees)), 3),
            }
        out[b] = row
    return out


def ml_factor(e: np.ndarray, C: np.ndarray, G: np.ndarray) -> float:
    """Maximum-likelihood variance factor ``k`` of ``e ~ N(0, k C + G)`` (fixes independent;
    ``G`` the reference's own noise): well defined also where ``G`` alone explains the median,
    where :func:`_pose_cov.fit_inflation` has no root."""
    from scipy.optimize import minimize_scalar

    def nll(lk: float) -> float:
        S = np.exp(lk) * C + G
        return float(np.sum(np.log(np.linalg.det(S))) + np.sum(_z2(e, S)))

    r = minimize_scalar(nll, bounds=(-15.0, 8.0), method="bounded")
    return float(np.exp(r.x))


def _vp_halves() -> tuple[Any, Any, np.ndarray, np.ndarray, float]:
    """Victoria Park: the dataset, its problem, the screened GPS fixes (mask), the frames'
    times and the time that splits the run into the halves the calibrations are chosen and
    scored on."""
    from stemmap.datasets.victoria_park import load_victoria_park

    vpd = load_victoria_park(None)
    problem = vpd.problem()
    t = problem.frames.times
    return vpd, problem, vpd.screened_gps(), t, 0.5 * (t[0] + t[-1])


def _vp_gps_cov(vpd: Any, problem: Any, keep: np.ndarray, ref: Any) -> tuple[np.ndarray, Any]:
    """The GPS's own error as an isotropic covariance ``G = rms² / 2 I`` (m²), from the fixes'
    disagreement at revisits of the locally right path ``ref`` (an iSAM2 result); with the
    :func:`stemmap.eval.gps_noise.gps_revisit_error` report."""
    from stemmap.eval.gps_noise import gps_revisit_error
    from stemmap.eval.trajectory import align_se2, point_track

    t = problem.frames.times
    m = keep & (vpd.gps_times >= t[0]) & (vpd.gps_times <= t[-1])
    gt, gxy = vpd.gps_times[m], vpd.gps_xy[m]
    ref_xy = point_track(ref.trajectory, gt, vpd.model.sensor_offset)
    gps = gps_revisit_error(gt, gxy, align_se2(ref_xy, gxy).apply(ref_xy))
    return np.eye(2) * gps.rms_2d**2 / 2.0, gps


def vp(backends: list[str], dump: str | None = None) -> dict[str, Any]:
    from stemmap.slam.base import make_backend

    vpd, problem, keep, t, t_mid = _vp_halves()
    results = {b: _run(b, problem) for b in backends}
    # the GPS's own error: revisits of a locally right path (iSAM2's, run here if not asked)
    ref = results.get("isam2") or make_backend("isam2").run(problem)
    G, gps = _vp_gps_cov(vpd, problem, keep, ref)
    n_fixes = int((keep & (vpd.gps_times >= t[0]) & (vpd.gps_times <= t[-1])).sum())
    out: dict[str, Any] = {
        "t_split_s": round(float(t_mid), 1),
        "screened_fixes": n_fixes,
        "gps_rms_2d_m (revisits of the iSAM2 path)": round(gps.rms_2d, 3),
        "gps_revisit_pairs": gps.pairs,
    }
    for b, res in results.items():
        n = len(res.trajectory)
        if res.pose_covs is None:
            out[b] = {"rows": n, "rows_with_covariance": 0}
            continue
        fin = np.all(np.isfinite(res.pose_covs), axis=(1, 2))
        ft, e, C = _pose_terms(res, vpd, keep)
        ok = np.all(np.isfinite(C), axis=(1, 2))
        row: dict[str, Any] = {
            "rows": n,
            "rows_with_covariance": int(fin.sum()),
            "fixes_with_covariance": int(ok.sum()),
            "median_error_m": round(float(np.median(np.hypot(*e[ok].T))), 3),
            "median_std_m": round(
                float(np.median(np.sqrt(0.5 * np.trace(C[ok], axis1=1, axis2=2)))), 3
            ),
        }
        first, second = ok & (ft < t_mid), ok & (ft >= t_mid)
        for label, sel in (("first_half", first), ("second_half", second), ("all", ok)):
            row[label + "_with_gps_noise"] = _stats(_z2(e[sel], C[sel] + G), 2)
        try:
            k = round(_fit_inflation(e[first], C[first], np.broadcast_to(G, C[first].shape)), 3)
        except ValueError:  # no factor reaches the median: the GPS's own error alone does
            k = None
        row["factor_for_median_on_first_half"] = k
        k_ml = ml_factor(e[first], C[first], G)
        row["factor_ml_on_first_half"] = round(k_ml, 4)
        row["second_half_with_gps_noise_at_ml_factor"] = _stats(
            _z2(e[second], k_ml * C[second] + G), 2
        )
        if dump:
            np.savez(f"{dump}_{b}.npz", t=ft, e=e, C=C, G=G, t_mid=t_mid)
        out[b] = row
        print(json.dumps({b: row}), file=sys.stderr, flush=True)
    return out


def vp_gnss() -> dict[str, Any]:
    """iSAM2 with every 10th screened fix fused (``VictoriaPark.gnss_split``): the laser point
    (= the antenna) against the fixes NOT fused, no alignment (the map is in the GPS frame);
    covariance = the pose covariance carried to the laser point + the GPS's own ``G``."""
    import dataclasses

    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.gps_noise import gps_revisit_error
    from stemmap.eval.trajectory import point_track
    from stemmap.slam.base import make_backend

    vpd = load_victoria_park(None)
    fx, unused = vpd.gnss_split()
    problem = dataclasses.replace(vpd.problem(), gnss=fx)
    res = make_backend("isam2").run(problem)
    t = res.trajectory.times
    m = unused & (vpd.gps_times >= t[0]) & (vpd.gps_times <= t[-1])
    gt, gxy = vpd.gps_times[m], vpd.gps_xy[m]
    est = point_track(res.trajectory, gt, vpd.model.sensor_offset)
    fi = np.clip(np.searchsorted(t, gt), 0, len(t) - 1)
    J = _lever(res.trajectory.interpolate(gt), est)
    P = np.asarray(res.pose_covs)
    C = J @ P[fi] @ np.swapaxes(J, 1, 2)
    gps = gps_revisit_error(gt, gxy, est)
    G = np.eye(2) * gps.rms_2d**2 / 2.0
    e = est - gxy
    return {
        "rows": len(t),
        "rows_with_covariance": int(np.all(np.isfinite(P), axis=(1, 2)).sum()),
        "fixes_scored": int(gt.size),
        "gps_rms_2d_m": round(gps.rms_2d, 3),
        "median_error_m": round(float(np.median(np.hypot(*e.T))), 3),
        "median_std_m": round(float(np.median(np.sqrt(0.5 * np.trace(C, axis1=1, axis2=2)))), 3),
        "with_gps_noise": _stats(_z2(e, C + G), 2),
    }


def vp_ekf_map_factor() -> dict[str, Any]:
    """The EKF's map-term factor (``EkfConfig.map_cov_inflation``) chosen on the first half of
    Victoria Park and scored on the second: the EKF run with the factor 0 (the path given the
    map) and 1 (the default) -- the same estimate, the reported covariance ``C(F) = C0 + F Cm``
    linear in ``F`` -- and ``F`` the maximum-likelihood factor of ``e ~ N(0, C(F) + G)`` on
    the first half (the GPS's error ``G`` as in ``--vp``), and the factor putting 86.5 % of the
    first half inside 2 sigma (the criterion of the tree DB / Forestrix chain factor, gone
    since Dec 3); the median criterion is reported too (None where a criterion has no root)."""
    from scipy.optimize import brentq

    from stemmap.slam.base import make_backend

    vpd, problem, keep, _, t_mid = _vp_halves()
    G, gps = _vp_gps_cov(vpd, problem, keep, make_backend("isam2").run(problem))
    ft, e, C0 = _pose_terms(make_backend("ekf", map_cov_inflation=0.0).run(problem), vpd, keep)
    _, e1, C1 = _pose_terms(make_backend("ekf").run(problem), vpd, keep)
    assert np.allclose(e, e1)  # the factor changes the covariance only
    ok = np.all(np.isfinite(C0), axis=(1, 2)) & np.all(np.isfinite(C1), axis=(1, 2))
    first, second = ok & (ft < t_mid), ok & (ft >= t_mid)
    Cm = C1 - C0
    base = C0 + G
    try:  # no root when the GPS's own error explains the first half's median ("--vp")
        f_med: float | None = round(_fit_inflation(e[first], Cm[first], base[first]), 2)
    except ValueError:
        f_med = None
    f = ml_factor(e[first], Cm[first], base[first])

    def coverage(lk: float) -> float:  # the criterion of the former chain factor
        return float(np.mean(_z2(e[first], np.exp(lk) * Cm[first] + base[first]) < 4.0)) - 0.865

    try:
        f_cov: float | None = float(np.exp(brentq(coverage, np.log(1e-3), np.log(1e5), xtol=1e-3)))
    except ValueError:
        f_cov = None
    out: dict[str, Any] = {
        "t_split_s": round(float(t_mid), 1),
        "gps_rms_2d_m": round(gps.rms_2d, 3),
        "factor_for_median_on_first_half": f_med,
        "factor_ml_on_first_half": round(f, 2),
        "factor_for_coverage_on_first_half": None if f_cov is None else round(f_cov, 2),
    }
    factors = {"factor_1": 1.0, "factor_0": 0.0, "ml_factor": f}
    if f_cov is not None:
        factors["coverage_factor"] = f_cov
    for label, k in factors.items():
        out[label] = {
            "first_half": _stats(_z2(e[first], k * Cm[first] + base[first]), 2),
            "second_half": _stats(_z2(e[second], k * Cm[second] + base[second]), 2),
        }
    return out


def _ekf_with_residuals(problem: Any, **config: Any) -> tuple[Any, tuple[Any, ...]]:
    """An EKF run and the inputs of its residual noise (the associated detections, the
    smoothed path, the map, the sensor offset), caught where the run measures it."""
    import stemmap.slam._ekf_compressed as ekf_c
    from stemmap.slam.base import make_backend

    caught: list[tuple[Any, ...]] = []
    orig = ekf_c.residual_noise_stats

    def catch(*args: Any) -> Any:
        caught.append(args)
        return orig(*args)

    ekf_c.residual_noise_stats = catch  # type: ignore[assignment]
    try:
        res = make_backend("ekf", **config).run(problem)
    finally:
        ekf_c.residual_noise_stats = orig  # type: ignore[assignment]
    return res, caught[-1]


def vp_ekf_residual_noise() -> dict[str, Any]:
    """The EKF's detection noise measured from its residuals (``EkfConfig.noise_from_residuals``;
    :mod:`stemmap.slam.residual_noise`), two folds on Victoria Park: the default run's residuals
    of one half of the run (detections before / after the middle time) give the long-run range
    and bearing std; the EKF re-run with them is scored on the *other* half (laser point vs GPS,
    the GPS's own error ``G`` counted, as ``--vp``); and the noise of the whole run (what the
    option uses) scored on both halves. ATE (m) of every run."""
    from stemmap.eval.trajectory import ate
    from stemmap.slam.base import make_backend
    from stemmap.slam.residual_noise import detection_residuals, residual_noise

    vpd, problem, keep, t, t_mid = _vp_halves()
    G, gps = _vp_gps_cov(vpd, problem, keep, make_backend("isam2").run(problem))

    def score(res: Any) -> dict[str, Any]:
        ft, e, C = _pose_terms(res, vpd, keep)
        ok = np.all(np.isfinite(C), axis=(1, 2))
        a = ate(
            res.trajectory, vpd.gps_times, vpd.gps_xy, offset=vpd.model.sensor_offset, keep=keep
        )
        return {
            "ate_m": round(a.rmse, 3),
            "trees": len(res.stem_map.trees),
            "first_half": _stats(_z2(e[ok & (ft < t_mid)], C[ok & (ft < t_mid)] + G), 2),
            "second_half": _stats(_z2(e[ok & (ft >= t_mid)], C[ok & (ft >= t_mid)] + G), 2),
        }

    res0, (poses, obs, lm_xy, off) = _ekf_with_residuals(problem)
    fr, lj, rz, bz = obs
    e = detection_residuals(poses, fr, lj, rz, bz, lm_xy, off)
    halves = {"first_half": t[fr] < t_mid, "second_half": t[fr] >= t_mid}
    out: dict[str, Any] = {
        "t_split_s": round(float(t_mid), 1),
        "gps_rms_2d_m": round(gps.rms_2d, 3),
        "default": {"sigma_range_m": 0.30, "sigma_bearing_deg": 1.0} | score(res0),
    }
    noise: dict[str, tuple[float, float]] = {}
    for label, sel in (*halves.items(), ("whole", np.ones(fr.size, dtype=bool))):
        r = residual_noise(fr[sel], lj[sel], e[sel])
        noise[label] = r.sigma_long_run
        out[f"residuals_{label}"] = {
            "sigma_range_m": round(r.sigma[0], 4),
            "sigma_bearing_deg": round(math.degrees(r.sigma[1]), 4),
            "lag1_correlation (range, bearing)": [round(r.rho[0][0], 3), round(r.rho[1][0], 3)],
            "lag10_correlation (range, bearing)": [round(r.rho[0][9], 3), round(r.rho[1][9], 3)],
            "long_run_sigma_range_m": round(r.sigma_long_run[0], 4),
            "long_run_sigma_bearing_deg": round(math.degrees(r.sigma_long_run[1]), 4),
            "used": r.used,
            "removed_as_gross": r.removed,
        }
    for label in ("first_half", "second_half", "whole"):
        sr, sb = noise[label]
        out[f"noise_from_{label}"] = {
            "sigma_range_m": round(sr, 4),
            "sigma_bearing_deg": round(math.degrees(sb), 4),
        } | score(make_backend("ekf", sigma_range=sr, sigma_bearing=sb).run(problem))
        print(json.dumps({label: out[f"noise_from_{label}"]}), file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS))
    ap.add_argument("--sim", action="store_true", help="the simulator check (module doc)")
    ap.add_argument("--vp", action="store_true", help="the Victoria Park check (module doc)")
    ap.add_argument("--vp-gnss", action="store_true", help="iSAM2 with GNSS on VP (vp_gnss)")
    ap.add_argument(
        "--vp-ekf-map-factor", action="store_true", help="choose the EKF map-term factor on VP"
    )
    ap.add_argument(
        "--vp-ekf-residual-noise",
        action="store_true",
        help="the EKF's detection noise from its residuals, two folds on VP",
    )
    ap.add_argument("--dump", default=None, help="with --vp: save PREFIX_BACKEND.npz (t, e, C, G)")
    a = ap.parse_args()
    out: dict[str, Any] = {}
    if a.sim:
        out["simulator"] = sim(a.seeds, a.backends)
    if a.vp:
        out["victoria_park"] = vp(a.backends, a.dump)
    if a.vp_ekf_map_factor:
        out["victoria_park_ekf_map_factor"] = vp_ekf_map_factor()
    if a.vp_ekf_residual_noise:
        out["victoria_park_ekf_residual_noise"] = vp_ekf_residual_noise()
    if a.vp_gnss:
        out["victoria_park_isam2_gnss"] = vp_gnss()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
