"""Problems of ``stemmap map`` that do not come from a log file: Victoria Park, the simulator,
and the options that change a problem (``--gnss``, ``--motion-sigma``) or how it is run
(``--realtime``), or what it reports (``--wheel-systematic``)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import ConfigError

__all__ = [
    "calibrates_odometry",
    "check_gnss",
    "motion_sigma",
    "realtime",
    "sim_motion_sigmas",
    "sim_problem",
    "simulated",
    "victoria_park",
    "vp_inputs",
    "wheel_systematic",
    "with_gnss",
]


def vp_inputs(data: Path | None) -> list[Path]:
    """The Victoria Park files a run reads (recorded and protected by the run manifest)."""
    from stemmap.datasets import find_datasets_dir

    if data is None:
        root = find_datasets_dir()
        if root is None:
            return []
        data = root / "victoria_park"
    return [data / n for n in ("inputs.dat", "measurements.dat", "gps.dat")]


def victoria_park(
    data: Path | None, t_end: float | None, t_start: float = 0.0
) -> tuple[Any, dict[str, Any]]:
    from stemmap.datasets.victoria_park import load_victoria_park

    vp = load_victoria_park(data)
    if t_end is not None or t_start > 0:
        vp = vp.slice(t_start, math.inf if t_end is None else t_end)
    return vp.problem(), {"kind": "victoria-park", "vp": vp}


def calibrates_odometry(backend: str) -> bool:
    """Whether ``backend`` (as run by ``map`` / ``demo``, not ``--realtime``) estimates the
    odometry's speed scale and yaw-rate offset itself: iSAM2 with its default self-calibration
    (docs/algorithms/slam.md "Odometry self-calibration")."""
    if backend != "isam2":
        return False
    from stemmap.slam._graph_config import Isam2Config

    return bool(Isam2Config().calibrate)


def simulated(
    seed: int, n_trees: int, size: float, *, backend: str | None = None
) -> tuple[Any, dict[str, Any]]:
    from stemmap.sim.forest import random_stand
    from stemmap.sim.trajectory import loop_path, simulate_run

    stand = random_stand(n_trees, (size, size), rng=seed)
    path = loop_path((size / 2, size / 2), (0.35 * size, 0.35 * size), laps=1.0)
    run = simulate_run(stand, path, speed=1.0, rate_hz=5.0, corridor_half_width=2.0, rng=seed)
    return sim_problem(
        run,
        name=f"sim(seed={seed}, trees={n_trees}, size={size} m)",
        backend=backend,
    )


def sim_problem(
    run: Any, obs: Any = None, *, name: str = "simulated run", backend: str | None = None
) -> tuple[Any, dict[str, Any]]:
    """A :class:`~stemmap.slam.base.SlamProblem` from a simulated run (and its context).

    ``obs`` are the run's per-scan trunk detections (default: the default detector on
    ``run.scans``). The motion noise is derived from the simulator's own odometry error
    generator (:func:`sim_motion_sigmas`), so nothing is tuned on the ground truth.
    ``backend`` is the back-end that will run the problem (``"online"`` for the
    ``--realtime`` mapper): one that estimates the speed scale and yaw-rate offset itself
    (:func:`calibrates_odometry`) is handed only the rest of the odometry noise.
    """
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.slam.base import Controls, SlamProblem, TreeFrames
    from stemmap.slam.motion import UnicycleModel

    if obs is None:
        obs = ScanTrunkDetector().detect_batch(run.scans)
    frames = TreeFrames.from_observations(obs, run.scans.times)
    odo = run.odometry
    controls = Controls(odo.times, odo.speed, odo.yaw_rate, "unicycle")
    off = run.sensor_offset
    v0 = run.vehicle_poses.poses[0]
    calibrated = backend is not None and calibrates_odometry(backend)
    sig_v, sig_w = sim_motion_sigmas(run, frames.ranges, odometry_calibrated=calibrated)
    problem = SlamProblem(
        controls,
        frames,
        UnicycleModel(sigma_speed=sig_v, sigma_steer=sig_w),
        sensor_offset=(off.x, off.y),
        initial_pose=(float(v0[0]), float(v0[1]), float(v0[2])),
        name=name,
        max_range=run.scanner.range_max if hasattr(run.scanner, "range_max") else math.inf,
    )
    return problem, {"kind": "sim", "run": run, "params": run.params, "scans": run.scans}


def sim_motion_sigmas(
    run: Any, ranges: Any, *, odometry_calibrated: bool = False
) -> tuple[float, float]:
    """Motion sigmas (m/s, rad/s; one-second white equivalents) of a simulated run's odometry.

    Derived from the run's own odometry error generator (``run.params["odometry_noise"]``,
    :func:`stemmap.sim.odometry_model.white_equivalent_sigmas`) at the horizon over which a
    pose rests on odometry alone: the vehicle driving past the 90th percentile of the
    detections' ``ranges`` at its median odometry speed
    (:func:`~stemmap.sim.odometry_model.dead_reckoning_horizon`). Nothing is read from the
    ground truth. Floors of 1 mm/s and 0.1 mrad/s keep a noise-free run well posed.

    ``odometry_calibrated``: the back-end estimates the constant speed scale and yaw-rate bias
    itself (iSAM2's self-calibration), so its odometry noise is the rest of the generator (the
    white noise and the slips). Handing it the scale and bias as white noise too counted them
    twice: demo seed 0 lost its loop closure (path RMSE 0.10 -> 1.87 m) because the
    front-end's association gates grew with the inflated heading noise
    (docs/algorithms/slam.md "Motion noise of simulated runs").
    """

    from stemmap.sim.motion_sensors import OdometryNoise
    from stemmap.sim.odometry_model import dead_reckoning_horizon, white_equivalent_sigmas

    noise = OdometryNoise(**(run.params.get("odometry_noise") or {}))
    if odometry_calibrated:
        noise = dataclasses.replace(noise, speed_scale=1.0, yaw_rate_bias=0.0)
    rate = float(run.params.get("odom_rate_hz", 50.0))
    speed = float(np.median(np.abs(run.odometry.speed)))
    if np.size(ranges) and speed > 0:
        horizon = dead_reckoning_horizon(np.asarray(ranges), speed)
    else:  # nothing detected or standing still: the one-second average
        horizon = 1.0
    sv, sw = white_equivalent_sigmas(noise, rate_hz=rate, speed=speed, horizon=max(horizon, 1.0))
    return max(sv, 1e-3), max(sw, 1e-4)


def _gnss_lever(lever: str | None, sigma: float, backend: str) -> tuple[float, float] | None:
    """The ``--gnss`` options checked: the ``--gnss-lever`` arm, or None when not given."""
    if backend != "isam2":
        raise ConfigError(f"--gnss is fused by the isam2 back-end only; got --backend {backend}.")
    if not (math.isfinite(sigma) and sigma > 0):
        raise ConfigError(f"--gnss-sigma must be a positive number of metres, got {sigma}.")
    if lever is None:
        return None
    try:
        lx, ly = (float(v) for v in lever.split(","))
    except ValueError as exc:
        raise ConfigError(f"--gnss-lever must be 'x,y' in metres, got {lever!r}.") from exc
    return (lx, ly)


def check_gnss(path: Path, lever: str | None, sigma: float, backend: str) -> None:
    """The ``--gnss`` options and file checked before any work (the file is read again by
    :func:`with_gnss` once the lever arm is known; a fixes CSV is small)."""
    from stemmap.slam.gnss import read_gnss_csv

    _gnss_lever(lever, sigma, backend)
    read_gnss_csv(path, lever_arm=(0.0, 0.0), default_sigma=sigma)


def with_gnss(problem: Any, path: Path, lever: str | None, sigma: float, backend: str) -> Any:
    """``problem`` with the fixes of ``path`` (``--gnss``); lever arm from ``--gnss-lever``."""
    from stemmap.slam.gnss import read_gnss_csv

    arm = _gnss_lever(lever, sigma, backend)
    if arm is None:  # Victoria Park: the antenna is at the laser (docs/algorithms/slam.md)
        arm = problem.sensor_offset if problem.name.startswith("victoria_park") else (0.0, 0.0)
    fixes = read_gnss_csv(path, lever_arm=arm, default_sigma=sigma)
    return dataclasses.replace(problem, gnss=fixes)


def realtime(problem: Any, backend: str, tick: Any, rrd: Path | None) -> Any:
    """``--realtime``: the log through :func:`stemmap.slam.online.replay` (latency in stats),
    logged to a Rerun recording with ``--rerun``."""
    from stemmap.slam.base import SlamResult
    from stemmap.slam.online import replay

    if backend != "isam2" or problem.gnss is not None or problem.prior_map is not None:
        raise ConfigError("--realtime runs the isam2 online mapper without --gnss/--prior-map.")
    rec = None
    if rrd is not None:
        from stemmap.viz.live import RerunRecorder

        rec = RerunRecorder(rrd)

    def on_scan(m: Any, f: int) -> None:
        if rec is not None:
            rec(m, f)
        tick(f + 1, len(problem.frames))

    try:
        st = replay(problem, on_scan=on_scan)
    finally:
        if rec is not None:
            rec.close()
    lat = np.asarray(st["latency_s"]) * 1e3
    stats = {"backend": "isam2-online", **st["stats"], "rss_mb": st["rss_mb_by_pass"][-1]}
    for q in (50, 90, 99):
        stats[f"latency_ms_p{q}"] = float(np.percentile(lat, q))
    stats["latency_ms_max"] = float(lat.max())
    return SlamResult(st["trajectory"], st["stem_map"], stats, pose_covs=st["pose_covs"])


def _pair(text: str, option: str, form: str, *, zero_ok: bool) -> tuple[float, float]:
    """``'a,b'`` -> two finite floats, > 0 (>= 0 with ``zero_ok``); ConfigError naming
    ``option`` and its ``form`` otherwise."""
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise ConfigError(f"{option} must be {form}, got {text!r}.") from exc
    lo_ok = (a >= 0 and b >= 0) if zero_ok else (a > 0 and b > 0)
    if not (lo_ok and math.isfinite(a) and math.isfinite(b)):
        bound = ">= 0" if zero_ok else "> 0"
        raise ConfigError(f"{option} values must be finite and {bound}, got {text!r}.")
    return a, b


def motion_sigma(text: str | None) -> tuple[float, float] | None:
    """``--motion-sigma 'speed,yaw_rate'`` -> (m/s, rad/s); None when not given."""
    if text is None:
        return None
    return _pair(text, "--motion-sigma", "'speed,yaw_rate' (m/s, rad/s)", zero_ok=False)


def wheel_systematic(text: str | None) -> tuple[float, float] | None:
    """``--wheel-systematic 'scale,yaw_rate_bias'`` -> (fraction, rad/s), 0 leaves a term out;
    None when not given (the measured defaults,
    :data:`stemmap.cli._map_motion.WHEEL_SIGMA_SCALE` and ``WHEEL_SIGMA_YAW_BIAS``)."""
    if text is None:
        return None
    return _pair(
        text, "--wheel-systematic", "'scale,yaw_rate_bias' (fraction, rad/s)", zero_ok=True
    )
