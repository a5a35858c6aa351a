"""Where FastSLAM's error comes from on Victoria Park: particle-filter diagnostics per time bin.

One FastSLAM run (``--seed``, ``--set KEY=VALUE`` overrides of its config) on the full run (or up
to ``--t-end``) with ``record_diagnostics``; prints JSON:

* ``summary``: ATE (the benchmark scorer of benchmarks/slam_victoria_park.py), trees, duplicate
  pairs < 1 m, CPU s, resamplings, median effective sample size (ESS, frames with detections),
  the share of frames at which the final particle set has ONE common ancestor and the lag (s)
  from the end of the run back to the last such frame (path degeneracy: how far back the
  particles still hold different histories);
* ``bins`` (``--bin`` seconds): ATE RMSE of the fixes in the bin (GPS only to look), median ESS,
  share of frames resampled, particle spread (median of sqrt(var x + var y) and of the heading
  std over the frames), detections per frame matched / starting a landmark / skipped (mean over
  particles), and with ``--isam2`` the heading and position of FastSLAM's path minus iSAM2's
  (GPS-free reference) and the share of the bin's detections (placed with the iSAM2 path) that
  lie within 1 m of a detection more than 60 s older (1 = driving over mapped ground, 0 = new
  ground).

Usage::

    python benchmarks/fastslam_diagnostics.py [--seed 0] [--bin 100] [--t0 0] [--t1 2000]
        [--isam2] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np


def _settings(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, _, raw = item.partition("=")
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out


def main() -> None:
    from scipy.spatial import cKDTree

    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate
    from stemmap.slam.base import duplicate_pairs, make_backend, observation_to_world
    from stemmap.slam.fastslam import FastSlam
    from stemmap.types import wrap_angle

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bin", type=float, default=100.0, help="bin width (s)")
    ap.add_argument("--t0", type=float, default=None, help="first bin start (s)")
    ap.add_argument("--t1", type=float, default=None, help="last bin end (s)")
    ap.add_argument("--t-end", type=float, default=None, help="use the run up to this time (s)")
    ap.add_argument("--isam2", action="store_true", help="compare with the iSAM2 path")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args()

    vp = load_victoria_park(None)
    if a.t_end is not None:
        vp = vp.slice(0.0, a.t_end)
    problem = vp.problem()
    off = vp.model.sensor_offset
    keep = vp.screened_gps()
    cfg = {"seed": a.seed, **_settings(a.set)}
    fs = FastSlam(record_diagnostics=True, **cfg)
    c0 = time.process_time()
    res = fs.run(problem)
    cpu = time.process_time() - c0
    r = ate(res.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=keep)
    d = fs.diagnostics
    t = problem.frames.times
    P = fs.n_particles
    # distinct ancestors of the final particle set at every frame
    anc = np.arange(P)
    n_anc = np.empty(t.size, dtype=np.int64)
    for f in range(t.size - 1, -1, -1):
        n_anc[f] = np.unique(anc).size
        anc = d["parents"][f][anc]
    one = np.flatnonzero(n_anc == 1)
    m = keep & (vp.gps_times >= t[0]) & (vp.gps_times <= t[-1])
    gt = vp.gps_times[m]
    out: dict[str, Any] = {
        "config": cfg,
        "summary": {
            "ate_rmse_m": round(float(r.rmse), 3),
            "trees": len(res.stem_map),
            "duplicates": duplicate_pairs(res.stem_map, 1.0),
            "cpu_s": round(cpu, 2),
            "resamples": int(res.stats["resamples"]),
            "ess_median": round(float(res.stats["ess_median"]), 1),
            "share_frames_one_ancestor": round(float(np.mean(n_anc == 1)), 3),
            "coalescence_lag_s": round(float(t[-1] - t[one[-1]]), 1) if one.size else None,
        },
    }
    if a.isam2:
        ref = make_backend("isam2").run(problem).trajectory
        ref_xy = ref.interpolate(t)[:, :2]
        ref_th = np.interp(t, ref.times, np.unwrap(ref.poses[:, 2]))
        dth = np.degrees(wrap_angle(res.trajectory.poses[:, 2] - ref_th))
        dxy = np.hypot(*(res.trajectory.poses[:, :2] - ref_xy).T)
        fr = problem.frames
        ref_poses = np.column_stack((ref_xy, ref_th))[fr.frame_index]
        world = observation_to_world(ref_poses, fr.ranges, fr.bearings, off)
        det_t = t[fr.frame_index]
    t0 = a.t0 if a.t0 is not None else float(np.floor(t[0] / a.bin) * a.bin)
    t1 = a.t1 if a.t1 is not None else float(t[-1])
    rows = []
    for b0 in np.arange(t0, t1, a.bin):
        fm = (t >= b0) & (t < b0 + a.bin)
        if not fm.any():
            continue
        em = (gt >= b0) & (gt < b0 + a.bin)
        pc = d["pose_cov_spread"][fm]
        row: dict[str, Any] = {
            "t0_s": float(b0),
            "ate_m": round(float(np.sqrt(np.mean(r.errors[em] ** 2))), 2) if em.any() else None,
            "ess_median": round(float(np.nanmedian(d["ess"][fm])), 1)
            if np.isfinite(d["ess"][fm]).any()
            else None,
            "share_resampled": round(float(d["resampled"][fm].mean()), 2),
            "spread_xy_m": round(float(np.median(np.sqrt(pc[:, 0, 0] + pc[:, 1, 1]))), 2),
            "spread_heading_deg": round(float(np.degrees(np.median(np.sqrt(pc[:, 2, 2])))), 2),
            "matched_new_skipped": [round(float(x), 2) for x in d["assoc_counts"][fm].mean(0)],
        }
        if a.isam2:
            row["heading_minus_isam2_deg"] = round(float(np.mean(dth[fm])), 2)
            row["position_minus_isam2_m"] = round(float(np.mean(dxy[fm])), 2)
            cur = (det_t >= b0) & (det_t < b0 + a.bin)
            old = det_t < b0 - 60.0
            if cur.any() and old.any():
                dd, _ = cKDTree(world[old]).query(world[cur])
                row["share_on_mapped_ground"] = round(float(np.mean(dd < 1.0)), 2)
        rows.append(row)
    out["bins"] = rows
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
