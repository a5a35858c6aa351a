"""Benchmark: the wheel odometry's drift estimate (``drift_estimate_percent`` of ``stemmap map``
with ``--motion wheel``, :func:`stemmap.cli._map_motion.wheel_drift_estimate`) against the
measured end drift of dead-reckoning the wheel odometry, on simulated logs.

Runs: ``stemmap sim scans`` 2D logs (default stand, ``--path`` loop by default, 1 m/s, ``wheel``
odometry preset at 50 Hz, scans at 10 Hz; the scans are not used), ``--length`` metres each, one
per seed. Per run:

* measured: the noisy ``NAME_odometry.csv`` and the true controls (``NAME_truth.npz``
  ``true_speed``, ``true_yaw_rate``, same times) dead-reckoned by the same integrator from the
  same start; the end-point distance in % of the true length, split along and across the true
  final heading;
* ``old``: the estimate before Dec 4 (``sigma_speed² T`` only);
* ``random``: the random-walk part alone with the mapper's default motion noise
  (``UnicycleModel()``: 0.05 m/s, 0.01 rad/s, what ``stemmap map`` uses without
  ``--motion-sigma``): the estimate of Dec 4 - before the systematic terms;
* ``model``: the reported estimate: ``random`` plus the default systematic terms
  (:data:`~stemmap.cli._map_motion.WHEEL_SIGMA_SCALE`,
  :data:`~stemmap.cli._map_motion.WHEEL_SIGMA_YAW_BIAS`, measured on Victoria Park, not on the
  simulator);
* ``sim``: the random-walk propagation with the generator's white-equivalent sigmas over the
  run (:func:`stemmap.sim.odometry_model.white_equivalent_sigmas`, horizon = the run's
  duration: the preset's white noise, scale and bias matched in mean square at the end), no
  systematic terms, for comparison -- the mapper does not know these.

It prints per run and the summary: ``end_rms`` (RMS over seeds), the median estimates and
their ratios to ``end_rms``.

Usage::

    python benchmarks/wheel_drift_calibration.py [--seeds 0 1 2 3 4 5] [--length 30 60]
        [--path loop|lawnmower|straight]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._map_inputs import read_odometry_csv
from stemmap.cli._map_motion import _random_walk_percent, wheel_drift_estimate
from stemmap.sim.motion_sensors import ODOMETRY_PRESETS
from stemmap.sim.odometry_model import white_equivalent_sigmas
from stemmap.slam.base import Controls
from stemmap.slam.motion import UnicycleModel

ODOM_RATE_HZ = 50.0  # simulate_run's default odometry rate (stemmap sim scans)


def dead_reckon(times: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray) -> np.ndarray:
    """(x, y, theta) at each time from (0, 0, 0), each sample held to the next (mid heading)."""
    dt = np.diff(times)
    v, w = speed[:-1], yaw_rate[:-1]
    theta = np.concatenate(([0.0], np.cumsum(w * dt)))
    mid = theta[:-1] + 0.5 * w * dt
    xy = np.vstack(([0.0, 0.0], np.cumsum((v * dt)[:, None] * np.c_[np.cos(mid), np.sin(mid)], 0)))
    return np.c_[xy, theta]


def simulate_log(work: Path, seed: int, length_m: float, path: str = "loop") -> Path:
    """A ``stemmap sim scans`` log of ``length_m`` m at 1 m/s (10 Hz scans) along ``path``."""
    out = work / f"{path}_s{seed}_{length_m:g}m.npz"
    args = ["sim", "scans", "--out", str(out), "--seed", str(seed), "--speed", "1", "--path",
            path, "--rate-hz", "10", "--n-scans", str(round(10 * length_m)), "-q"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    if res.exit_code != 0:
        raise RuntimeError(f"stemmap {' '.join(args)} failed: {res.output}")
    return out


def measure(log: Path) -> dict[str, float]:
    """Measured end drift and the estimates of one log (module doc)."""
    t, v, w = read_odometry_csv(log.with_name(f"{log.stem}_odometry.csv"))
    truth = np.load(log.with_name(f"{log.stem}_truth.npz"))
    assert np.allclose(truth["odom_time"], t)
    est = dead_reckon(t, v, w)
    ref = dead_reckon(t, truth["true_speed"], truth["true_yaw_rate"])
    true_m = float(np.sum(np.abs(truth["true_speed"][:-1]) * np.diff(t)))
    err = est[-1, :2] - ref[-1, :2]
    c, s = math.cos(ref[-1, 2]), math.sin(ref[-1, 2])
    controls = Controls(t, v, w, "unicycle")
    duration = float(t[-1] - t[0])
    sv, sw = white_equivalent_sigmas(
        ODOMETRY_PRESETS["wheel"], rate_hz=ODOM_RATE_HZ, speed=1.0, horizon=duration
    )
    model = UnicycleModel()
    dist = float(np.sum(np.abs(v[:-1]) * np.diff(t)))
    reported = wheel_drift_estimate(controls, model)
    return {
        "length_m": true_m,
        "end": 100.0 * float(np.hypot(*err)) / true_m,
        "along": 100.0 * float(c * err[0] + s * err[1]) / true_m,
        "across": 100.0 * float(-s * err[0] + c * err[1]) / true_m,
        "old": float(_random_walk_percent(model.sigma_speed**2 * np.diff(t), dist) or math.nan),
        "random": float(reported["drift_random_percent"]),
        "model": float(reported["drift_estimate_percent"]),
        "sim": float(
            wheel_drift_estimate(
                controls,
                UnicycleModel(sigma_speed=sv, sigma_steer=sw),
                sigma_scale=0.0,
                sigma_bias=0.0,
            )["drift_estimate_percent"]
        ),
        "sim_sigma_speed": sv,
        "sim_sigma_yaw_rate": sw,
    }


def summary(runs: list[dict[str, float]]) -> dict[str, float]:
    end = float(np.sqrt(np.mean([r["end"] ** 2 for r in runs])))
    out = {
        "seeds": len(runs),
        "end_rms": end,
        "along_rms": float(np.sqrt(np.mean([r["along"] ** 2 for r in runs]))),
        "across_rms": float(np.sqrt(np.mean([r["across"] ** 2 for r in runs]))),
    }
    for key in ("old", "random", "model", "sim"):
        med = float(np.median([r[key] for r in runs]))
        out[key] = med
        out[f"{key}/end"] = med / end
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--length", type=float, nargs="+", default=[30.0, 60.0])
    ap.add_argument("--path", default="loop", help="stemmap sim scans --path")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for length in args.length:
            runs = []
            for seed in args.seeds:
                r = measure(simulate_log(Path(tmp), seed, length, args.path))
                runs.append(r)
                row = {
                    "path": args.path,
                    "length": length,
                    "seed": seed,
                    **{k: round(x, 4) for k, x in r.items()},
                }
                print(json.dumps(row), flush=True)
            s = summary(runs)
            print(
                json.dumps(
                    {
                        "path": args.path,
                        "length": length,
                        "summary": {k: round(x, 3) for k, x in s.items()},
                    }
                )
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
