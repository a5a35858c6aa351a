"""Benchmark: systematic error of real wheel odometry (Victoria Park) and the wheel drift
estimate's calibration on it.

Victoria Park (Guivant & Nebot, ACFR text redistribution, /work/shared/datasets/victoria_park):
a car with a rear-wheel speed encoder and a steering-angle sensor at 40 Hz, GPS at 5 Hz with
outages and jumps, 4.0 km in 26 min. The odometry is turned into the unicycle controls a wheel
log gives ``stemmap map`` (rear-axle-centre speed and yaw rate of the Ackermann model,
:class:`stemmap.slam.motion.AckermannModel`: ``v_c = v_e / (1 - tan(a) H / L)``,
``omega = v_c tan(a) / L``), with the steering offset the loader estimates without GPS
(``--steer-offset`` 0 for the raw signal).

Windows of ``--length`` metres of driven distance (starts every ``--step`` m). Per window:

* **GPS fit**: the dead-reckoned laser point (the antenna is at the laser,
  docs/algorithms/slam.md) with a speed scale error ``s`` and a constant yaw-rate bias ``b``
  (``v (1 + s)``, ``omega + b``), started from an unknown pose ``(x0, y0, theta0)``, fitted to
  the screened GPS fixes (:func:`stemmap.eval.trajectory.screen_gps`) of the window: 5
  parameters, robust least squares (soft-L1, scale 1 m, the GPS's per-fix error), the window
  dead-reckoned again with the perturbed controls at every iteration. GPS dropouts: a window
  is used only when kept fixes lie within 10 % of its length of both ends and no gap between
  kept fixes is longer than 25 % of it (fixes dropped by the screening count as gaps). The GPS
  error is a slow offset (Gauss-Markov, 0.95 m per axis, correlation time 19.8 s, white 0.085
  m: docs/algorithms/slam.md "First-order Gauss-Markov model"), which does not average out
  within a window: its share of the spread of ``s`` and ``b`` is measured by fitting the same
  windows with that noise added to the unperturbed dead-reckoned path (``--noise-draws``
  draws) and is subtracted in quadrature from the robust RMS.
* ``--gain`` adds a third parameter to both fits, a yaw-rate scale error ``g`` (``omega (1 +
  g) + b``): the Ackermann yaw rate from the steering angle under-reads sharp turns.
* **SLAM fit** (cross-check, ``--no-slam`` to skip): the same parameters fitted to the
  iSAM2 path without GNSS (``Isam2Slam`` on the full run, tree-consistent to ~0.1 m at
  revisits), the start pose taken from that path; and the **measured end drift**: the window
  dead-reckoned from the SLAM pose at its start, the end-point distance to the SLAM pose at its
  end, % of the window's length.
* **estimate**: :func:`stemmap.cli._map_motion.wheel_drift_estimate` of the window's unicycle
  controls with the mapper's default motion noise (``UnicycleModel()``) and the default
  systematic sigmas (or ``--sigma-scale`` / ``--sigma-bias``), compared with the RMS of the
  measured end drifts.

Prints JSON lines: one summary per window length (medians, robust spreads and RMS of ``s``
and ``b``; the GPS-noise spread; the RMS measured end drift and the estimate / measured ratio).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/wheel_drift_victoria_park.py
        [--length 30 60 100 200 400] [--step 10] [--steer-offset RAD] [--noise-draws 10]
        [--gain] [--no-slam] [--rows] [--data DIR]

Takes ~15 min of CPU for the five lengths with 10 noise draws (the 400 m windows dominate).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from stemmap.cli._map_motion import WHEEL_SIGMA_SCALE, WHEEL_SIGMA_YAW_BIAS, wheel_drift_estimate
from stemmap.datasets.victoria_park import load_victoria_park
from stemmap.slam.base import Controls
from stemmap.slam.motion import UnicycleModel
from wheel_drift_calibration import dead_reckon

#: GPS error model of Victoria Park, per axis (docs/algorithms/slam.md, "First-order
#: Gauss-Markov model", whole run, fitted to the semivariogram of the GPS against the iSAM2
#: path's displacements): white nugget, offset sigma and its correlation time.
GPS_WHITE_M, GPS_BIAS_M, GPS_TAU_S = 0.085, 0.947, 19.8


@dataclass
class Run:
    """The run as unicycle controls of the rear-axle centre plus the references."""

    t: np.ndarray  # control times, s
    v: np.ndarray  # rear-axle-centre speed, m/s
    w: np.ndarray  # yaw rate, rad/s
    dist: np.ndarray  # driven distance at t, m
    offset: tuple[float, float]  # laser (antenna) in the vehicle frame, m
    gps_t: np.ndarray  # screened fixes
    gps_xy: np.ndarray
    slam_t: np.ndarray | None  # iSAM2 vehicle poses
    slam_p: np.ndarray | None


def load_run(data: str | None, steer_offset: float | None, slam: bool) -> Run:
    """Victoria Park as unicycle controls (module doc), its screened GPS and, with ``slam``,
    the iSAM2 path without GNSS."""
    vp = load_victoria_park(data)
    m = vp.model if steer_offset is None else replace(vp.model, steer_offset=steer_offset)
    vp = replace(vp, model=m)
    c = vp.controls
    alpha = c.steer + m.steer_offset
    v = m.centre_speed(c.speed, alpha)
    w = v * np.tan(alpha) / m.L
    dist = np.concatenate(([0.0], np.cumsum(np.abs(v[:-1]) * np.diff(c.times))))
    keep = vp.screened_gps()
    slam_t = slam_p = None
    if slam:
        from stemmap.slam.base import make_backend

        tr = make_backend("isam2").run(vp.problem()).trajectory
        slam_t, slam_p = np.asarray(tr.times), np.asarray(tr.poses)
    return Run(c.times, v, w, dist, m.sensor_offset, vp.gps_times[keep], vp.gps_xy[keep],
               slam_t, slam_p)  # fmt: skip


def laser_path(t: np.ndarray, run: Run, i: int, x: np.ndarray, offset: tuple[float, float]):
    """The point ``offset`` of the window ``i..`` dead-reckoned with speed ``v (1 + s)`` and yaw
    rate ``omega (1 + g) + b`` from the pose ``(x0, y0, theta0)``, ``x = (x0, y0, theta0, s, b,
    g)``: (n, 2) at every control time of the window, and the vehicle's headings."""
    n = t.size
    pose = dead_reckon(t, run.v[i : i + n] * (1 + x[3]), run.w[i : i + n] * (1 + x[5]) + x[4])
    th = pose[:, 2] + x[2]
    c, sn = math.cos(x[2]), math.sin(x[2])
    a, b = offset
    xy = np.c_[c * pose[:, 0] - sn * pose[:, 1], sn * pose[:, 0] + c * pose[:, 1]] + x[:2]
    return xy + np.c_[a * np.cos(th) - b * np.sin(th), a * np.sin(th) + b * np.cos(th)], th


