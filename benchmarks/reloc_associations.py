"""Scan-by-scan associations of session 2 to the prior trees, against the full run (issue 17).

Victoria Park: session 1 = iSAM2 on 0-800 s (the prior map), session 2 = 800-1549 s on it
(relocalised from session 1's end pose, session 1's odometry calibration carried over, as in
``slam_field.py --parts reloc``), and the single full run. The front-end kernel
(``track_keyframe``) is wrapped to record, for every associated detection, its scan and index
in the scan and the tree it went to. Every prior tree gets its full-run counterpart (the
full-run tree that session 1's detections of it went to, by majority); then each session-2
detection of a prior tree is checked: did the full run give the same detection to that
counterpart ("same trunk"), to another tree, or to none? And where does the detection lie
(full run's path) relative to the prior tree's position? Split by the prior trees that
session 2 moves >= 0.5 m (``prior_trees_moved_0p5m`` of ``slam_field.py --reloc-diagnosis``)
and the others. docs/algorithms/slam.md, "Maps reused across sessions".

Usage: ``python benchmarks/reloc_associations.py [--data DIR]`` (one JSON object).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
from typing import Any

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    args = ap.parse_args()
    from scipy.spatial import cKDTree

    import stemmap.slam.graph as graph_mod
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.slam.graph import Isam2Slam
    from stemmap.slam.motion import compose, preintegrate
    from stemmap.slam.relocalise import relocalise, with_calibration

    rec: list[tuple[int, int, int]] = []  # (scan, detection index in the scan, tree)
    kernel = graph_mod.track_keyframe

    def recording(f0: int, f1: int, kf: int, f_upd: int, ptr: Any, rng: Any, brg: Any,
                  dia: Any, sp: Any, *rest: Any) -> Any:  # fmt: skip
        out = kernel(f0, f1, kf, f_upd, ptr, rng, brg, dia, sp, *rest)
        out_j, out_kx, out_ky = rest[16], rest[17], rest[18]
        # the kernel's outputs are detections in the keyframe's dead-reckoned sensor frame:
        # recompute them for every detection of the window and match
        ck, sk = math.cos(sp[kf, 2]), math.sin(sp[kf, 2])
        f_of, i_of, xy = [], [], []
        for f in range(f0, f1):
            dx, dy, qt = sp[f, 0] - sp[kf, 0], sp[f, 1] - sp[kf, 1], sp[f, 2] - sp[kf, 2]
            qx, qy = ck * dx + sk * dy, -sk * dx + ck * dy
            r, b = rng[ptr[f] : ptr[f + 1]], brg[ptr[f] : ptr[f + 1]]
            px, py = r * np.cos(b), r * np.sin(b)
            xy.append(np.column_stack((qx + np.cos(qt) * px - np.sin(qt) * py,
                                       qy + np.sin(qt) * px + np.cos(qt) * py)))  # fmt: skip
            f_of += [f] * r.size
            i_of += list(range(r.size))
        cand = np.concatenate(xy) if xy else np.zeros((0, 2))
        for t in range(out[1]):
            d = np.hypot(cand[:, 0] - out_kx[t], cand[:, 1] - out_ky[t])
            k = int(np.argmin(d))
            if d[k] > 1e-6:
                raise RuntimeError("detection not found")
            rec.append((f_of[k], i_of[k], int(out_j[t])))
        return out

    graph_mod.track_keyframe = recording  # type: ignore[assignment]

    def run(problem: Any, **kw: Any) -> tuple[Any, dict[tuple[float, int], int]]:
        rec.clear()
        res = Isam2Slam(**kw).run(problem)
        t = problem.frames.times
        return res, {(round(float(t[f]), 4), i): j for f, i, j in rec}

    vp = load_victoria_park(args.data)
    off = vp.model.sensor_offset
    p1, p2, pf = vp.slice(0.0, 800.0).problem(), vp.slice(800.0, 1549.0).problem(), vp.problem()
    r1, a1 = run(p1, joint_information=True)
    t1l, t2f = float(r1.trajectory.times[-1]), float(p2.frames.times[0])
    d = preintegrate(vp.model, vp.controls, [t1l, t2f], with_covariance=False).deltas[0]
    rel = relocalise(p2, r1.stem_map, guess=tuple(compose(r1.trajectory.poses[-1], d)))
    cal = (float(r1.stats["calib_offset_mean"]), float(r1.stats["calib_scale_mean"]))
    p2r = dataclasses.replace(p2, initial_pose=rel.pose, prior_map=r1.stem_map)
    r2, a2 = run(with_calibration(p2r, *cal))
    full, af = run(pf)

    prior = list(r1.stem_map)
    n_p = len(prior)
    moved = cKDTree(r2.stem_map.xy).query(r1.stem_map.xy)[0] >= 0.5
    by_tree1 = collections.defaultdict(list)
    for key, j in a1.items():
        by_tree1[j].append(key)
    counterpart = {}
    for jp, tr in enumerate(prior):  # full-run tree of session 1's detections of tree jp
        c = collections.Counter(af.get(key, -1) for key in by_tree1[tr.id])
        counterpart[jp] = c.most_common(1)[0][0] if c else -2
    fr, traj = p2.frames, full.trajectory
    rows = []
    for (t, i), j in a2.items():
        if j >= n_p:
            continue
        f = int(np.searchsorted(fr.times, t - 1e-6))
        x, y, th = traj.interpolate([fr.times[f]])[0]
        sx = x + math.cos(th) * off[0] - math.sin(th) * off[1]
        sy = y + math.sin(th) * off[0] + math.cos(th) * off[1]
        r, b = fr.ranges[fr.ptr[f] + i], fr.bearings[fr.ptr[f] + i]
        e = math.hypot(
            sx + r * math.cos(th + b) - prior[j].x, sy + r * math.sin(th + b) - prior[j].y
        )
        jf = af.get((t, i), -1)
        rows.append((moved[j], e, r, jf == counterpart[j], jf == -1))
    R = np.array(rows, dtype=float)
    out: dict[str, Any] = {
        "data": "Victoria Park; session 1 = isam2 0-800 s, session 2 = 800-1549 s on its map",
        "prior_trees": n_p,
        "prior_trees_moved_0p5m": int(moved.sum()),
    }
    for name, m in (("moved", R[:, 0] == 1), ("kept", R[:, 0] == 0)):
        far = m & (R[:, 1] > 1.5)
        out[f"{name}_trees"] = {
            "session2_detections": int(m.sum()),
            "full_run_same_tree": int((m & (R[:, 3] == 1)).sum()),
            "full_run_none": int((m & (R[:, 4] == 1)).sum()),
            "full_run_other_tree": int((m & (R[:, 3] == 0) & (R[:, 4] == 0)).sum()),
            "beyond_1p5m_of_prior": int(far.sum()),
            "beyond_1p5m_full_run_same_tree": int((far & (R[:, 3] == 1)).sum()),
            "median_range_m": round(float(np.median(R[m, 2])), 1),
            "median_range_beyond_1p5m_m": round(float(np.median(R[far, 2])), 1),
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
