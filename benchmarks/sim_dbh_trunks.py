"""Per trunk: is the simulated DBH error at <= 5 m the sensor's bound or a detector defect?
(issue 11, Dec 5, scan-detection.md "Per seed or on the mean").

For each seed's drive (``scan_detection.py``'s 400-scan drive by default, or the ``stemmap
demo`` drive) and the ``stemmap`` preset (with ``--set`` overrides), every matched pair within
5 m (``_scan_sim.tree_errors``: the scorer's eligibility and one-to-one matching) gets the
Cramér-Rao bound of its own scan (``sim_dbh_causes.pair_crlb``: 1 cm range noise on the
trunk's returns, tangent priors narrowed where the beam beyond returned from the background,
no tangent where an edge is occluded or at the field of view's end, footprint-averaged edge
returns; scan-fits.md). No unbiased fit of those returns has a smaller standard error, so:

* per seed, ``crlb_rmse_cm`` (the RMS of the bound over the same pairs) is the RMSE an
  efficient fit of these scans would have, and ``rmse_cm`` / ``crlb_rmse_cm`` how far above it
  the detector is; ``attainable_rmse_cm`` is the RMSE with every pair more than
  ``--z`` bounds off replaced by one bound (what the seed would read if those pairs were fitted
  as well as their returns allow and every other pair kept its error);
* per tree (``trees``, the ``--top`` with the largest share of the seed's sum of squares): its
  pairs, share, RMSE, the RMS of its bounds (``crlb_cm``; a trunk whose bound is above the
  target cannot be measured to it by any unbiased fit), the RMS of error / bound (``z_rms``),
  and ``verdict``: ``bound`` when the sum of its pairs' (error / bound)^2 is within the 99 %
  point of chi^2 with that many degrees of freedom (its error is what its returns allow),
  ``bound_above_target`` when that holds and its bound is above the target, else
  ``beyond_bound``;
* per pair more than ``--z`` bounds off (``beyond``): what it is (returns, edges, range, the
  beams the detection's circle lies on that are not the trunk's, ``foreign_beams``, and the
  trunk's returns it does not cover, ``missing_beams``) and which single switch of the preset
  brings its scan's detection of that trunk within ``--z`` bounds (``ablation``: the error with
  each switch off, ``None`` when no detection within the gate). The switches are the preset's
  stages after the whole-candidate fit (``arc_replace`` / ``arc_refit``: the largest
  consistent arc replacing a fit; ``step_split``; ``refit_pieces``: corner split pieces;
  ``neighbour_silhouette``: the tangent priors of the beams beyond) and ``isolated``: the
  detector on the scan with every other object's return within 10 beams of the trunk and not
  in front of it removed (a merge with clutter or a neighbour shows as a large change; the
  background beyond its edges goes too, so ``isolated`` also carries the change of the
  neighbour-silhouette priors that ``neighbour_silhouette_off`` shows).

Usage: python benchmarks/sim_dbh_trunks.py --seeds 6 11 13 17 [--drive benchmark|demo]
       [--set '{}'] [--top 5] [--z 3]

One JSON line per seed.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import argparse
import dataclasses
import json
import math
import sys
from typing import Any

import numpy as np
from scipy.stats import chi2

from _scan_sim import SCENARIO, edge_status, tree_errors
from sim_dbh_causes import NEAR_M, _local, drive, pair_crlb
from stemmap.eval.matching import match_points
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

#: Issue 11's simulated DBH target at <= 5 m (cm).
TARGET_CM = 1.2

#: The preset's stages after the whole-candidate fit, each switched off alone (``ablation``).
SWITCHES: dict[str, dict[str, Any]] = {
    "arc_replace_off": {"arc_replace": math.inf},
    "arc_refit_off": {"arc_refit": False},
    "step_split_off": {"step_split": False},
    "refit_pieces_off": {"refit_pieces": False},
    "neighbour_silhouette_off": {"neighbour_silhouette": False},
}

#: ``isolated``: other objects' returns within this many beams of the trunk are removed.
ISOLATE_BEAMS = 10


def _rms(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return round(float(np.sqrt(np.mean(v**2))), 3) if v.size else None


def pair_bounds(run: Any, err: dict[str, np.ndarray], near: np.ndarray) -> np.ndarray:
    """The Cramér-Rao bound (cm) of each pair ``near`` of :func:`_scan_sim.tree_errors`."""
    ks, js = err["scan"][near], err["tree"][near]
    return 100.0 * np.array([pair_crlb(run, int(k), int(j)) for k, j in zip(ks, js, strict=True)])


def _error_in_scan(det: ScanTrunkDetector, run: Any, ranges: np.ndarray, k: int, j: int) -> Any:
    """Tree ``j``'s DBH error (cm) as ``det`` detects it in scan ``k`` with ``ranges`` (the
    nearest detection within the scoring gate), ``None`` if none."""
    scan = dataclasses.replace(run.scans[k], ranges=ranges)
    obs = det.detect(scan)
    if len(obs) == 0:
        return None
    c = _local(run, k, j)
    m = match_points(obs.centers, c[None, :], SCENARIO["scoring"]["gate_m"])
    if not m.n_matched:
        return None
    i = int(m.pairs[0, 0])
    return round(100.0 * (2.0 * float(obs.radii[i]) - float(run.stand.diameters[j])), 2)


def _detection_beams(run: Any, k: int, j: int, det: ScanTrunkDetector) -> dict[str, Any]:
    """The default's detection of tree ``j`` in scan ``k``: its returns (those of the scan in
    the circle's angular span, in front of its centre, within max(2 cm, 3 sigma) of it) that
    are not the trunk's (``foreign_beams``) and the trunk's returns it leaves out
    (``missing_beams``), with the detection's own return count."""
    sc = run.scans
    r = sc.ranges[k]
    obs = det.detect(sc[k])
    c = _local(run, k, j)
    m = match_points(obs.centers, c[None, :], SCENARIO["scoring"]["gate_m"])
    if not m.n_matched:
        return {}
    i = int(m.pairs[0, 0])
    cc, rad = obs.centers[i], float(obs.radii[i])
    ang = sc.angles
    dist = float(np.hypot(*cc))
    half = math.asin(min(1.0, rad / max(dist, 1e-9)))
    da = np.abs((ang - math.atan2(cc[1], cc[0]) + np.pi) % (2 * np.pi) - np.pi)
    with np.errstate(invalid="ignore"):
        res = np.abs(np.hypot(r * np.cos(ang) - cc[0], r * np.sin(ang) - cc[1]) - rad)
        on = np.isfinite(r) & (da <= half + abs(sc.angle_increment)) & (r < dist) & (res < 0.03)
    mine = run.hit_ids[k] == j
    return {
        "detection_returns": int(obs.n_points[i]),
        "foreign_beams": int(np.sum(on & ~mine)),
        "missing_beams": int(np.sum(mine & ~on)),
    }


