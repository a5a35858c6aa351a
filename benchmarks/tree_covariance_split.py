"""Split-half consistency of the tree covariances on Victoria Park (no tree truth there).

Issue 14: the tree DB's and Forestrix's tree covariances
(:mod:`stemmap.slam.tree_covariance`: the observing poses' covariances propagated and
correlated between frames) are checked on real data without truth: a tree re-observed in
both halves of the drive (split at the middle time) gets one estimate per half, the mean of
that half's detections at the run's final poses (equal weights; detections given to the
mapped trees by :func:`~stemmap.slam.tree_covariance.associate_per_frame` within the
back-end's gate). The two estimates differ by ``d = t̂₁ - t̂₂``; a calibrated covariance makes
``z² = dᵀ C_d⁻¹ d`` chi-square with 2 dof (median 1.386, 86.5 % below 4). ``C_d`` is scored
four ways:

* ``model_difference``: the model's covariance of ``d`` itself (weights ``+W`` on the first
  half, ``-W`` on the second: the pose errors the halves share cancel);
* ``model_sum``: ``C₁ + C₂``, the two halves' model covariances as if independent (larger when
  the halves' pose errors are positively correlated);
* ``independent_frames``: per half, the pose covariance propagated into every detection but
  the frames treated as independent (the tree DB's earlier Kalman refinement, here at the
  reported pose covariances), summed;
* ``scatter_over_n``: per half, the scatter of the detections over their number (Forestrix's
  earlier covariance, :func:`stemmap.slam.uncertainty._mean_covariance`), summed.

Trees with at least ``--min-half`` detections in each half. Usage::

    python benchmarks/tree_covariance_split.py [--backends treedb forestrix] [--min-half 5]

Prints JSON. Needs the Victoria Park folder (``STEMMAP_DATASETS`` or ../shared/datasets).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np


def _z2(d: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", d, np.linalg.solve(C, d[..., None])[..., 0])


def _stats(z2: np.ndarray) -> dict[str, float]:
    return {
        "z2_median (calibrated 1.386)": round(float(np.median(z2)), 3),
        "share_in_2sigma (calibrated 0.865)": round(float(np.mean(z2 < 4.0)), 3),
    }


def split_half(backend: str, min_half: int) -> dict[str, Any]:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.slam.base import make_backend, observation_to_world
    from stemmap.slam.refine import world_observation_jacobians
    from stemmap.slam.tree_covariance import associate_per_frame, averaged_tree_covariances

    problem = load_victoria_park(None).problem()
    cfg = make_backend(backend)
    res = cfg.run(problem)
    fr = problem.frames
    sm = res.stem_map
    poses, P = res.trajectory.poses, res.pose_covs
    fi = fr.frame_index
    off = problem.sensor_offset
    z = observation_to_world(poses[fi], fr.ranges, fr.bearings, off)
    gate = cfg.gate if backend == "treedb" else cfg.new_tree_gate
    idx = associate_per_frame(sm.xy, z, fi, gate)
    t = fr.times[fi]
    t_mid = 0.5 * (fr.times[0] + fr.times[-1])
    half = (t >= t_mid).astype(np.int64)  # 0 = first, 1 = second
    n = len(sm)
    counts = np.zeros((2, n), dtype=np.int64)
    for h in (0, 1):
        counts[h] = np.bincount(idx[(idx >= 0) & (half == h)], minlength=n)
    both = np.flatnonzero((counts[0] >= min_half) & (counts[1] >= min_half))
    use = np.isin(idx, both)
    Jp, Jz = world_observation_jacobians(poses[fi], fr.ranges, fr.bearings, off)
    Rz = np.diag([cfg.sigma_range**2, cfg.sigma_bearing**2])
    M = Jz @ Rz @ np.swapaxes(Jz, 1, 2)
    means = np.zeros((2, n, 2))
    C_half = np.zeros((2, n, 2, 2))
    C_indep = np.zeros((2, n, 2, 2))
    C_scatter = np.zeros((2, n, 2, 2))
    for h in (0, 1):
        sel = use & (half == h)
        ih = np.where(sel, idx, -1)
        c = np.maximum(counts[h], 1)[:, None]
        means[h] = (
            np.column_stack([np.bincount(ih[sel], z[sel, i], minlength=n) for i in (0, 1)]) / c
        )
        C_half[h] = averaged_tree_covariances(ih, n, Jp, P[fi], M)
        R_ind = Jp @ P[fi] @ np.swapaxes(Jp, 1, 2) + M
        # equal weights, independent frames: sum of the detection covariances over n²
        s = np.zeros((n, 2, 2))
        np.add.at(s, ih[sel], R_ind[sel])
        C_indep[h] = s / (c * c)[..., None]
        dev = z - means[h][np.clip(ih, 0, None)]
        sc = np.zeros((n, 2, 2))
        np.add.at(sc, ih[sel], np.einsum("ki,kj->kij", dev[sel], dev[sel]))
        C_scatter[h] = sc / (np.maximum(counts[h] - 1, 1) * c[:, 0])[:, None, None]
    # the difference's own covariance: +W on the first half, -W on the second
    cnt = counts[half, np.clip(idx, 0, None)]
    sign = np.where(half == 0, 1.0, -1.0)
    W = np.einsum("k,ij->kij", sign / np.maximum(cnt, 1), np.eye(2))
    C_diff = averaged_tree_covariances(np.where(use, idx, -1), n, Jp, P[fi], M, weights=W)
    d = means[0, both] - means[1, both]
    out: dict[str, Any] = {
        "trees_mapped": n,
        "trees_in_both_halves": int(both.size),
        "t_split_s": round(float(t_mid), 1),
        "median_split_difference_m": round(float(np.median(np.hypot(*d.T))), 3),
        "model_difference": _stats(_z2(d, C_diff[both])),
        "model_sum": _stats(_z2(d, C_half[0, both] + C_half[1, both])),
        "independent_frames": _stats(_z2(d, C_indep[0, both] + C_indep[1, both])),
        "scatter_over_n": _stats(_z2(d, C_scatter[0, both] + C_scatter[1, both])),
    }
    # the reported covariance itself (whole run): its median std, for scale
    rep = np.array([tr.cov for tr in sm])[both]
    out["reported_median_std_m"] = round(
        float(np.median(np.sqrt(0.5 * np.trace(rep, axis1=1, axis2=2)))), 3
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--backends", nargs="+", default=["treedb", "forestrix"])
    ap.add_argument("--min-half", type=int, default=5)
    a = ap.parse_args()
    out: dict[str, Any] = {"dataset": "Victoria Park (full run)", "min_per_half": a.min_half}
    for b in a.backends:
        out[b] = split_half(b, a.min_half)
        print(json.dumps({b: out[b]}), file=sys.stderr, flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
