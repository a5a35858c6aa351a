"""Benchmark: the visual odometry's drift estimate (``drift_estimate_percent`` of ``stemmap map
--motion visual``) against the measured drift, on rendered stereo drives at several camera
rates.

Drives: the S-curve along the middle aisle of a 3-row orchard of tests/odometry/conftest.py
(rows 4 m apart, trees 3 m apart; :func:`stemmap.sim.render.render_stereo` with the default
``StereoCamera``, 320 x 200 px, 2 grey levels of pixel noise), ``--length`` metres at 1 m/s,
rendered at each ``--rates`` (Hz) for each seed (seed = the stand's jitter and the pixel
noise). Each is run through :func:`stemmap.odometry.visual.run_visual_odometry` and
:func:`~stemmap.odometry.visual.planar_from_camera` with the default config, as ``stemmap map
--motion visual --camera FOLDER`` does (``stemmap.cli._odometry_camera.camera_trajectory``).

Per rate (seeds pooled) it prints: ``end_rms`` (RMS over seeds of the end-point error, % of
the true length; the odometry frame is the vehicle at the first frame), split into ``along``
(mean and RMS of its component along the final true heading: a scale error) and ``cross_rms``
(across it), ``length_err`` (mean error of the reported ``distance_m`` against the true
length, %), ``step_sd`` (std of the frame-to-frame change of path length against the truth's,
m), ``keyframes`` (mean count), ``estimate`` (median of the
reported ``drift_estimate_percent``, :func:`stemmap.cli._map_motion.visual_drift_estimate`: a
random walk of ``VISUAL_DRIFT_XY_PER_SQRT_M`` per sqrt(metre)) with ``estimate / end_rms``, and
``old`` with ``old / end_rms`` (the estimate until Dec 4: :data:`OLD_STEP_SIGMA_M` per axis per
frame as independent steps, which grew with the frame rate). ``c_fit`` is the random-walk
constant these runs alone give, ``sqrt(mean(|e|² / d))`` (m per sqrt(m); ``e`` the end error,
``d`` the reported distance): how ``VISUAL_DRIFT_XY_PER_SQRT_M`` was measured.

The EKF's VO noise (:func:`stemmap.odometry.visual.visual_velocity_sigma`, what ``stemmap map
--motion fused`` gives the filter): ``speed_rms_m_s`` and ``yaw_rate_rms_deg_s`` (RMS over
seeds of the errors of the per-interval speed and yaw rate as
:func:`stemmap.odometry.fusion.velocities_from_poses` makes them), ``step_sigma_m`` /
``step_sigma_deg`` (the same times the frame interval), and ``library_z2`` / ``old_z2``:
mean z^2 per degree of freedom of those errors (speed, yaw rate) under the library's noise
and under the noise until Dec 4 (:data:`OLD_STEP_SIGMA_M`, :data:`OLD_STEP_SIGMA_RAD` per step
at any rate). ``VISUAL_STEP_SIGMA`` was fitted to these errors with ``--rates 5 10 20 40
--seeds 0 1 2 3 4 --work DIR`` and :func:`fit_step_sigma`.

Usage::

    python benchmarks/visual_drift_calibration.py [--rates 5 10 20] [--seeds 0 1 2]
        [--length 10] [--work DIR] [--render-cache DIR [--base-rate HZ]]

The last line, ``step_sigma_fit``, is :func:`fit_step_sigma` over all the runs: ``free`` (the
exponent fitted too) and ``white`` (exponent 0.5, the library's form).

``--work DIR`` keeps each run's trajectories (``vo_<rate>hz_s<seed>.npz``); with the files
present they are re-read instead of re-rendered. ``--render-cache DIR`` renders each seed's
drive once, noise-free, at the highest rate (every rate must divide it), stores the images
(float32, ``clean_s<seed>_<length>m_<rate>hz.npz``, ~0.7 GB per seed for 10 m at 40 Hz) and
makes each rate's frames from every k-th of them, adding the pixel noise as
:func:`~stemmap.sim.render.iter_stereo` does (same generator, seed and order): the same drives
as without the cache, rendered once, so the odometry can be re-run on them after a change.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.cli._map_motion import _random_walk_percent, visual_drift_estimate
from stemmap.eval.trajectory import path_length
from stemmap.odometry.visual import StereoCalibration, VoStatus, visual_velocity_sigma
from stemmap.types import Trajectory

#: The VO's step noise until Dec 4 (``VISUAL_STEP_SIGMA`` then: one step's error at any camera
#: rate, measured at 10 Hz on tests/odometry's 4.9 m drive with the tracking from the previous
#: image); the old drift estimate and the ``old_z2`` column use it.
OLD_STEP_SIGMA_M, OLD_STEP_SIGMA_RAD = 0.0041, math.radians(0.029)


def s_curve(length: float, rate_hz: float, speed: float = 1.0) -> Trajectory:
    """tests/odometry/conftest.py's S-curve along the aisle y = 2 m, ``length`` m long (in x)."""
    t = np.arange(round(length / speed * rate_hz) + 1) / rate_hz
    x = -2.0 + speed * t
    y = 2.0 + 0.3 * np.sin(x / 4.0)
    th = np.arctan2(0.3 / 4.0 * np.cos(x / 4.0), 1.0)
    return Trajectory(t, np.column_stack((x, y, th)), frame="world")