def _isolated(run: Any, k: int, j: int) -> np.ndarray:
    """Scan ``k``'s ranges without the returns of other objects within :data:`ISOLATE_BEAMS`
    beams of tree ``j``'s that are not in front of its surface (occluders stay)."""
    r = run.scans.ranges[k].copy()
    hit = run.hit_ids[k]
    beams = np.flatnonzero(hit == j)
    dist = float(np.hypot(*_local(run, k, j)))
    front = dist - float(run.stand.radii[j])
    lo, hi = max(int(beams[0]) - ISOLATE_BEAMS, 0), min(int(beams[-1]) + ISOLATE_BEAMS + 1, r.size)
    idx = np.arange(lo, hi)
    drop = idx[(hit[idx] != j) & np.isfinite(r[idx]) & (r[idx] >= front - 0.02)]
    r[drop] = np.inf
    return r


def diagnose_pair(
    run: Any, k: int, j: int, overrides: dict[str, Any], det: ScanTrunkDetector
) -> dict[str, Any]:
    """What a pair beyond its bound is (:func:`_detection_beams`) and its error with each of
    :data:`SWITCHES` off and on the ``isolated`` scan."""
    out: dict[str, Any] = _detection_beams(run, k, j, det)
    abl: dict[str, Any] = {}
    for name, sw in SWITCHES.items():
        d = ScanTrunkDetector(DetectorConfig.preset("stemmap", **{**overrides, **sw}))
        abl[name] = _error_in_scan(d, run, run.scans.ranges[k], k, j)
    abl["isolated"] = _error_in_scan(det, run, _isolated(run, k, j), k, j)
    out["ablation"] = abl
    return out


