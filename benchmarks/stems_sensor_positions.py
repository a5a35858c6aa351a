"""Benchmark: DBH of `stemmap stems` on a mobile-lidar LAS file with and without the sensor
positions (--trajectory + the points' gps_time), through the command line; and the same
detector in memory on the float64 and the 1-mm-rounded coordinates (what the LAS file holds).

The stands, sensor and path are those of the ``mobile`` scenario of benchmarks/cloud_stems.py
(30 trees in 25 x 25 m, VLP-16-like lidar with 3 cm range noise at 0.8 m, 60 revolutions along
a straight line; seeds 1-3, simulator seeds 200 + seed). Each merged cloud is written the way a
mobile-mapping system delivers it: a LAS 1.2 file (1 mm scale, point format 1) whose points
carry gps_time (revolution k at 1e6 + 0.1 k s), and the machine's path as a stemmap trajectory
CSV holding the pose of every other revolution of a reference point 1.2 m behind and 0.3 m left
of the scanner (so the command interpolates and applies --sensor-offset 1.2,-0.3).

`python -m stemmap stems` runs in a subprocess for each file, without and with the sensor
positions, alternating; detections are matched to the simulator's trees within 0.5 m and pooled
over the stands. Prints one JSON object (with --json): recall, precision, DBH RMSE / bias,
position RMSE, and the child processes' CPU time, with the load average.

    python benchmarks/stems_sensor_positions.py --json [--seeds 1 2 3]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from _mobile_files import point_times, vehicle_trajectory, write_las, write_trajectory
from stemmap.cloud.stems import detect_stems
from stemmap.eval.matching import match_points
from stemmap.sim.lidar import lidar_preset, random_stand3d, simulate_mobile

GATE = 0.5  # m, as benchmarks/cloud_stems.py
IN_MEMORY = (
    "in_memory_float64_without",
    "in_memory_float64_true_origins",
    "in_memory_1mm_without",
    "in_memory_1mm_true_origins",
)
LEVER = (1.2, -0.3)
N_PATH = 60


def _cli(args: list[str]) -> float:
    """Run `python -m stemmap` with args; return the child's CPU time (user + system)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    # the checkout's own src first: the child must run the code being benchmarked, not
    # whatever stemmap happens to be installed
    here = Path(__file__).resolve().parent
    paths = [str(here.parent / "src"), str(here), os.environ.get("PYTHONPATH", "")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in paths if p)}
    subprocess.run(
        [sys.executable, "-m", "stemmap", *args],
        check=True,
        env=env,
        text=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(-1, 2)
    return xy, np.array([float(r["diameter"]) for r in rows])


def run(seeds: list[int]) -> dict[str, Any]:
    vlp = lidar_preset("vlp16")
    load0 = os.getloadavg()[0]
    res: dict[str, Any] = {
        "scenario": {
            "stands": "random_stand3d(30, (25, 25), rng=seed) as benchmarks/cloud_stems.py",
            "seeds": seeds,
            "lidar": "vlp16 (16 beams, 0.2 deg, 3 cm range noise), 0.8 m above ground",
            "path": f"straight line y = 12.3 m, x 0.5..24.5 m, {N_PATH} revolutions",
            "files": "LAS 1.2 point format 1, 1 mm scale, gps_time per point; trajectory CSV "
            "of every other revolution, reference point offset from the scanner by "
            f"{LEVER} m (forward, left)",
            "match_gate_m": GATE,
            "cpu": "CLI rows: user + system CPU of the `python -m stemmap stems` child "
            "processes (whole command); in_memory rows: process CPU of detect_stems alone",
        }
    }
    names = ("without", "with_trajectory", *IN_MEMORY)
    acc: dict[str, dict[str, list[Any]]] = {
        k: {"d": [], "p": [], "n_det": [], "n_match": [], "n_truth": [], "cpu": [], "n_pts": []}
        for k in names
    }
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for seed in seeds:
            stand = random_stand3d(30, (25.0, 25.0), rng=seed)
            path = np.column_stack((np.linspace(0.5, 24.5, N_PATH), np.full(N_PATH, 12.3)))
            mob = simulate_mobile(stand, path, vlp, rng=200 + seed, keep_frames=False)
            las, traj = d / f"drive{seed}.las", d / f"path{seed}.csv"
            write_las(las, mob.cloud.xyz, point_times(mob))
            write_trajectory(traj, vehicle_trajectory(mob, LEVER))
            runs = {
                "without": [],
                "with_trajectory": ["--trajectory", str(traj), "--sensor-offset", "1.2,-0.3"],
            }
            detections = {}
            for name, extra in runs.items():  # alternate within each stand
                out = d / f"{name}{seed}.csv"
                cpu = _cli(["stems", str(las), "--out", str(out), *extra])
                detections[name] = (*_read(out), cpu)
            # the same detector in memory, on the simulator's float64 coordinates and on
            # them rounded to the LAS file's 1 mm, with and without the true sensor positions
            origins = mob.poses[mob.cloud.fields["frame_index"], :3]
            rounded = np.round(mob.cloud.xyz * 1000.0) / 1000.0
            for name, (xyz, o) in {
                "in_memory_float64_without": (mob.cloud.xyz, None),
                "in_memory_float64_true_origins": (mob.cloud.xyz, origins),
                "in_memory_1mm_without": (rounded, None),
                "in_memory_1mm_true_origins": (rounded, origins),
            }.items():
                c0 = time.process_time()
                det = detect_stems(xyz, origins=o)
                detections[name] = (det.xy, det.diameter, time.process_time() - c0)
            for name, (xy, dia, cpu) in detections.items():
                m = match_points(xy, stand.trees_xy, GATE)
                a = acc[name]
                a["d"].append(dia[m.pairs[:, 0]] - stand.dbh[m.pairs[:, 1]])
                a["p"].append(xy[m.pairs[:, 0]] - stand.trees_xy[m.pairs[:, 1]])
                a["n_det"].append(len(dia))
                a["n_match"].append(m.n_matched)
                a["n_truth"].append(stand.n_trees)
                a["cpu"].append(cpu)
                a["n_pts"].append(len(mob.cloud))
    for name, a in acc.items():
        dd, pp = np.concatenate(a["d"]), np.concatenate(a["p"])
        res[name] = {
            "recall": round(sum(a["n_match"]) / sum(a["n_truth"]), 3),
            "precision": round(sum(a["n_match"]) / max(sum(a["n_det"]), 1), 3),
            "n_matched": int(sum(a["n_match"])),
            "dbh_bias_cm": round(100 * float(np.mean(dd)), 2),
            "dbh_rmse_cm": round(100 * float(np.sqrt(np.mean(dd**2))), 2),
            "dbh_abs_p95_cm": round(100 * float(np.quantile(np.abs(dd), 0.95)), 2),
            "position_rmse_cm": round(100 * float(np.sqrt(np.mean(np.sum(pp**2, 1)))), 2),
            "cpu_s": [round(c, 2) for c in a["cpu"]],
            "n_points": a["n_pts"],
        }
    res["cpu_ratio_with_vs_without"] = round(
        sum(acc["with_trajectory"]["cpu"]) / sum(acc["without"]["cpu"]), 2
    )
    res["load_avg"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    a = ap.parse_args()
    res = run(a.seeds)
    print(json.dumps(res, indent=None if a.json else 2))


if __name__ == "__main__":
    main()
