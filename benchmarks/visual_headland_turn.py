"""Benchmark: the stereo visual odometry through simulated headland turns (end error, heading).

A check of tracking through fast rotation (the keyframe's corners tracked from the keyframe
image, docs/algorithms/visual-odometry.md): a 3-row orchard (rows 4 m apart, trees 3 m apart)
inside a forest edge (:func:`stemmap.sim.render.with_forest_edge`), driven 2 m along the
aisle y = 2 m past the last tree, a half circle of ``--radius`` metres into the next aisle and
2 m back, at 1 m/s, rendered with the default ``StereoCamera`` at ``--rate`` Hz; one drive per
seed (seed = stand jitter, forest edge and pixel noise). Prints one JSON line per drive: end
error (m, in the frame of the first pose), end heading error (degrees), lost frames,
keyframes.

Usage::

    python benchmarks/visual_headland_turn.py [--rate 5] [--radius 1 2] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from stemmap.odometry.visual import (
    StereoCalibration,
    VisualFrame,
    VoStatus,
    planar_from_camera,
    run_visual_odometry,
)
from stemmap.sim.forest import row_stand
from stemmap.sim.render import StereoCamera, iter_stereo, stand3d_from_stand, with_forest_edge
from stemmap.types import Trajectory


def headland_turn(x_end: float, radius: float, rate_hz: float) -> Trajectory:
    """2 m along y = 2 to ``x_end``, a half circle of ``radius`` (left), 2 m back."""
    arc = math.pi * radius
    s = np.arange(0.0, 4.0 + arc, 1.0 / rate_hz)
    a = np.clip((s - 2.0) / radius, 0.0, math.pi)
    x = np.where(s < 2.0, x_end - 2.0 + s, x_end + radius * np.sin(a))
    x = np.where(s > 2.0 + arc, x_end - (s - 2.0 - arc), x)
    y = 2.0 + radius - radius * np.cos(a)
    return Trajectory(s, np.column_stack((x, y, a)), frame="world")


def run(seed: int, radius: float, rate_hz: float) -> dict[str, float]:
    rows = row_stand(3, 10, row_spacing=4.0, tree_spacing=3.0, rng=seed + 1)
    stand = with_forest_edge(rows, rng=seed + 3)
    truth = headland_turn(float(rows.trees_xy[:, 0].max()) + 2.0, radius, rate_hz)
    cam = StereoCamera(rate_hz=rate_hz)
    k = cam.K
    cal = StereoCalibration(
        cam.fx, cam.fx, k[0, 2], k[1, 2], cam.width, cam.height, baseline=cam.baseline
    )
    frames = (
        VisualFrame(f.time, f.left, f.right)
        for f in iter_stereo(stand3d_from_stand(stand, rng=seed + 2), truth, cam, rng=seed)
    )
    res = run_visual_odometry(frames, cal)
    est = planar_from_camera(res, cam.vehicle_from_camera())
    p = truth.poses
    c, s = math.cos(p[0, 2]), math.sin(p[0, 2])
    d = p[-1, :2] - p[0, :2]
    end = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    dth = math.remainder(float(est.poses[-1, 2] - (p[-1, 2] - p[0, 2])), math.tau)
    return {
        "seed": seed,
        "radius": radius,
        "rate_hz": rate_hz,
        "frames": len(res),
        "end_m": round(float(np.hypot(*(est.poses[-1, :2] - end))), 3),
        "heading_deg": round(math.degrees(dth), 2),
        "lost": int(np.sum(~res.ok)),
        "keyframes": int(np.sum(res.status == VoStatus.KEYFRAME)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=5.0)
    ap.add_argument("--radius", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args(argv)
    for radius in args.radius:
        for seed in args.seeds:
            print(json.dumps(run(seed, radius, args.rate)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
