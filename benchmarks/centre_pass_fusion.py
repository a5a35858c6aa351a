"""Map-level tree POSITION fused over a drive-by pass on REAL trunk geometry: is the fused
position's stated covariance calibrated, and do the detections' centre covariances weight
well? (issue 11, Dec 6, "First-echo centre covariance" in docs/algorithms/scan-detection.md;
the position analogue of ``map_dbh_fusion.py``.)

The passes of ``diameter_rho_real.py`` (every real breast-height slice, DBH 10-100 cm, a 0.5
deg scan every 0.5 m from 15 m before to 15 m after the trunk at 4 and 8 m offset on both
sides; the same seeds, so the same scans), the ``stemmap`` preset set up for the scanner
(``--set``: overrides on top of it). The poses are exact, so what is measured is the
detections' share of a map's position error. Per (trunk, pass) group with >= 2 matched
detections (within radius + 5 cm of the reference centre, the slice's full-ring fit):

* ``information``: the information-weighted mean ``P = (sum C_i^-1)^-1``, ``x = P sum
  C_i^-1 x_i`` with ``C_i`` the detection's reported centre covariance -- what a tree
  database or a landmark filter fusing independent detections by their covariance states;
* ``correlated``: the same position, its covariance from
  ``stemmap.slam.uncertainty.fused_positions`` with the detections' errors correlated within
  the pass (``--rho``, default ``CENTRE_RHO``; ``--shared``: which part of each detection's
  covariance is shared -- all of it, the default, or the outline's terms);
* ``mean``: the plain mean (every detection the same weight), stated ``cov(x_i) / n``.

Reported per scanner model, noise and dataset: groups, RMS error of the fused position (cm),
the RMS it states (``sqrt(mean trace P)``), the median and 90th percentile of the Mahalanobis
distance of the fused error (1.177 / 2.146 calibrated) and the coverage of the 1- / 2-sigma
ellipses (0.393 / 0.865). ``--loo``: ``rho`` chosen on all but one real-bark dataset (TreeLS
plot, pine, lidR; every noise level pooled) as the smallest of 0, 0.05, ..., 1 whose pooled
median d is <= 1.177, the held-out dataset's median d per noise level before (rho 0) / after.
``--rows-out`` / ``--rows-in`` keep the matched detections (several seeds pooled: give each
``--seed``'s file, trunks told apart by file).

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/centre_pass_fusion.py [--models nearest]
        [--noise 0 0.01 0.03] [--set JSON] [--seed S --rows-out FILE]
    PYTHONPATH=src:benchmarks python benchmarks/centre_pass_fusion.py --rows-in FILE...
        [--loo] [--rho R] [--shared all|both|along]

Prints JSON.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _real_scanning import ANY_HIT, ReturnRule, add_hit_fraction, matched
from diameter_rho_real import passes
from first_echo_dbh_z import SHORT
from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch, virtual_scans
from stemmap.scan._centre_cov import outline_centre_covs, outline_covs
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.slam.uncertainty import CENTRE_RHO, fused_positions


def pass_records(
    name: str, model: str, noise: float, seed: int, cfg: DetectorConfig, return_rule: ReturnRule
) -> list[dict[str, Any]]:
    """One record per matched detection: trunk, pass, centre error (m), centre covariance
    (``return_rule``: the averaging scanner's)."""
    where = require_datasets_dir()
    sl = load_slice(where, name)
    rng = np.random.default_rng(seed)
    det = ScanTrunkDetector(cfg)
    out = []
    for t, (c, d) in enumerate(zip(sl.centers, sl.diameters, strict=True)):
        if not 0.1 <= d <= 1.0:
            continue
        for p, vp in enumerate(passes(c, rng)):
            ranges0, _ = virtual_scans(
                sl.xy, sl.labels, vp, resolution_deg=0.5, model=model,  # type: ignore[arg-type]
                centers=sl.centers, **return_rule.kwargs(),
            )  # fmt: skip
            obs = det.detect_batch(noisy_batch(ranges0, 0.5, noise, rng))
            for s in range(vp.shape[0]):
                m = np.flatnonzero(obs.index == s)
                if not m.size:
                    continue
                dist = np.hypot(*(obs.centers[m] - (c - vp[s])).T)
                k = m[int(np.argmin(dist))]
                if dist.min() <= d / 2.0 + 0.05:
                    e = obs.centers[k] - (c - vp[s])
                    out.append(
                        {
                            "trunk": t,
                            "pass": p,
                            "e": [float(e[0]), float(e[1])],
                            "cxy": [float(v) for v in obs.covs[k, :2, :2].ravel()],
                            "centre": [float(v) for v in obs.centers[k]],
                        }
                    )
    return out


def group_detections(recs: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """The (trunk, pass) groups with >= 2 detections."""
    groups: dict[tuple[str, int], list[dict[str, Any]]] = defaultdict(list)
    for r in recs:
        groups[(json.dumps(r["trunk"]), r["pass"])].append(r)
    return [g for g in groups.values() if len(g) >= 2]


def shared_covs(g: list[dict[str, Any]], cfg: DetectorConfig, part: str) -> np.ndarray:
    """The outline's part of each detection's centre covariance (``outline_centre_covs``);
    ``part`` "along": its along-sight term alone; "all": the whole covariance
    (``fused_positions``' default)."""
    c = np.array([r["centre"] for r in g])
    if part == "all":
        return np.array([r["cxy"] for r in g]).reshape(-1, 2, 2)
    if part == "along":
        return outline_covs(c, cfg.dbh_sd_outline, cfg.centre_sd_along, 0.0)
    return outline_centre_covs(c, cfg)


def fused_errors(
    groups: list[list[dict[str, Any]]], cfg: DetectorConfig, rho: float, part: str = "all"
) -> tuple[np.ndarray, np.ndarray]:
    """Errors (G, 2) and stated covariances (G, 2, 2) of the groups' information-weighted
    positions (``fused_positions``, the outline part correlated with ``rho``)."""
    err, cov = [], []
    for g in groups:
        e = np.array([r["e"] for r in g])
        c = np.array([r["cxy"] for r in g]).reshape(-1, 2, 2)
        x, p, _ = fused_positions(
            np.zeros(len(g), np.int64), e, c, 1, shared=shared_covs(g, cfg, part), rho=rho
        )
        err.append(x[0])
        cov.append(p[0])
    return np.array(err).reshape(-1, 2), np.array(cov).reshape(-1, 2, 2)


def dists(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Mahalanobis distances of the errors ``err`` (K, 2) under their covariances (K, 2, 2)."""
    return np.sqrt(np.einsum("ki,kij,kj->k", err, np.linalg.pinv(cov), err))


def scores(err: np.ndarray, cov: np.ndarray) -> dict[str, float]:
    """RMS error, the RMS the covariances state, median / 90th percentile of the distances and
    the shares inside 1 and 2 sigma, over ``groups`` (K) fused positions."""
    d = dists(err, cov)
    return {
        "groups": int(err.shape[0]),
        "rms_cm": round(100.0 * float(np.sqrt(np.mean(np.sum(err * err, axis=1)))), 2),
        "stated_rms_cm": round(100.0 * float(np.sqrt(np.mean(cov[:, 0, 0] + cov[:, 1, 1]))), 2),
        "med_d": round(float(np.median(d)), 3),
        "p90_d": round(float(np.quantile(d, 0.9)), 3),
        "cov1": round(float(np.mean(d <= 1.0)), 3),
        "cov2": round(float(np.mean(d <= 2.0)), 3),
    }


def fuse(
    recs: list[dict[str, Any]], cfg: DetectorConfig, rho: float, part: str = "all"
) -> dict[str, dict[str, float]]:
    """Scores of the fused positions of every (trunk, pass) group with >= 2 detections:
    ``information`` (independent detections, rho 0), ``correlated`` (``rho``), ``mean``."""
    groups = group_detections(recs)
    if not groups:
        return {}
    out = {"information": scores(*fused_errors(groups, cfg, 0.0, part))}
    out["correlated"] = scores(*fused_errors(groups, cfg, rho, part))
    err, cov = [], []
    for g in groups:
        e = np.array([r["e"] for r in g])
        err.append(e.mean(axis=0))
        cov.append(np.cov(e.T) / e.shape[0])
    out["mean"] = scores(np.array(err), np.array(cov))
    return out


def median_d(
    groups: list[list[dict[str, Any]]], cfg: DetectorConfig, rho: float, part: str
) -> float:
    err, cov = fused_errors(groups, cfg, rho, part)
    return float(np.median(np.sqrt(np.einsum("ki,kij,kj->k", err, np.linalg.inv(cov), err))))


def choose_rho(
    groups: list[list[dict[str, Any]]], cfg: DetectorConfig, part: str, target: float = 1.177
) -> float:
    """The smallest rho of the grid (0, 0.05, ..., 1) whose pooled median d is <= ``target``
    (1 when none is: the most the model can state)."""
    for rho in np.round(np.arange(0.0, 1.0001, 0.05), 2):
        if median_d(groups, cfg, float(rho), part) <= target:
            return float(rho)
    return 1.0


TRUSTED = ("TreeLS plot", "TreeLS pine", "lidR")


def loo(rows: dict[str, list[dict[str, Any]]], cfg: DetectorConfig, part: str) -> dict[str, Any]:
    """rho chosen on the other real-bark datasets (every noise level pooled), scored on the one
    left out, per noise level; then the choice on all three."""
    by: dict[str, list[list[dict[str, Any]]]] = defaultdict(list)
    cells: dict[str, list[list[dict[str, Any]]]] = {}
    for key, recs in rows.items():
        name = key.rsplit(" | ", 1)[1]
        gs = group_detections(recs)
        cells[key] = gs
        by[name].extend(gs)
    out: dict[str, Any] = {"part": part}
    for held in TRUSTED:
        train = [g for n in TRUSTED if n != held for g in by[n]]
        rho = choose_rho(train, cfg, part)
        res: dict[str, Any] = {"rho": rho, "train_med_d": round(median_d(train, cfg, rho, part), 3)}
        for key, gs in cells.items():
            if key.endswith(" | " + held) and gs:
                res[key] = {
                    "groups": len(gs),
                    "before": round(median_d(gs, cfg, 0.0, part), 3),
                    "after": round(median_d(gs, cfg, rho, part), 3),
                }
        out[held] = res
    out["all three"] = choose_rho([g for n in TRUSTED for g in by[n]], cfg, part)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.01, 0.03])
    ap.add_argument("--models", nargs="+", default=["nearest"])
    ap.add_argument("--seed", type=int, default=0, help="diameter_rho_real.py's --seed")
    ap.add_argument("--skip", nargs="*", default=["fortls_slice"], help="datasets left out")
    ap.add_argument("--set", default="{}", help="JSON overrides of the stemmap preset")
    ap.add_argument("--rows-out", help="write the matched detections (JSON) to this file")
    ap.add_argument("--rows-in", nargs="+", help="score these rows (--rows-out) instead")
    ap.add_argument("--rho", type=float, default=CENTRE_RHO, help="the correlated scheme's rho")
    ap.add_argument(
        "--shared", choices=["all", "both", "along"], default="all",
        help="the part of each detection's centre covariance shared within a pass: all of it "
        "(fused_positions' default), the outline's terms (along and across the line of "
        "sight), or the along term only",
    )  # fmt: skip
    ap.add_argument("--loo", action="store_true", help="choose rho leave one dataset out")
    add_hit_fraction(ap, ANY_HIT)
    a = ap.parse_args()
    rule = ReturnRule(a.hit_fraction)
    base = DetectorConfig.preset("stemmap", **json.loads(a.set))
    rows: dict[str, list[dict[str, Any]]]
    if a.rows_in:  # several files (e.g. --seed 0..4): pooled, trunks told apart by file
        rows = defaultdict(list)
        for j, path in enumerate(a.rows_in):
            with open(path) as f:
                for key, recs in json.load(f).items():
                    for r in recs:
                        r["trunk"] = [j, *r["trunk"]]
                    rows[key].extend(recs)
    else:
        rows = {}
        for model in a.models:
            cfg = matched(base, model, 0.5)
            for noise in a.noise:
                for i, name in enumerate(SLICES):
                    if name in a.skip:
                        continue
                    recs = pass_records(name, model, noise, a.seed + i, cfg, rule)
                    for r in recs:
                        r["trunk"] = [i, r["trunk"]]
                    rows[f"{model} | {100 * noise:g} cm | {SHORT.get(name, name)}"] = recs
        if a.rows_out:
            with open(a.rows_out, "w") as f:
                json.dump(rows, f)
    out: dict[str, Any] = {"benchmark": "centre_pass_fusion", "set": a.set, "rho": a.rho}
    cfg = matched(base, "nearest", 0.5)  # the outline terms are the preset's (any first echo)
    if a.loo:
        out["loo"] = loo(rows, cfg, a.shared)
        print(json.dumps(out))
        return
    pooled: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for key, recs in rows.items():
        out[key] = fuse(recs, cfg, a.rho, a.shared)
        pooled[key.rsplit(" | ", 1)[0] + " | all"].extend(recs)
    for key, recs in pooled.items():
        out[key] = fuse(recs, cfg, a.rho, a.shared)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
