"""Diagnosis: where the unaligned GNSS score on Victoria Park comes from (prints JSON).

Every 10th screened fix fused (``VictoriaPark.gnss_split``), the other screened fixes scored
without alignment, as in ``benchmarks/slam_field.py --parts gnss``. Reported:

* ``grid``: iSAM2 + GNSS for each kernel ("cauchy", "huber", "none" = plain Gaussian) and
  sigma, scored on the unused fixes of the first half, the second half and the whole run, with
  the GPS-free chi2 per dof of the odometry and tree factors; ``chosen_on_first_half`` is the
  grid's best on the first half (the second half is the held-out report).
* ``ate_unused_per_100s_m``, ``segment_offsets_800_920s`` ([t0, t1, dx, dy] per segment) and
  ``segments``: the residual of the screened fixes against the chosen default path (Huber
  0.2 m) split at GPS gaps > 0.5 s: the RMS of the per-segment mean offset and the scatter
  inside the segments; the fix-weighted RMS of the per-segment offsets along their principal
  direction and across it.
* ``lever_time``: lever-arm correction (forward, left) and GPS time lag fitted to the
  within-segment residuals (each segment's mean offset removed) against the no-GNSS iSAM2
  path, per half, with a segment bootstrap standard error; the first half's values applied to
  the fused fixes (Huber 0.2 m), scored on the second half.

Usage::

    python benchmarks/gnss_diagnosis.py [--data DIR] [--no-grid]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

import numpy as np

GRID = [
    (k, s)
    for k, sig in (
        ("cauchy", (0.2, 0.5, 1.0)),
        ("huber", (0.05, 0.1, 0.2, 0.5, 1.0)),
        ("none", (0.05, 0.1, 0.15, 0.2, 0.5, 1.0)),
    )
    for s in sig
]


def _segments(t: Any, r: Any, gap: float = 0.5) -> Any:
    return np.cumsum(np.concatenate(([True], np.diff(t) > gap))) - 1


def main() -> None:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import align_se2, ate, point_track
    from stemmap.slam.graph import Isam2Slam

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", default=None)
    ap.add_argument("--no-grid", action="store_true")
    args = ap.parse_args()
    vp = load_victoria_park(args.data)
    fused, unused = vp.gnss_split(every=10)
    t, g, off = vp.gps_times, vp.gps_xy, vp.model.sensor_offset
    half = 0.5 * float(vp.frames.times[0] + vp.frames.times[-1])
    out: dict[str, Any] = {"split_s": round(half, 1)}

    def run(kern: str, sig: float) -> Any:
        fx = dataclasses.replace(fused, sigma=np.full(len(fused), sig))
        return Isam2Slam(gnss_robust=kern).run(dataclasses.replace(vp.problem(), gnss=fx))

    if not args.no_grid:
        rows = []
        for kern, sig in GRID:
            res = run(kern, sig)
            row: dict[str, Any] = {"kernel": kern, "sigma_m": sig}
            for lab, m in (("first", t < half), ("second", t >= half), ("all", t >= 0)):
                a = ate(res.trajectory, t, g, offset=off, keep=unused & m, align=False)
                row[f"ate_{lab}_m"] = round(a.rmse, 3)
            row["odometry_chi2_per_dof"] = round(float(res.stats["odometry_chi2_per_dof"]), 3)
            row["measurement_chi2_per_dof"] = round(float(res.stats["measurement_chi2_per_dof"]), 3)
            rows.append(row)
        out["grid"] = rows
        out["chosen_on_first_half"] = min(rows, key=lambda r: r["ate_first_m"])

    # per-segment structure of the residual of the default choice (Huber 0.2 m)
    res = run("huber", 0.2)
    k = np.flatnonzero(vp.screened_gps())
    k = k[(t[k] >= res.trajectory.times[0]) & (t[k] <= res.trajectory.times[-1])]
    r = g[k] - point_track(res.trajectory, t[k], off)
    seg = _segments(t[k], r)
    mean = np.array([r[seg == s].mean(axis=0) for s in range(seg.max() + 1)])
    n = np.bincount(seg)
    _, v = np.linalg.eigh(np.cov(mean.T, aweights=n))
    along, across = mean @ v[:, 1], mean @ v[:, 0]
    tu = t[unused & (t >= res.trajectory.times[0]) & (t <= res.trajectory.times[-1])]
    eu = g[np.isin(t, tu)] - point_track(res.trajectory, tu, off)
    out["ate_unused_per_100s_m"] = {
        f"{lo}": round(float(np.sqrt(np.mean(np.sum(eu[(tu >= lo) & (tu < lo + 100)] ** 2, 1)))), 2)
        for lo in range(0, int(tu[-1]) + 1, 100)
    }
    out["segment_offsets_800_920s"] = [
        [round(float(t[k][seg == s][0]), 1), round(float(t[k][seg == s][-1]), 1)]
        + [round(float(c), 2) for c in mean[s]]
        for s in np.unique(seg[(t[k] >= 800) & (t[k] < 920)])
    ]
    out["segments"] = {
        "segments": int(seg.max() + 1),
        "rms_of_segment_offsets_m": round(float(np.sqrt(np.mean(np.sum(mean[seg] ** 2, 1)))), 3),
        "rms_inside_segments_m": round(float(np.sqrt(np.mean(np.sum((r - mean[seg]) ** 2, 1)))), 3),
        "principal_direction": [round(float(x), 3) for x in v[:, 1]],
        "rms_along_m": round(float(np.sqrt(np.average(along**2, weights=n))), 3),
        "rms_across_m": round(float(np.sqrt(np.average(across**2, weights=n))), 3),
    }

    # lever arm and time lag from the within-segment residuals against the no-GNSS path
    base = Isam2Slam().run(vp.problem())
    tr = base.trajectory
    k = np.flatnonzero(vp.screened_gps())
    k = k[(t[k] >= tr.times[0] + 0.1) & (t[k] <= tr.times[-1] - 0.1)]
    al = align_se2(point_track(tr, t[k], off), g[k])

    def track(tt: Any) -> Any:
        return al.apply(point_track(tr, tt, off))

    r = g[k] - track(t[k])
    th = tr.interpolate(t[k])[:, 2] + al.theta
    vel = (track(t[k] + 0.05) - track(t[k] - 0.05)) / 0.1
    x = np.zeros((k.size, 2, 3))
    x[:, 0, 0], x[:, 0, 1] = np.cos(th), -np.sin(th)
    x[:, 1, 0], x[:, 1, 1] = np.sin(th), np.cos(th)
    x[:, :, 2] = vel
    seg = _segments(t[k], r)
    for s in range(seg.max() + 1):  # remove each segment's mean (the GPS's slow offset)
        m = seg == s
        x[m] -= x[m].mean(axis=0)
        r[m] -= r[m].mean(axis=0)
    rng = np.random.default_rng(0)
    lt = {}
    for lab, mm in (("first", t[k] < half), ("second", t[k] >= half), ("all", t[k] >= 0)):
        a, y, sg = x[mm].reshape(-1, 3), r[mm].reshape(-1), seg[mm]
        est = np.linalg.lstsq(a, y, rcond=None)[0]
        ids = np.unique(sg)
        boot = []
        for _ in range(300):
            rows = np.concatenate([np.flatnonzero(sg == b) for b in rng.choice(ids, ids.size)])
            boot.append(
                np.linalg.lstsq(x[mm][rows].reshape(-1, 3), r[mm][rows].reshape(-1), rcond=None)[0]
            )
        se = np.std(boot, axis=0)
        lt[lab] = {
            "lever_forward_m": [round(float(est[0]), 3), round(float(se[0]), 3)],
            "lever_left_m": [round(float(est[1]), 3), round(float(se[1]), 3)],
            "gps_time_lag_s": [round(float(est[2]), 3), round(float(se[2]), 3)],
        }
    out["lever_time"] = lt
    # the first half's estimates applied to the fused fixes (antenna and GPS times), scored on
    # the second half at the fixes' stamps and at the stamps corrected the same way
    from stemmap.slam.gnss import GnssFixes

    f1 = lt["first"]
    lever = (off[0] + f1["lever_forward_m"][0], off[1] + f1["lever_left_m"][0])
    lag = f1["gps_time_lag_s"][0]
    fx = GnssFixes(fused.times + lag, fused.xy, np.full(len(fused), 0.2), lever)
    res = Isam2Slam(gnss_robust="huber").run(dataclasses.replace(vp.problem(), gnss=fx))
    out["first_half_lever_time_applied_second_half_m"] = {
        lab: round(
            ate(res.trajectory, tt, g, offset=lever, keep=unused & (t >= half), align=False).rmse,
            3,
        )
        for lab, tt in (("at_stamps", t), ("at_corrected_stamps", t + lag))
    }
    out["note"] = "lever_time values are [estimate, bootstrap standard error]"
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