def fit_path(
    run: Run,
    i: int,
    t: np.ndarray,
    idx: np.ndarray,
    obs: np.ndarray,
    *,
    gain: bool,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """``(x0, y0, theta0, s, b, g)`` fitting the dead-reckoned window to the points ``obs`` at
    control samples ``idx``: with ``start`` (a known start pose: the SLAM reference) only
    ``s, b`` (and ``g``) by least squares, the antenna offset 0; else all, the GPS antenna at
    the laser, robust (soft-L1, 1 m)."""
    offset = (0.0, 0.0) if start is not None else run.offset
    free = [3, 4, 5] if gain else [3, 4]
    if start is None:
        free = [0, 1, 2, *free]
    x = np.zeros(6)
    if start is not None:
        x[:3] = start
    else:  # the rigid alignment of the chord from the first to the last point
        q, _ = laser_path(t, run, i, x, offset)
        dq, do = q[idx[-1]] - q[idx[0]], obs[-1] - obs[0]
        x[2] = math.atan2(do[1], do[0]) - math.atan2(dq[1], dq[0])
        q, _ = laser_path(t, run, i, x, offset)
        x[:2] = obs[0] - q[idx[0]]

    def resid(y: np.ndarray) -> np.ndarray:
        x[free] = y
        return (laser_path(t, run, i, x, offset)[0][idx] - obs).ravel()

    scales = np.array([1.0, 1.0, 0.01, 0.01, 0.001, 0.01])[free]
    loss = "linear" if start is not None else "soft_l1"
    r = least_squares(resid, x[free], loss=loss, f_scale=1.0, x_scale=scales)
    x[free] = r.x
    return x


def gauss_markov(times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) GPS errors at ``times``: the Gauss-Markov offset plus white noise (per axis)."""
    out = np.empty((times.size, 2))
    x = rng.normal(0.0, GPS_BIAS_M, 2)
    for i in range(times.size):
        if i:
            phi = math.exp(-(times[i] - times[i - 1]) / GPS_TAU_S)
            x = phi * x + rng.normal(0.0, GPS_BIAS_M * math.sqrt(1 - phi * phi), 2)
        out[i] = x
    return out + rng.normal(0.0, GPS_WHITE_M, out.shape)


def windows(run: Run, length: float, step: float) -> list[tuple[int, int]]:
    """Control index ranges ``[i, j]`` of ``length`` m of driving, starts every ``step`` m."""
    starts = np.arange(0.0, run.dist[-1] - length, step)
    i = np.searchsorted(run.dist, starts)
    j = np.searchsorted(run.dist, starts + length)
    return [(int(a), int(b)) for a, b in zip(i, j, strict=True) if b < run.t.size]


def gps_in(run: Run, i: int, j: int, length: float) -> np.ndarray | None:
    """Indices of the kept fixes inside control window ``[i, j]``, or None when the coverage
    rule fails (module doc)."""
    t0, t1 = run.t[i], run.t[j]
    k = np.flatnonzero((run.gps_t >= t0) & (run.gps_t <= t1))
    if k.size < 10:
        return None
    d = np.interp(run.gps_t[k], run.t, run.dist) - run.dist[i]
    edges = np.concatenate(([0.0], d, [length]))
    if d[0] > 0.1 * length or length - d[-1] > 0.1 * length or np.diff(edges).max() > 0.25 * length:
        return None
    return k


def robust_sd(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else math.nan


def robust_rms(x: np.ndarray) -> float:
    """RMS about zero, robust: sqrt(median(x^2) / 0.455) (chi-square 1 dof median)."""
    return float(math.sqrt(np.median(x * x) / 0.4549)) if x.size else math.nan


PARAMS = ("scale", "bias", "gain")


def analyse(
    run: Run,
    length: float,
    step: float,
    draws: int,
    seed: int,
    sig: tuple[float, float],
    gain: bool,
) -> list[dict[str, float]]:
    """One row per window (module doc)."""
    rng = np.random.default_rng(seed)
    npar = 3 if gain else 2
    rows: list[dict[str, float]] = []
    for i, j in windows(run, length, step):
        t = run.t[i : j + 1]
        row: dict[str, float] = {"t0": float(t[0]), "duration_s": float(t[-1] - t[0])}
        row["turn_rad"] = float(np.sum(run.w[i:j] * np.diff(t)))
        ctl = Controls(t, run.v[i : j + 1], run.w[i : j + 1], "unicycle")
        est = wheel_drift_estimate(ctl, UnicycleModel(), sigma_scale=sig[0], sigma_bias=sig[1])
        row["estimate"] = float(est["drift_estimate_percent"])
        row["estimate_random"] = float(est["drift_random_percent"])
        k = gps_in(run, i, j, length)
        if k is not None:
            idx = np.clip(np.searchsorted(t, run.gps_t[k]), 0, t.size - 1)
            x = fit_path(run, i, t, idx, run.gps_xy[k], gain=gain)
            row.update(
                {f"gps_{n}": float(v) for n, v in zip(PARAMS[:npar], x[3 : 3 + npar], strict=True)}
            )
            row["gps_n"] = int(k.size)
            ideal = laser_path(t, run, i, np.zeros(6), run.offset)[0][idx]
            sim = [  # the GPS error model on the unperturbed path: the fit's noise
                fit_path(run, i, t, idx, ideal + gauss_markov(run.gps_t[k], rng), gain=gain)
                for _ in range(draws)
            ]
            if sim:
                sd = np.std([v[3 : 3 + npar] for v in sim], axis=0)
                row.update({f"noise_{n}": float(v) for n, v in zip(PARAMS[:npar], sd, strict=True)})
        if run.slam_t is not None:
            sref = _slam_at(run, t)
            x = fit_path(run, i, t, np.arange(t.size), sref[:, :2], gain=gain, start=sref[0])
            row.update(
                {f"slam_{n}": float(v) for n, v in zip(PARAMS[:npar], x[3 : 3 + npar], strict=True)}
            )
            dr = laser_path(t, run, i, np.r_[sref[0], 0.0, 0.0, 0.0], (0.0, 0.0))[0]
            row["end_drift"] = 100.0 * float(np.hypot(*(dr[-1] - sref[-1, :2]))) / length
        rows.append(row)
    return rows


def _slam_at(run: Run, t: np.ndarray) -> np.ndarray:
    assert run.slam_t is not None and run.slam_p is not None
    th = np.unwrap(run.slam_p[:, 2])
    return np.c_[
        np.interp(t, run.slam_t, run.slam_p[:, 0]),
        np.interp(t, run.slam_t, run.slam_p[:, 1]),
        np.interp(t, run.slam_t, th),
    ]


def summary(rows: list[dict[str, float]], length: float, step: float) -> dict[str, Any]:
    out: dict[str, Any] = {"length_m": length, "windows": len(rows),
                           "independent": int(len(rows) * step / length)}  # fmt: skip
    for src in ("gps", "slam"):
        for p in PARAMS:
            x = np.array([r[f"{src}_{p}"] for r in rows if f"{src}_{p}" in r])
            if not x.size:
                continue
            key = f"{src}_{p}"
            out[key] = {"n": int(x.size), "median": float(np.median(x)),
                        "p10_p90": [float(v) for v in np.percentile(x, [10, 90])],
                        "robust_sd": robust_sd(x), "robust_rms": robust_rms(x),
                        "rms": float(np.sqrt(np.mean(x * x)))}  # fmt: skip
            if src == "gps":
                nz = np.array([r[f"noise_{p}"] for r in rows if f"noise_{p}" in r])
                if nz.size:
                    noise = float(np.sqrt(np.mean(nz * nz)))
                    out[key]["gps_noise_sd"] = noise
                    rr = out[key]["robust_rms"]
                    out[key]["rms_minus_noise"] = math.sqrt(max(rr * rr - noise * noise, 0.0))
    drift = np.array([r["end_drift"] for r in rows if "end_drift" in r])
    if drift.size:
        end = float(np.sqrt(np.mean(drift**2)))
        est = float(np.median([r["estimate"] for r in rows]))
        rnd = float(np.median([r["estimate_random"] for r in rows]))
        out["end_drift_rms"] = end
        out["end_drift_median"] = float(np.median(drift))
        out["estimate"], out["estimate/end"] = est, est / end
        out["random_only"], out["random_only/end"] = rnd, rnd / end
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--length", type=float, nargs="+", default=[30.0, 60.0, 100.0, 200.0])
    ap.add_argument("--step", type=float, default=10.0)
    ap.add_argument("--steer-offset", type=float, default=None, help="rad (default: loader's)")
    ap.add_argument("--noise-draws", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sigma-scale", type=float, default=WHEEL_SIGMA_SCALE)
    ap.add_argument("--sigma-bias", type=float, default=WHEEL_SIGMA_YAW_BIAS, help="rad/s")
    ap.add_argument("--no-slam", action="store_true")
    ap.add_argument("--gain", action="store_true", help="also fit a yaw-rate scale error")
    ap.add_argument("--rows", action="store_true", help="also print every window")
    args = ap.parse_args(argv)
    run = load_run(args.data, args.steer_offset, not args.no_slam)
    sig = (args.sigma_scale, args.sigma_bias)
    for length in args.length:
        rows = analyse(run, length, args.step, args.noise_draws, args.seed, sig, args.gain)
        if args.rows:
            for r in rows:
                print(json.dumps({"length_m": length, **r}), flush=True)
        print(json.dumps(summary(rows, length, args.step)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
