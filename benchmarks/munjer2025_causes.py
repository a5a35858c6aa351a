"""Why EB-LiDAR misses trees on the Munjer-like simulated drives: a cause table.

For every lidar frame, EB-LiDAR's own stages run once (:func:`stemmap.cloud.munjer.
munjer_clusters`, the code path :func:`~stemmap.cloud.munjer.detect_stems_munjer` uses, the
published Table 1 values, per frame); every voxel point takes the simulator's hit label of its
nearest pass-through point, every DBSCAN cluster the label most of its points carry. A tree
*counts* in a frame when at least 20 of its returns (DBSCAN's minPts) lie inside the
pass-through box (:meth:`MunjerDrive.trees_visible`, per frame). For each counted (tree, frame)
pair the table records the furthest stage any of the tree's clusters reached:

``no_cluster`` (DBSCAN gave the tree no cluster of its own: fewer than minPts voxel points
within eps, e.g. rings more than eps apart beyond eps / tan(2 deg) = 7.16 m, or merged into a
ground / bush cluster) < ``min_points`` < ``eccentricity_low`` / ``eccentricity_high`` (outside
[10, 20]) < ``tilt`` (principal axis > 45 deg from vertical) < ``circle_fit`` (residual std
> 0.1 m) < ``mislocated`` (accepted, centre > 1.0 m from the tree) < ``accepted``.

Per tree over the drive: its best stage, the frames it is detected in, and whether a perfect
mapper (true poses, perfect association) would put it in the map: detected in at least
``MunjerMapConfig.min_observations`` (3) frames. ``upper_bound`` gives that map's recall and
F1 at precision 1 -- the ceiling of per-frame EB-LiDAR on these drives whatever FastSLAM and
the Kalman refinement do. ``map`` is the real pipeline's map (FastSLAM 100 particles + Kalman
refinement on the simulator's noisy odometry, as ``benchmarks/munjer2025.py``'s ``eb_lidar``
row) with, per tree, whether it was found; ``false_clusters`` counts accepted clusters on no
tree by what they lie on; ``resolvable_pairs_by_diameter`` splits the pairs within 7.16 m by
trunk diameter (the eccentricity window acts as a diameter filter).

Usage: python benchmarks/munjer2025_causes.py [--seeds 0 1 2] [--layout park] [--speed 4]
       [--lidar vlp16|vlp16_hires] [--range-noise 0.03]
``--lidar vlp16_hires`` (Puck Hi-Res, rings 1.33 deg apart) moves the ring-gap range bound to
eps / tan(1.33 deg) = 10.74 m (``resolvable_range`` of benchmarks/munjer2025.py).
Prints one JSON object. The drives are those of benchmarks/munjer2025.py (same seeds; the RGB-D
frames are not rendered, which changes nothing of the lidar frames or the stand).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from collections import Counter
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from munjer2025 import resolvable_range  # same folder
from stemmap.cloud.filters import pass_through
from stemmap.cloud.munjer import CLUSTER_STAGES, MunjerConfig, munjer_clusters
from stemmap.sim.lidar import LABEL_BRANCH, LABEL_GROUND, LABEL_SHRUB, lidar_preset
from stemmap.sim.munjer import MunjerDrive, simulate_munjer_drive
from stemmap.slam.munjer import MunjerMapConfig, eb_lidar_observations, map_munjer, munjer_problem

GATE = 1.0
MIN_RETURNS = 20
STAGES = ("no_cluster", *CLUSTER_STAGES[:-1], "mislocated", "accepted")


def _range_bins(resolvable: float) -> tuple[float, ...]:
    """Centre-range bins (m), one edge at the sensor's ring-gap bound ``resolvable``."""
    return tuple(sorted({0.0, 4.0, 6.0, resolvable, 10.0, 15.0}))


DIAMETER_BINS = (0.0, 0.25, 0.30, 0.35, 0.50)
KINDS = {LABEL_GROUND: "ground", LABEL_BRANCH: "branch", LABEL_SHRUB: "bush"}


