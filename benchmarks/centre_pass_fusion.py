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
* ``mean``: the plain mean (every detection the same weight), stated ``cov(x_i) / n``.

Reported per scanner model, noise and dataset: groups, RMS error of the fused position (cm),
the RMS it states (``sqrt(mean trace P)``), the median Mahalanobis distance of the fused error
(1.177 calibrated) and the coverage of the 1- / 2-sigma ellipses (0.393 / 0.865).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/centre_pass_fusion.py [--models nearest]
        [--noise 0 0.01 0.03] [--set JSON]

Prints JSON.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from typing import Any

import numpy as np

from _real_scanning import matched
from diameter_rho_real import passes
from first_echo_dbh_z import SHORT
from stemmap.datasets import find_datasets_dir
from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch, virtual_scans
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector


def pass_records(
    name: str, model: str, noise: float, seed: int, cfg: DetectorConfig
) -> list[dict[str, Any]]:
    """One record per matched detection: trunk, pass, centre error (m), centre covariance."""
    where = find_datasets_dir()
    if where is None:
        raise SystemExit("no shared/datasets folder found: set STEMMAP_DATASETS.")
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
                centers=sl.centers,
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
                        }
                    )
    return out


def fuse(recs: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Scores of the fused positions of every (trunk, pass) group with >= 2 detections."""
    groups: dict[tuple[int, int], list[dict[str, Any]]] = defaultdict(list)
    for r in recs:
        groups[(r["trunk"], r["pass"])].append(r)
    res: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"information": [], "mean": []}
    for g in groups.values():
        if len(g) < 2:
            continue
        e = np.array([r["e"] for r in g])
        c = np.array([r["cxy"] for r in g]).reshape(-1, 2, 2)
        info = np.linalg.inv(c)
        p = np.linalg.inv(info.sum(axis=0))
        res["information"].append((p @ np.einsum("kij,kj->i", info, e), p))
        pm = np.cov(e.T) / e.shape[0]
        res["mean"].append((e.mean(axis=0), pm))
    out = {}
    for scheme, items in res.items():
        if not items:
            continue
        err = np.array([x for x, _ in items])
        cov = np.array([p for _, p in items])
        d = np.sqrt(np.einsum("ki,kij,kj->k", err, np.linalg.pinv(cov), err))
        out[scheme] = {
            "groups": len(items),
            "rms_cm": round(100.0 * float(np.sqrt(np.mean(np.sum(err * err, axis=1)))), 2),
            "stated_rms_cm": round(100.0 * float(np.sqrt(np.mean(cov[:, 0, 0] + cov[:, 1, 1]))), 2),
            "med_d": round(float(np.median(d)), 3),
            "cov1": round(float(np.mean(d <= 1.0)), 3),
            "cov2": round(float(np.mean(d <= 2.0)), 3),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.01, 0.03])
    ap.add_argument("--models", nargs="+", default=["nearest"])
    ap.add_argument("--seed", type=int, default=0, help="diameter_rho_real.py's --seed")
    ap.add_argument("--skip", nargs="*", default=["fortls_slice"], help="datasets left out")
    ap.add_argument("--set", default="{}", help="JSON overrides of the stemmap preset")
    a = ap.parse_args()
    base = DetectorConfig.preset("stemmap", **json.loads(a.set))
    out: dict[str, Any] = {"benchmark": "centre_pass_fusion", "set": a.set}
    for model in a.models:
        cfg = matched(base, model, 0.5)
        for noise in a.noise:
            pooled: list[dict[str, Any]] = []
            for i, name in enumerate(SLICES):
                if name in a.skip:
                    continue
                recs = pass_records(name, model, noise, a.seed + i, cfg)
                for r in recs:
                    r["trunk"] = (i, r["trunk"])
                key = f"{model} | {100 * noise:g} cm | {SHORT.get(name, name)}"
                out[key] = fuse(recs)
                pooled.extend(recs)
            out[f"{model} | {100 * noise:g} cm | all"] = fuse(pooled)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