def _stand(seed: int) -> Any:
    from stemmap.sim.forest import row_stand
    from stemmap.sim.render import stand3d_from_stand

    stand = row_stand(3, 10, row_spacing=4.0, tree_spacing=3.0, rng=seed + 1)
    return stand3d_from_stand(stand, rng=seed + 2)


def clean_frames(seed: int, length: float, rate_hz: float, cache: Path) -> dict[str, np.ndarray]:
    """Noise-free left / right images (float32) of the drive at ``rate_hz``, rendered once
    into ``cache`` (``--render-cache``)."""
    from stemmap.sim.render import StereoCamera, camera_poses, render_view

    f = cache / f"clean_s{seed}_{length:g}m_{rate_hz:g}hz.npz"
    if f.exists():
        z = np.load(f)
        return {k: z[k] for k in ("t", "left", "right")}
    stand, cam, truth = _stand(seed), StereoCamera(rate_hz=rate_hz), s_curve(length, rate_hz)
    T_wc = camera_poses(truth, cam)
    T_lr = np.eye(4)
    T_lr[0, 3] = cam.baseline
    views = [
        [render_view(stand, T, cam)[0].astype(np.float32) for T in (T_wc[k], T_wc[k] @ T_lr)]
        for k in range(len(truth))
    ]
    out = {
        "t": truth.times,
        "left": np.array([v[0] for v in views]),
        "right": np.array([v[1] for v in views]),
    }
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(f, **out)
    return out


def simulate_visual_drive(
    rate_hz: float,
    seed: int,
    length: float,
    *,
    render_cache: Path | None = None,
    base_rate: float | None = None,
) -> tuple[Trajectory, Trajectory, int]:
    """(visual odometry vehicle path in its odom frame, truth in the same frame, keyframes).

    With ``render_cache`` the frames are every ``base_rate / rate_hz``-th noise-free image of
    :func:`clean_frames` at ``base_rate``, with the pixel noise of :func:`iter_stereo` added.
    """
    from stemmap.odometry.visual import VisualFrame, planar_from_camera, run_visual_odometry
    from stemmap.sim.render import StereoCamera, iter_stereo

    cam = StereoCamera(rate_hz=rate_hz)
    truth = s_curve(length, rate_hz)
    k = cam.K
    calib = StereoCalibration(
        cam.fx, cam.fx, k[0, 2], k[1, 2], cam.width, cam.height, baseline=cam.baseline
    )
    frames: Any
    if render_cache is None:
        frames = (
            VisualFrame(f.time, f.left, f.right)
            for f in iter_stereo(_stand(seed), truth, cam, rng=seed)
        )
    else:
        base = base_rate or rate_hz
        stride = round(base / rate_hz)
        if abs(stride * rate_hz - base) > 1e-9 * base:
            raise SystemExit(f"--render-cache: {rate_hz:g} Hz does not divide {base:g} Hz.")
        z = clean_frames(seed, length, base, render_cache)
        idx = np.arange(0, len(z["t"]), stride)
        if len(idx) != len(truth) or not np.allclose(z["t"][idx], truth.times):
            raise SystemExit("--render-cache: cached frame times do not match the drive.")
        gen = np.random.default_rng(seed)

        def noisy(img: np.ndarray) -> np.ndarray:
            a = img.astype(np.float64)
            if cam.pixel_noise > 0:
                a = a + gen.normal(0.0, cam.pixel_noise, a.shape)
            return np.clip(np.rint(a), 0, 255).astype(np.uint8)

        frames = (
            VisualFrame(float(truth.times[j]), noisy(z["left"][i]), noisy(z["right"][i]))
            for j, i in enumerate(idx)
        )
    res = run_visual_odometry(frames, calib)
    traj = planar_from_camera(res, cam.vehicle_from_camera())
    return traj, in_start_frame(truth), int(np.sum(res.status == VoStatus.KEYFRAME))


