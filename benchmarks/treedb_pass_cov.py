"""The tree DB's reported tree covariance on REAL drive-by passes: detections' own covariances
and their correlation within a pass (issue 11, Dec 6; docs/algorithms/slam.md "Correlated
detections in the tree DB's covariance").

Input: the matched detections of ``centre_pass_fusion.py --rows-out`` (first-echo 0.5 deg
drive-by passes of every real breast-height slice, poses exact; several seeds' files pooled,
trunks told apart by file). Each (trunk, pass) group with >= 2 detections is mapped as the
tree DB (:class:`stemmap.slam._treedb_slam.TreeDbSlam`) maps it at exact poses: the tree is
the Kalman refinement of its detections (``refine``, the default: information-weighted by
the constant ``sigma_range`` / ``sigma_bearing``; with exact poses the refinement is that
weighted mean) or eq. (2)'s plain mean (``--eq2``), and its covariance is
:func:`stemmap.slam.tree_covariance.mapped_tree_covariances` at zero pose covariance:

* ``constant``: the detections' noise the constant ``diag(sigma_range², sigma_bearing²)``,
  independent (the tree DB's covariance before Dec 6);
* ``own``: each detection's own centre covariance (``TreeFrames.noise_cov``), independent;
* ``own_rho``: the same, correlated within the pass with ``rho`` (``--rho``, default
  ``CENTRE_RHO``).

Per dataset and noise level: groups, RMS error (cm), the RMS stated, median / 90th pct of the
Mahalanobis distance d (1.177 / 2.146 calibrated), inside 1 / 2 sigma (0.393 / 0.865).
``--loo``: ``rho`` chosen on all but one of TreeLS plot, pine, lidR (every noise level pooled)
as the smallest of 0, 0.05, ..., 1 whose pooled median d is <= 1.177, the held-out dataset's
median d per noise level (constant / own rho 0 / own at the chosen rho).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/treedb_pass_cov.py --rows-in FILE... [--loo]
        [--rho R] [--eq2] [--sigma-range M --sigma-bearing-deg DEG]

Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from typing import Any

import numpy as np

from centre_pass_fusion import dists, scores
from stemmap.slam.tree_covariance import mapped_tree_covariances
from stemmap.slam.uncertainty import CENTRE_RHO

TRUSTED = ("TreeLS plot", "TreeLS pine", "lidR")
SPACING = 100.0  # m between the groups' trees: each group is mapped as its own tree


class Cell:
    """The (trunk, pass) groups of one cell as one tree DB problem: group g's tree at
    (SPACING g, 0), one frame per detection, heading 0 (the scans' frame is the map's)."""

    def __init__(self, groups: list[list[dict[str, Any]]]) -> None:
        tree = np.concatenate([np.full(len(g), i) for i, g in enumerate(groups)])
        e = np.array([r["e"] for g in groups for r in g])
        c = np.array([r["centre"] for g in groups for r in g])
        cxy = np.array([r["cxy"] for g in groups for r in g]).reshape(-1, 2, 2)
        self.n = len(groups)
        self.tree = tree
        truth = np.column_stack((SPACING * tree, np.zeros(tree.size)))
        # the sensor: the detection (truth + error) minus its sensor-frame centre
        self.poses = np.column_stack((truth + e - c, np.zeros(tree.size)))
        self.ranges = np.hypot(c[:, 0], c[:, 1])
        self.bearings = np.arctan2(c[:, 1], c[:, 0])
        self.ptr = np.arange(tree.size + 1)
        self.times = tree * 1e3 + np.arange(tree.size)  # one pass per group
        self.e = e
        J = np.zeros((tree.size, 2, 2))
        r = self.ranges
        J[:, 0, 0], J[:, 0, 1] = c[:, 0] / r, c[:, 1] / r
        J[:, 1, 0], J[:, 1, 1] = -c[:, 1] / r**2, c[:, 0] / r**2
        self.polar = J @ cxy @ np.swapaxes(J, 1, 2)  # TreeFrames.from_observations' noise_cov

    def fused(self, sr: float, sb: float, eq2: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Map-frame tree positions (n, 2) and the refinement's information weights."""
        z = np.column_stack((self.poses[:, 0] + self.ranges * np.cos(self.bearings),
                             self.poses[:, 1] + self.ranges * np.sin(self.bearings)))  # fmt: skip
        if eq2:
            cnt = np.bincount(self.tree, minlength=self.n)[:, None]
            acc = np.zeros((self.n, 2))
            np.add.at(acc, self.tree, z)
            return acc / cnt, None
        b = self.bearings
        Jz = np.zeros((b.size, 2, 2))
        Jz[:, 0, 0], Jz[:, 0, 1] = np.cos(b), -self.ranges * np.sin(b)
        Jz[:, 1, 0], Jz[:, 1, 1] = np.sin(b), self.ranges * np.cos(b)
        info = np.linalg.inv(Jz @ np.diag([sr * sr, sb * sb]) @ np.swapaxes(Jz, 1, 2))
        tot = np.zeros((self.n, 2, 2))
        np.add.at(tot, self.tree, info)
        acc = np.zeros((self.n, 2))
        np.add.at(acc, self.tree, np.einsum("kij,kj->ki", info, z))
        return np.einsum("nij,nj->ni", np.linalg.inv(tot), acc), info

    def scheme(
        self, scheme: str, rho: float, sr: float, sb: float, eq2: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Errors (n, 2) and stated covariances (n, 2, 2) of the groups' trees."""
        xy, _ = self.fused(sr, sb, eq2)
        cov, nobs = mapped_tree_covariances(
            xy, self.poses, np.zeros((self.tree.size, 3, 3)), self.ptr, self.ranges,
            self.bearings, sigma_range=sr, sigma_bearing=sb, gate=0.5 * SPACING,
            information_pose_covs=None if eq2 else np.zeros((self.tree.size, 3, 3)),
            detection_covs=None if scheme == "constant" else self.polar, times=self.times,
            pass_rho=rho if scheme == "own_rho" else 0.0,
        )  # fmt: skip
        assert np.array_equal(nobs, np.bincount(self.tree, minlength=self.n))
        err = xy - np.column_stack((SPACING * np.arange(self.n), np.zeros(self.n)))
        return err, cov


def load(paths: list[str]) -> dict[str, list[list[dict[str, Any]]]]:
    """Per cell key, the (trunk, pass) groups with >= 2 detections (files pooled)."""
    rows: dict[str, dict[str, list[dict[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for j, path in enumerate(paths):
        with open(path) as f:
            for key, recs in json.load(f).items():
                for r in recs:
                    rows[key][json.dumps([j, r["trunk"], r["pass"]])].append(r)
    return {k: [g for g in v.values() if len(g) >= 2] for k, v in rows.items()}


def med_d(cells: list[Cell], rho: float, sr: float, sb: float, eq2: bool) -> float:
    d = [dists(*c.scheme("own_rho", rho, sr, sb, eq2)) for c in cells]
    return float(np.median(np.concatenate(d)))


def choose_rho(cells: list[Cell], sr: float, sb: float, eq2: bool) -> float:
    for rho in np.round(np.arange(0.0, 1.0001, 0.05), 2):
        if med_d(cells, float(rho), sr, sb, eq2) <= 1.177:
            return float(rho)
    return 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows-in", nargs="+", required=True)
    ap.add_argument("--rho", type=float, default=CENTRE_RHO)
    ap.add_argument("--loo", action="store_true")
    ap.add_argument("--eq2", action="store_true", help="eq. (2)'s plain mean (refine off)")
    ap.add_argument("--sigma-range", type=float, default=0.3, help="TreeDbSlam's default")
    ap.add_argument("--sigma-bearing-deg", type=float, default=1.0)
    a = ap.parse_args()
    sr, sb = a.sigma_range, math.radians(a.sigma_bearing_deg)
    groups = load(a.rows_in)
    cells = {k: Cell(g) for k, g in groups.items() if g}
    out: dict[str, Any] = {"benchmark": "treedb_pass_cov", "rho": a.rho, "eq2": a.eq2,
                           "sigma_range": sr, "sigma_bearing_deg": a.sigma_bearing_deg}  # fmt: skip
    if a.loo:
        by: dict[str, list[Cell]] = defaultdict(list)
        for k, c in cells.items():
            by[k.rsplit(" | ", 1)[1]].append(c)
        for held in TRUSTED:
            train = [c for n in TRUSTED if n != held for c in by[n]]
            rho = choose_rho(train, sr, sb, a.eq2)
            res: dict[str, Any] = {
                "rho": rho,
                "train_med_d": round(med_d(train, rho, sr, sb, a.eq2), 3),
            }
            for k, c in cells.items():
                if k.endswith(" | " + held):
                    const, own = (
                        float(np.median(dists(*c.scheme(s, 0.0, sr, sb, a.eq2))))
                        for s in ("constant", "own")
                    )
                    res[k] = {
                        "groups": c.n,
                        "constant": round(const, 3),
                        "own": round(own, 3),
                        "own_rho": round(med_d([c], rho, sr, sb, a.eq2), 3),
                        "own_centre_rho": round(med_d([c], a.rho, sr, sb, a.eq2), 3),
                    }
            out[held] = res
        out["all three"] = choose_rho([c for n in TRUSTED for c in by[n]], sr, sb, a.eq2)
    else:
        for k, c in cells.items():
            out[k] = {"groups": c.n} | {
                s: scores(*c.scheme(s, a.rho, sr, sb, a.eq2))
                for s in ("constant", "own", "own_rho")
            }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