def seed_trunks(
    which: str, seed: int, overrides: dict[str, Any], top: int, z_max: float
) -> dict[str, Any]:
    """The per-seed, per-tree and per-pair breakdown of the module docstring."""
    run = drive(which, seed)
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides))
    err = tree_errors(det.detect_batch(run.scans), run)
    near = err["range"] < NEAR_M
    e = 100.0 * err["error"][near]
    bound = pair_bounds(run, err, near)
    z = e / bound
    ks, js = err["scan"][near], err["tree"][near]
    whole = err["whole"][near].astype(bool)
    sse = float(np.sum(e**2))
    beyond = np.isfinite(z) & (np.abs(z) > z_max)
    attainable = np.where(beyond, bound, e)
    trees = []
    for j in np.unique(js):
        t = js == j
        zt = z[t][np.isfinite(z[t])]
        crlb_t = _rms(bound[t])
        at_bound = zt.size > 0 and float(np.sum(zt**2)) <= float(chi2.ppf(0.99, zt.size))
        verdict = "beyond_bound"
        if at_bound:
            verdict = "bound_above_target" if (crlb_t or 0.0) > TARGET_CM else "bound"
        trees.append(
            {
                "tree": int(j),
                "pairs": int(t.sum()),
                "sse_share": round(float(np.sum(e[t] ** 2)) / sse, 3) if sse > 0 else 0.0,
                "rmse_cm": _rms(e[t]),
                "mean_error_cm": round(float(np.mean(e[t])), 2),
                "crlb_cm": crlb_t,
                "z_rms": _rms(z[t]),
                "verdict": verdict,
                "dbh_cm": round(100.0 * float(run.stand.diameters[j]), 1),
                "range_m": round(float(np.mean(err["range"][near][t])), 2),
                "partial_fraction": round(float(np.mean(~whole[t])), 2),
                "pairs_beyond": int(np.sum(beyond[t])),
            }
        )
    trees.sort(key=lambda r: -float(r["sse_share"]))
    shares = np.array([r["sse_share"] for r in trees])
    pairs = []
    for i in np.flatnonzero(beyond):
        k, j = int(ks[i]), int(js[i])
        beams = np.flatnonzero(run.hit_ids[k] == j)
        dist = float(err["range"][near][i])
        sides = edge_status(run.scans.ranges[k], beams, dist, float(run.stand.diameters[j]))
        pairs.append(
            {
                "scan": k,
                "tree": j,
                "range_m": round(dist, 2),
                "dbh_cm": round(100.0 * float(run.stand.diameters[j]), 1),
                "error_cm": round(float(e[i]), 2),
                "crlb_cm": round(float(bound[i]), 2),
                "z": round(float(z[i]), 1),
                "sse_share": round(float(e[i] ** 2) / sse, 3),
                "returns": int(beams.size),
                "edges": list(sides),
                **diagnose_pair(run, k, j, overrides, det),
            }
        )
    pairs.sort(key=lambda p: -abs(p["error_cm"]))
    return {
        "seed": seed,
        "drive": which,
        "pairs": int(e.size),
        "rmse_cm": _rms(e),
        "bias_cm": round(float(np.mean(e)), 3) if e.size else None,
        "crlb_rmse_cm": _rms(bound),
        "z_rms": _rms(z),
        "top1_sse_share": round(float(shares[:1].sum()), 3),
        "top3_sse_share": round(float(shares[:3].sum()), 3),
        "rmse_without_top1_cm": _rms(e[js != trees[0]["tree"]]) if trees else None,
        "pairs_beyond": int(beyond.sum()),
        "beyond_sse_share": round(float(np.sum(e[beyond] ** 2)) / sse, 3) if sse > 0 else 0.0,
        "attainable_rmse_cm": _rms(attainable),
        "trees_above_target_bound": int(sum(1 for r in trees if (r["crlb_cm"] or 0) > TARGET_CM)),
        "trees": trees[:top],
        "beyond": pairs,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[6, 11, 13, 17])
    ap.add_argument("--drive", choices=("benchmark", "demo"), default="benchmark")
    ap.add_argument("--set", type=json.loads, default=None, help="stemmap preset overrides")
    ap.add_argument("--top", type=int, default=5, help="trees listed per seed")
    ap.add_argument("--z", type=float, default=3.0, help="pairs beyond this many bounds")
    args = ap.parse_args(argv)
    for seed in args.seeds:
        row = seed_trunks(args.drive, seed, args.set or {}, args.top, args.z)
        print(json.dumps({"benchmark": "sim_dbh_trunks", "set": args.set, **row}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