def in_start_frame(truth: Trajectory) -> Trajectory:
    """The truth in the frame of its first pose (the visual odometry's odom frame)."""
    p = truth.poses
    c, s = math.cos(p[0, 2]), math.sin(p[0, 2])
    d = p[:, :2] - p[0, :2]
    xy = np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))
    return Trajectory(truth.times, np.column_stack((xy, p[:, 2] - p[0, 2])), frame="odom")


def reported_estimate(traj: Trajectory) -> float | None:
    """``drift_estimate_percent`` of ``stemmap map --motion visual`` for this path."""
    est = visual_drift_estimate(traj)["drift_estimate_percent"]
    return None if est is None else float(est)


def old_estimate(traj: Trajectory) -> float | None:
    """The estimate until Dec 4: one step of :data:`OLD_STEP_SIGMA_M` per axis per frame,
    independent, over ``path_length``."""
    n = len(traj) - 1
    return _random_walk_percent(np.full(n, 2.0 * OLD_STEP_SIGMA_M**2), path_length(traj))


def velocity_errors(traj: Trajectory, truth: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Errors of the VO's per-interval speed (m/s) and yaw rate (rad/s) as the EKF gets them
    (:func:`stemmap.odometry.fusion.velocities_from_poses`, what ``stemmap map --motion
    fused`` feeds it) against the truth's, differenced the same way."""
    from stemmap.odometry.fusion import velocities_from_poses

    a = velocities_from_poses(traj, sigma_speed=1.0, sigma_yaw_rate=1.0)
    b = velocities_from_poses(truth, sigma_speed=1.0, sigma_yaw_rate=1.0)
    return a.speed - b.speed, a.yaw_rate - b.yaw_rate


def measure(traj: Trajectory, truth: Trajectory, keyframes: int) -> dict[str, float]:
    """One run: the reported estimate and the measured end error (both % of distance)."""
    true_m = path_length(truth, min_step=0.0)
    err = traj.poses[-1, :2] - truth.poses[-1, :2]
    th = float(truth.poses[-1, 2])
    step = np.hypot(*np.diff(traj.poses[:, :2], axis=0).T)
    true_step = np.hypot(*np.diff(truth.poses[:, :2], axis=0).T)
    est, old = reported_estimate(traj), old_estimate(traj)
    ev, ew = velocity_errors(traj, truth)
    return {
        "frames": float(len(traj)),
        "dt": float(np.median(np.diff(traj.times))),
        "keyframes": float(keyframes),
        "distance_m": path_length(traj),
        "end": 100.0 * float(np.hypot(*err)) / true_m,
        "along": 100.0 * float(err[0] * math.cos(th) + err[1] * math.sin(th)) / true_m,
        "cross": 100.0 * float(-err[0] * math.sin(th) + err[1] * math.cos(th)) / true_m,
        "length_err": 100.0 * (path_length(traj) / true_m - 1.0),
        "step_sd": float(np.std(step - true_step)),
        "speed_rms": float(np.sqrt(np.mean(ev**2))),
        "yaw_rate_rms": math.degrees(float(np.sqrt(np.mean(ew**2)))),
        "estimate": float("nan") if est is None else est,
        "old": float("nan") if old is None else old,
        "e2_over_d": float(err @ err) / path_length(traj),
    }


def _summary(runs: list[dict[str, float]]) -> dict[str, Any]:
    g = {k: np.array([r[k] for r in runs]) for k in runs[0]}
    end_rms = float(np.sqrt(np.mean(g["end"] ** 2)))
    est = float(np.median(g["estimate"]))
    old = float(np.median(g["old"]))
    return {
        "n": len(runs),
        "frames": float(np.mean(g["frames"])),
        "keyframes": round(float(np.mean(g["keyframes"])), 1),
        "distance_m": round(float(np.mean(g["distance_m"])), 2),
        "end": [round(float(e), 3) for e in g["end"]],
        "end_rms": round(end_rms, 3),
        "along_mean": round(float(np.mean(g["along"])), 3),
        "along_rms": round(float(np.sqrt(np.mean(g["along"] ** 2))), 3),
        "cross_rms": round(float(np.sqrt(np.mean(g["cross"] ** 2))), 3),
        "length_err": round(float(np.mean(g["length_err"])), 3),
        "step_sd": round(float(np.median(g["step_sd"])), 4),
        "estimate": round(est, 3),
        "estimate_over_end": round(est / end_rms, 2),
        "old": round(old, 3),
        "old_over_end": round(old / end_rms, 2),
        "c_fit": round(float(np.sqrt(np.mean(g["e2_over_d"]))), 4),
        **_step_sigma(g),
    }


def _step_sigma(g: dict[str, np.ndarray]) -> dict[str, Any]:
    """The EKF's VO noise on these runs (seeds pooled, equal frame counts): RMS speed and
    yaw-rate errors, per step (times the frame interval), and their mean z^2 (speed, yaw rate)
    under the library's noise and the noise until Dec 4."""
    dt = float(np.median(g["dt"]))
    v = float(np.sqrt(np.mean(g["speed_rms"] ** 2)))
    w = math.radians(float(np.sqrt(np.mean(g["yaw_rate_rms"] ** 2))))
    sv, sw = visual_velocity_sigma(dt)
    return {
        "speed_rms_m_s": round(v, 4),
        "yaw_rate_rms_deg_s": round(math.degrees(w), 3),
        "step_sigma_m": round(v * dt, 5),
        "step_sigma_deg": round(math.degrees(w) * dt, 4),
        "library_z2": [round((v / sv) ** 2, 2), round((w / sw) ** 2, 2)],
        "old_z2": [
            round((v * dt / OLD_STEP_SIGMA_M) ** 2, 2),
            round((w * dt / OLD_STEP_SIGMA_RAD) ** 2, 2),
        ],
    }


def fit_step_sigma(
    errors: dict[float, tuple[np.ndarray, np.ndarray]],
    exponent: float | None = None,
    ref_rate: float = 10.0,
) -> dict[str, float]:
    """Maximum-likelihood fit of the VO's step noise ``sigma_step(dt) = S (dt * ref_rate) **
    a`` (Gaussian, zero mean) to the speed and yaw-rate errors of runs at several rates
    (``errors[rate] = (speed errors m/s, yaw-rate errors rad/s)``, e.g. :func:`velocity_errors`
    pooled over seeds): the exponent ``a`` (given, or on a 0.05 grid in [0, 1.5], shared by
    both components) and ``S`` in closed form per component. ``a = 0.5`` is white velocity
    noise (a rate-independent noise density, :func:`~stemmap.odometry.visual.
    visual_velocity_sigma`), ``a = 0`` one fixed error per step at any rate (the form until
    Dec 4). ``nll`` is ``sum(log sigma^2 + e^2 / sigma^2)`` (twice the negative
    log-likelihood, constants dropped)."""
    grid = np.arange(0.0, 1.501, 0.05) if exponent is None else [exponent]
    best: tuple[float, float, float, float] | None = None
    for a in grid:
        nll, scales = 0.0, []
        for j in (0, 1):
            # a step's error over its model factor: e * dt / (dt * ref_rate) ** a ~ N(0, S^2)
            u = np.concatenate(
                [e[j] / r / (ref_rate / r) ** a for r, e in errors.items() if len(e[j])]
            )
            s2 = float(np.mean(u**2))
            scales.append(math.sqrt(s2))
            for r, e in errors.items():
                sig2 = s2 * (ref_rate / r) ** (2 * a) * r**2  # variance of a velocity error
                nll += float(np.sum(np.log(sig2) + e[j] ** 2 / sig2))
        if best is None or nll < best[0]:
            best = (nll, float(a), scales[0], scales[1])
    assert best is not None
    return {
        "exponent": round(best[1], 2),
        "step_m": round(best[2], 5),
        "step_deg": round(math.degrees(best[3]), 4),
        "nll": round(best[0], 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[5.0, 10.0, 20.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--length", type=float, default=10.0)
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--render-cache", type=Path, default=None)
    ap.add_argument("--base-rate", type=float, default=None, help="default: the highest rate")
    args = ap.parse_args(argv)
    base_rate = args.base_rate or max(args.rates)
    errors: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    for rate in args.rates:
        runs, ev, ew = [], [], []
        for seed in args.seeds:
            f = None if args.work is None else args.work / f"vo_{rate:g}hz_s{seed}.npz"
            if f is not None and f.exists():
                z = np.load(f)
                traj = Trajectory(z["t"], z["vo"], frame="odom")
                truth = Trajectory(z["t"], z["truth"], frame="odom")
                kf = int(z["keyframes"])
            else:
                traj, truth, kf = simulate_visual_drive(
                    rate, seed, args.length, render_cache=args.render_cache, base_rate=base_rate
                )
                if f is not None:
                    f.parent.mkdir(parents=True, exist_ok=True)
                    np.savez(f, t=traj.times, vo=traj.poses, truth=truth.poses, keyframes=kf)
            runs.append(measure(traj, truth, kf))
            e = velocity_errors(traj, truth)
            ev.append(e[0])
            ew.append(e[1])
            print(json.dumps({"rate_hz": rate, "seed": seed, **runs[-1]}), flush=True)
        print(json.dumps({f"{rate:g}hz": _summary(runs)}), flush=True)
        errors[rate] = (np.concatenate(ev), np.concatenate(ew))
    fits = {"free": fit_step_sigma(errors), "white": fit_step_sigma(errors, 0.5)}
    print(json.dumps({"step_sigma_fit": fits}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
