"""EB-LiDAR per frame vs frames joined (``MunjerConfig.window``) on a real plot: virtual VLP-16
drives through ``treels/pine_plot.laz`` (TLS, 10 x 10 m, planted rows ~3 m apart).

The repository has no real mobile-lidar sequence, so lidar frames are cut from the TLS cloud:
a sensor 0.8 m above the local ground (2nd percentile of the points within 1.5 m) moves along a
straight line at 0.4 m per frame (4 m/s at 10 Hz, the simulated drives' speed), heading along the
line; each frame keeps, per VLP-16 beam (16 beams, -15..15 degrees, 2 degrees apart, a point
counts for a beam within +-0.3 degrees of it) and 0.2 degree azimuth bin, the nearest point (what
the sensor would see first). Three lines run between the tree rows (x = 1.9, 4.9, 7.8 m) from
y = -8 to 18 m. EB-LiDAR (:func:`stemmap.slam.munjer.eb_lidar_observations`, the paper's Table 1
values, the principal-axis tilt check ``MunjerConfig.max_tilt_deg`` at ``--max-tilt``, and beside it
without that check: rows ``window_K_no_tilt_check``) runs with ``window`` 1 (per frame) and the
windows in ``--windows``; detections go to the
world with the (exact) virtual poses and are associated at 1.0 m
(:func:`stemmap.cloud.munjer.associate_proximity`); a tree needs 3 detections (the Munjer map's
``min_observations``). Reference: stemmap's own detector on the full plot (17 stems); a confirmed
tree within 0.5 m of a reference stem is ``matched``, else ``unmatched`` (a false tree: the rows
are 3 m apart, nothing between them is a trunk).

Usage: python benchmarks/munjer2025_real_frames.py [--windows 3 5 10] [--ground-relative]
       [--max-tilt 45] [--ecc-range 10 20].
Prints one JSON object.
Caveat: virtual frames re-sample one static TLS cloud, so joined frames add fewer independent
points on a trunk than a real sensor's frames would.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from stemmap.cloud.munjer import MunjerConfig, associate_proximity
from stemmap.cloud.stems import detect_stems
from stemmap.eval.matching import match_points
from stemmap.io.clouds import read_cloud
from stemmap.slam.munjer import eb_lidar_observations
from stemmap.types import StemObservations

BEAMS_DEG = np.arange(-15.0, 16.0, 2.0)
LINES_X = (1.9, 4.9, 7.8)


def virtual_frame(xyz: np.ndarray, pose: np.ndarray, height: float = 0.8) -> np.ndarray:
    """The points a level VLP-16 at ``pose`` (x, y, heading), ``height`` above the local ground,
    sees first per beam and 0.2 degree azimuth bin, in its frame (x forward, z up)."""
    near = np.hypot(*(xyz[:, :2] - pose[:2]).T) < 1.5
    ground = np.percentile(xyz[near, 2], 2) if near.sum() > 20 else np.percentile(xyz[:, 2], 1)
    d = xyz - (pose[0], pose[1], ground + height)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    loc = np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]))
    r = np.linalg.norm(loc, axis=1)
    el = np.degrees(np.arcsin(loc[:, 2] / np.maximum(r, 1e-9)))
    k = np.rint((el - BEAMS_DEG[0]) / 2.0).astype(np.int64)
    ok = (k >= 0) & (k < BEAMS_DEG.size)
    ok &= np.abs(el - BEAMS_DEG[np.clip(k, 0, BEAMS_DEG.size - 1)]) < 0.3
    az = np.floor(np.degrees(np.arctan2(loc[:, 1], loc[:, 0])) / 0.2).astype(np.int64)
    idx = np.flatnonzero(ok)
    key = k[idx] * 10_000 + az[idx]
    order = np.lexsort((r[idx], key))
    first = np.r_[True, key[order][1:] != key[order][:-1]]
    return loc[idx[order][first]]


def _to_world(obs: StemObservations, poses: np.ndarray) -> list[Any]:
    from stemmap.cloud.result import CloudStems

    parts = []
    for f in np.unique(obs.index):
        m = obs.index == f
        x, y, th = poses[f]
        c, s = math.cos(th), math.sin(th)
        xy = obs.centers[m] @ np.array([[c, s], [-s, c]]) + (x, y)
        parts.append(
            CloudStems.from_columns(
                xy=xy, z=np.zeros(m.sum()), diameter=2 * obs.radii[m], n_points=obs.n_points[m],
                method="munjer2025", frame="world",
            )
        )  # fmt: skip
    return parts


def run_line(
    xyz: np.ndarray,
    ref_xy: np.ndarray,
    x_line: float,
    windows: list[int],
    ground_relative: bool,
    max_tilt: float | None,
    ecc_range: tuple[float, float] = (10.0, 20.0),
) -> dict:
    ys = np.arange(-8.0, 18.0, 0.4)
    poses = np.column_stack((np.full_like(ys, x_line), ys, np.full_like(ys, math.pi / 2)))
    frames = [virtual_frame(xyz, p) for p in poses]
    out: dict[str, Any] = {
        "frames": len(frames),
        "median_points": int(np.median([len(f) for f in frames])),
    }
    for w, (key, tilt) in itertools.product(
        [1, *windows], [("", max_tilt), ("_no_tilt_check", None)]
    ):
        cfg = MunjerConfig(
            window=w,
            ground_relative=ground_relative,
            max_tilt_deg=tilt,
            eccentricity_range=ecc_range,
        )
        obs = eb_lidar_observations(frames, ys / 4.0, cfg, poses=poses)
        trees = associate_proximity(_to_world(obs, poses), 1.0) if len(obs) else None
        xy = trees.xy[trees.n_slices >= 3] if trees is not None else np.zeros((0, 2))
        m = match_points(xy, ref_xy, 0.5)
        out[f"window_{w}{key}"] = {
            "frame_detections": len(obs),
            "confirmed_trees": len(xy),
            "matched": int(m.n_matched),
            "unmatched": int(len(xy) - m.n_matched),
        }
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, nargs="+", default=[3, 5, 10])
    ap.add_argument(
        "--ground-relative", action="store_true", help="MunjerConfig(ground_relative=True) box"
    )
    ap.add_argument(
        "--max-tilt",
        type=float,
        default=MunjerConfig().max_tilt_deg,
        help="MunjerConfig.max_tilt_deg of the main rows (degrees; default the library's)",
    )
    ap.add_argument(
        "--ecc-range",
        type=float,
        nargs=2,
        default=list(MunjerConfig().eccentricity_range),
        metavar=("LO", "HI"),
        help="MunjerConfig.eccentricity_range of every row (default the paper's 10 20)",
    )
    a = ap.parse_args(argv)
    ecc = (float(a.ecc_range[0]), float(a.ecc_range[1]))
    t0 = time.process_time()
    path = require_datasets_dir() / "treels" / "pine_plot.laz"
    xyz = read_cloud(path).xyz
    ref = detect_stems(xyz)
    res: dict[str, Any] = {
        "cloud": "treels/pine_plot.laz",
        "reference_stems": len(ref),
        "ground_relative": a.ground_relative,
        "max_tilt_deg": a.max_tilt,
        "eccentricity_range": list(ecc),
    }
    for x in LINES_X:
        res[f"line_x{x}"] = run_line(xyz, ref.xy, x, a.windows, a.ground_relative, a.max_tilt, ecc)
    res["total"] = {
        f"window_{w}{key}": {
            k: sum(res[f"line_x{x}"][f"window_{w}{key}"][k] for x in LINES_X)
            for k in ("confirmed_trees", "matched", "unmatched")
        }
        for w in [1, *a.windows]
        for key in ("", "_no_tilt_check")
    }
    res["cpu_seconds"] = round(time.process_time() - t0, 1)
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
