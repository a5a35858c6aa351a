"""Benchmark: the 2D lidar odometry's end drift on ``stemmap sim scans`` logs at the SICK
preset's two return thresholds (0.3, the measured LMS200's, and 0.5, the preset before Dec 6),
and what in the scans drives seed 12's excursion (tests/cli/test_drift_estimate.py at 75 Hz).

Per log (75 Hz, 1 m/s, 20 m, the test's settings) the lidar-only odometry
(:func:`stemmap.odometry.lidar.lidar_odometry`, ``stemmap map --motion lidar``'s defaults) is
run on the scans as simulated and on edited copies:

* ``asis``: the scans as simulated;
* ``no_mixed_surface``: the mixed beams on a trunk whose point lies on the trunk's surface
  (within 5 cm: partial edge returns) removed, by the simulator's truth labels;
* ``no_mixed_phantom``: the mixed beams labelled trunk whose point lies > 5 cm behind the
  trunk surface (trunk + background, a point between the two) removed;
* ``no_clutter``: every clutter return removed;
* ``jump10``: a geometric filter needing no labels, the farther point of every pair of
  neighbouring beams whose connecting segment lies within 10 deg of the beam (a range jump
  steeper than 80 deg incidence) removed, as a laser "shadow" / veiling-point filter.

With ``--draws D`` each log is also run ``D - 1`` more times with 1 mm Gaussian noise added to
every range (below the scanner's 1 cm): a measure of how sensitive the end drift is to the
input. Drift = end-point error / true length x 100, the map frame put on the true first pose
(as the test). Writes JSON to ``--out``.

Usage::

    python benchmarks/lidar_edge_returns.py [--seeds 10 11 12 13 14] [--q 0.3 0.5]
        [--variants asis jump10] [--draws 1] [--out /tmp/lidar_edge_returns.json]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from typer.testing import CliRunner

import stemmap.sim.scanner as scanner
from stemmap.cli import app
from stemmap.eval.trajectory import path_length
from stemmap.io.lidar_frames import open_frames
from stemmap.io.trajectory import read_trajectory_csv
from stemmap.odometry.lidar import LidarOdometryConfig, lidar_odometry
from stemmap.slam.motion import compose

VARIANTS = ("asis", "no_mixed_surface", "no_mixed_phantom", "no_clutter", "jump10")


def simulate(work: Path, seed: int, q: float, rate: int = 75, seconds: int = 20) -> Path:
    """The test's log (``stemmap sim scans --seed S --speed 1 --rate-hz R``) with the
    ``sick_lms`` preset's return threshold set to ``q``."""
    preset = scanner.SCANNER_PRESETS["sick_lms"]
    scanner.SCANNER_PRESETS["sick_lms"] = dataclasses.replace(preset, min_hit_fraction=q)
    try:
        out = work / f"s{seed}_q{q}.npz"
        args = ["sim", "scans", "--out", str(out), "--seed", str(seed), "--speed", "1",
                "--rate-hz", str(rate), "--n-scans", str(seconds * rate), "-q"]  # fmt: skip
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 0, res.output
    finally:
        scanner.SCANNER_PRESETS["sick_lms"] = preset
    return out


def removed(log: Path, variant: str) -> np.ndarray:
    """(scans, beams) mask of the returns ``variant`` removes."""
    z = np.load(log)
    r = z["ranges"]
    if variant == "asis":
        return np.zeros(r.shape, dtype=bool)
    if variant == "jump10":
        a, b = r[:, :-1], r[:, 1:]
        with np.errstate(invalid="ignore"):
            steep = np.isfinite(a) & np.isfinite(b)
            steep &= np.abs(a - b) > np.minimum(a, b) * float(z["angle_increment"]) / np.tan(
                np.radians(10.0)
            )
        drop = np.zeros(r.shape, dtype=bool)
        drop[:, :-1] |= steep & (a > b)
        drop[:, 1:] |= steep & (b > a)
        return drop
    t = np.load(log.with_name(f"{log.stem}_truth.npz"))
    hit, mixed = t["hit_ids"], t["mixed"]
    if variant == "no_clutter":
        return np.asarray(hit == -2)
    poses = read_trajectory_csv(log.with_name(f"{log.stem}_poses.csv")).poses
    with open(log.with_name(f"{log.stem}_trees.csv")) as fh:
        rows = list(csv.DictReader(fh))
    row = {int(q["id"]): k for k, q in enumerate(rows)}
    trees = np.array([[float(q["x"]), float(q["y"]), float(q["diameter"]) / 2] for q in rows])
    ang = float(z["angle_min"]) + float(z["angle_increment"]) * np.arange(r.shape[1])
    x, y, th = poses.T
    with np.errstate(invalid="ignore"):
        wx = x[:, None] + r * np.cos(th[:, None] + ang)
        wy = y[:, None] + r * np.sin(th[:, None] + ang)
    on_tree = mixed & (hit >= 0)
    k = np.array([row[i] for i in hit[on_tree]], dtype=np.int64)
    behind = np.zeros(r.shape, dtype=bool)
    gap = np.hypot(wx[on_tree] - trees[k, 0], wy[on_tree] - trees[k, 1]) - trees[k, 2]
    behind[on_tree] = gap > 0.05
    return on_tree & (behind if variant == "no_mixed_phantom" else ~behind)


def end_drift(log: Path, drop: np.ndarray, jitter: float, rng: np.random.Generator) -> float:
    truth = read_trajectory_csv(log.with_name(f"{log.stem}_poses.csv"))
    frames = []
    for i, (t, scan) in enumerate(open_frames(log, topic=None, rate_hz=None)):
        r = np.array(scan.ranges, dtype=np.float64)
        r[drop[i]] = np.inf
        if jitter > 0:
            r = r + rng.normal(0.0, jitter, r.shape)
        frames.append((t, dataclasses.replace(scan, ranges=r)))
    res = lidar_odometry(frames, LidarOdometryConfig())
    end = compose(truth.poses[0], res.planar[-1])[:2] - truth.poses[-1, :2]
    return 100.0 * float(np.hypot(*end)) / path_length(truth, min_step=0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12, 13, 14])
    ap.add_argument("--q", type=float, nargs="+", default=[0.3, 0.5])
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=["asis", "jump10"])
    ap.add_argument("--draws", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("/tmp/lidar_edge_returns.json"))
    a = ap.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for q in a.q:
            for seed in a.seeds:
                log = simulate(Path(tmp), seed, q)
                for v in a.variants:
                    drop = removed(log, v)
                    rng = np.random.default_rng(1000 + seed)
                    d = [
                        end_drift(log, drop, 0.0 if k == 0 else 0.001, rng) for k in range(a.draws)
                    ]
                    rows.append({"q": q, "seed": seed, "variant": v, "removed_frac": float(
                        drop.mean()), "drift_pct": [round(x, 3) for x in d]})  # fmt: skip
                    print(json.dumps(rows[-1]), flush=True)
    summary = {}
    for q in a.q:
        for v in a.variants:
            first = [r["drift_pct"][0] for r in rows if r["q"] == q and r["variant"] == v]
            summary[f"q{q}_{v}"] = {
                "rms_first_draw": round(float(np.sqrt(np.mean(np.square(first)))), 3),
                "max_first_draw": max(first),
            }
    print(json.dumps(summary, indent=1))
    a.out.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