def _tree_frame_stages(
    drive: MunjerDrive, cfg: MunjerConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, Counter[str]]:
    """(F, T) stage index per (frame, tree) (-1: the tree does not count in that frame), (F, T)
    range of the tree centre (m), (F, T) bool counted, and the false accepted clusters by kind."""
    st = drive.stand2d
    n_t = st.n_trees
    n_f = len(drive.frames)
    stage = np.full((n_f, n_t), -1, dtype=np.int64)
    counted = np.zeros((n_f, n_t), dtype=bool)
    false_kinds: Counter[str] = Counter()
    d = st.trees_xy[None, :, :] - drive.poses[:, None, :2]
    c, s = np.cos(drive.poses[:, 2])[:, None], np.sin(drive.poses[:, 2])[:, None]
    local = np.stack((c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]), axis=-1)
    rng = np.hypot(local[..., 0], local[..., 1])
    for f, fr in enumerate(drive.frames):
        box = pass_through(fr.xyz, x=cfg.box_x, y=cfg.box_y, z=cfg.box_z)
        lab_box = fr.fields["label"][box].astype(np.int64)
        n_ret = np.bincount(lab_box[(lab_box >= 0) & (lab_box < n_t)], minlength=n_t)
        counted[f] = n_ret >= MIN_RETURNS
        cl = munjer_clusters(fr.xyz, cfg)
        if len(cl):
            _, nn = cKDTree(fr.xyz[box]).query(cl.points)
            vlab = lab_box[nn]
            ok = cl.labels >= 0
            keys, cnt = np.unique(cl.labels[ok] * 1000 + (vlab[ok] + 100), return_counts=True)
            major = np.full(len(cl), -99, dtype=np.int64)
            best = np.zeros(len(cl), dtype=np.int64)
            for key, n in zip(keys, cnt, strict=True):
                k, lab = int(key // 1000), int(key % 1000) - 100
                if n > best[k]:
                    best[k], major[k] = n, lab
            cstage = cl.stage()
            for k in range(len(cl)):
                lab = int(major[k])
                if 0 <= lab < n_t:
                    sidx = STAGES.index(str(cstage[k]))
                    if cstage[k] == "accepted" and math.dist(cl.center[k], local[f, lab]) > GATE:
                        sidx = STAGES.index("mislocated")
                    stage[f, lab] = max(stage[f, lab], sidx)
                elif cstage[k] == "accepted":
                    false_kinds[KINDS.get(lab, "other")] += 1
        stage[f][counted[f] & (stage[f] < 0)] = STAGES.index("no_cluster")
        stage[f][~counted[f]] = -1
    return stage, rng, counted, false_kinds


def _map_found(drive: MunjerDrive, seed: int, cfg: MunjerConfig) -> tuple[np.ndarray, dict]:
    """(T,) bool: trees the FastSLAM + Kalman map finds (one-to-one within 1.0 m), and its
    Table 2 counts."""
    obs = eb_lidar_observations(drive.frames, drive.times, cfg)
    p0 = (float(drive.poses[0, 0]), float(drive.poses[0, 1]), float(drive.poses[0, 2]))
    problem = munjer_problem(
        obs, drive.times, drive.controls(), drive.motion_model(), initial_pose=p0, max_range=12.0
    )
    sm = map_munjer(problem, MunjerMapConfig(seed=seed)).stem_map
    m, _ = drive.score(sm, GATE)
    found = np.zeros(drive.stand2d.n_trees, dtype=bool)
    if m.matching is not None:
        found[m.matching.pairs[:, 1]] = True
    return found, {"ta": m.ta, "fa": m.fa, "fr": m.fr, "tr": m.tr}


def _rates(ta: int, fa: int, fr: int) -> dict[str, float | None]:
    p = ta / (ta + fa) if ta + fa else math.nan
    r = ta / (ta + fr) if ta + fr else math.nan
    f1 = 2 * p * r / (p + r) if p + r > 0 else math.nan
    return {k: (round(v, 4) if math.isfinite(v) else None)
            for k, v in (("precision", p), ("recall", r), ("f1", f1))}  # fmt: skip


def run_seed(seed: int, a: argparse.Namespace) -> dict[str, Any]:
    noise = {} if a.range_noise is None else {"range_noise": a.range_noise}
    lidar = lidar_preset(a.lidar, **noise)
    drive = simulate_munjer_drive(
        layout=a.layout, speed=a.speed, lidar=lidar, camera_every=0, rng=seed
    )
    cfg = MunjerConfig()
    stage, rng, counted, false_kinds = _tree_frame_stages(drive, cfg)
    min_obs = MunjerMapConfig().min_observations
    acc = STAGES.index("accepted")
    n_det = (stage == acc).sum(axis=0)
    found, table2 = _map_found(drive, seed, cfg)
    st = drive.stand2d
    trees = []
    for t in range(st.n_trees):
        r_in = rng[counted[:, t], t]
        best = int(stage[:, t].max())
        trees.append({
            "tree": t,
            "diameter_m": round(float(st.diameters[t]), 3),
            "closest_counted_range_m": round(float(r_in.min()), 2) if r_in.size else None,
            "counted_frames": int(counted[:, t].sum()),
            "detected_frames": int(n_det[t]),
            "best_stage": STAGES[best] if best >= 0 else "never_counted",
            "in_perfect_map": bool(n_det[t] >= min_obs),
            "in_map": bool(found[t]),
        })  # fmt: skip
    return {
        "seed": seed,
        "trees": trees,
        "pairs": stage[counted].tolist(),
        "pair_range": rng[counted].tolist(),
        "pair_diameter": np.broadcast_to(st.diameters, counted.shape)[counted].tolist(),
        "false_clusters": dict(false_kinds),
        "map": table2,
    }


def summarise(runs: list[dict[str, Any]], min_obs: int, resolvable: float) -> dict[str, Any]:
    trees = [t for r in runs for t in r["trees"]]
    n = len(trees)
    stages = np.array([s for r in runs for s in r["pairs"]], dtype=np.int64)
    ranges = np.array([x for r in runs for x in r["pair_range"]])
    by_range = {}
    for lo, hi in itertools.pairwise(_range_bins(resolvable)):
        m = (ranges >= lo) & (ranges < hi)
        by_range[f"{lo:.2f}-{hi:.2f} m"] = {
            "pairs": int(m.sum()),
            **{s: int((stages[m] == i).sum()) for i, s in enumerate(STAGES)},
        }
    diam = np.array([x for r in runs for x in r["pair_diameter"]])
    near = ranges < resolvable
    by_diam = {}
    for lo, hi in itertools.pairwise(DIAMETER_BINS):
        m = near & (diam >= lo) & (diam < hi)
        by_diam[f"{lo:.2f}-{hi:.2f} m"] = {
            "pairs": int(m.sum()),
            **{s: int((stages[m] == i).sum()) for i, s in enumerate(STAGES)},
        }
    pairs = {s: int((stages == i).sum()) for i, s in enumerate(STAGES)}
    ub = sum(t["in_perfect_map"] for t in trees)
    best = Counter(t["best_stage"] for t in trees)
    det_lt = Counter(
        t["best_stage"] if t["detected_frames"] == 0 else f"detected_in_{t['detected_frames']}"
        for t in trees
        if not t["in_perfect_map"]
    )
    mp = {k: sum(r["map"][k] for r in runs) for k in ("ta", "fa", "fr", "tr")}
    false = Counter()
    for r in runs:
        false.update(r["false_clusters"])
    return {
        "n_trees": n,
        "tree_frame_pairs": {"n": int(stages.size), **pairs},
        "tree_frame_pairs_by_range": by_range,
        "resolvable_pairs_by_diameter": by_diam,
        "trees_by_best_stage": dict(best),
        "trees_not_in_perfect_map": dict(det_lt),
        "upper_bound": {
            "rule": f"tree detected (accepted, within {GATE} m) in >= {min_obs} frames",
            "ta": ub,
            "fr": n - ub,
            **_rates(ub, 0, n - ub),
        },
        "map": {**mp, **_rates(mp["ta"], mp["fa"], mp["fr"])},
        "map_misses_in_perfect_map": sum(t["in_perfect_map"] and not t["in_map"] for t in trees),
        "map_finds_outside_perfect_map": sum(
            t["in_map"] and not t["in_perfect_map"] for t in trees
        ),
        "false_clusters": dict(false),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--layout", choices=["park", "orchard"], default="park")
    ap.add_argument("--speed", type=float, default=4.0)
    ap.add_argument("--lidar", choices=["vlp16", "vlp16_hires"], default="vlp16")
    ap.add_argument("--range-noise", type=float, default=None)
    a = ap.parse_args(argv)
    t0 = time.process_time()
    runs = [run_seed(s, a) for s in a.seeds]
    res_range = resolvable_range(lidar_preset(a.lidar))
    out = {
        **summarise(
            runs, MunjerMapConfig().min_observations, resolvable_range(lidar_preset(a.lidar))
        ),
        "stages": list(STAGES),
        "per_seed": [{k: v for k, v in r.items() if not k.startswith("pair")} for r in runs],
        "scenario": {
            "seeds": a.seeds,
            "layout": a.layout,
            "speed": a.speed,
            "lidar": a.lidar,
            "lidar_range_noise": a.range_noise if a.range_noise is not None else 0.03,
            "resolvable_range_m": res_range,
            "config": MunjerConfig().__dict__,
            "min_returns": MIN_RETURNS,
            "gate_m": GATE,
        },
        "cpu_seconds": round(time.process_time() - t0, 1),
    }
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
