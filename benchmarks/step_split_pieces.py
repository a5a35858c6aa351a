"""Every piece ``step_split`` accepts, with what its beams hit (issue 11, Dec 4, "step split,
fold by fold").

Wraps :func:`stemmap.scan._step_split.step_refit` and lists each accepted piece: scan, its
beams, returns in the piece and in its parent candidate, fitted radius and mean range, the
sigma of its fit, the parent's range steps (cm), and the ground truth of its beams:

- ``--sim SEED``: the two simulated drives of ``_scan_sim`` (``scan_detection.py``'s 400
  scans and the ``stemmap demo`` drive), per beam the tree index, -2 clutter (rock, bush);
- ``--real NAME MODEL RES NOISE``: one real slice and scanner configuration of
  ``real_geometry.py --loo`` (its vantage points, seed and noise draw, 20 vantage points),
  per beam the reference trunk index or -1, and the nearest reference trunk to the piece's
  centre (index, distance m, radius m).

The detector is the ``stemmap`` preset with :data:`_loo_grid.LOO_GRID` setting ``--grid``
(default 36) and ``--set`` overrides (default ``{"step_split": true}``).

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    python benchmarks/step_split_pieces.py --sim 1
    python benchmarks/step_split_pieces.py --real treels_pine nearest 0.25 0.03
    python benchmarks/step_split_pieces.py --real treels_pine_plot nearest 0.5 0 \\
        --set '{"step_split": true, "step_noise_pool": true}'

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np

import stemmap.scan._pieces as pieces_mod
from _datasets import require_datasets_dir
from _loo_grid import LOO_GRID
from _real_scanning import (
    ANY_HIT,
    FULL_SCANNERS,
    ReturnRule,
    add_hit_fraction,
    matched,
    scene_scans,
    vantage_points,
)
from _scan_sim import _runs
from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch
from stemmap.scan._step_split import step_refit
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector


def _recorded(det: ScanTrunkDetector, batch: Any) -> list[dict[str, Any]]:
    """The accepted pieces of ``step_split`` while ``det`` runs on ``batch``."""
    rec: list[dict[str, Any]] = []

    def wrapped(*args: Any) -> Any:
        out = step_refit(*args)
        every = args[1]
        for g in out:
            for i in np.flatnonzero(g.ok):
                a, b = g.segs.start[i], g.segs.stop[i]
                pa, pb = every.start[g.parent[i]], every.stop[g.parent[i]]
                pts = g.segs.points
                rec.append(
                    {
                        "scan": int(pts.scan[a]),
                        "beams": pts.beam[a:b].tolist(),
                        "returns": int(b - a),
                        "parent_returns": int(pb - pa),
                        "radius_m": round(float(g.fitted.radii[i]), 3),
                        "centre_m": np.round(g.fitted.centers[i], 3).tolist(),
                        "range_m": round(float(np.mean(pts.r[a:b])), 2),
                        "sigma_m": round(float(g.fitted.sigma[i]), 4),
                        "parent_steps_cm": np.round(
                            np.diff(every.points.r[pa:pb]) * 100, 1
                        ).tolist(),
                    }
                )
        return out

    with mock.patch.object(pieces_mod, "step_refit", wrapped):
        det.detect_batch(batch)
    return rec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sim", type=int, default=None, help="simulator seed")
    ap.add_argument("--real", nargs=4, default=None, metavar=("NAME", "MODEL", "RES", "NOISE"))
    ap.add_argument("--grid", type=int, default=36)
    ap.add_argument("--set", type=json.loads, default={"step_split": True})
    ap.add_argument("--datasets", type=Path, default=None)
    add_hit_fraction(ap, ANY_HIT)
    args = ap.parse_args(argv)
    setting = {**LOO_GRID[args.grid], **args.set}
    out: dict[str, Any] = {"grid": args.grid, "set": args.set}
    if args.sim is not None:
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **setting))
        for drive, run in zip(("benchmark", "demo"), _runs(args.sim), strict=True):
            rec = _recorded(det, run.scans)
            for p in rec:
                p["hit"] = run.hit_ids[p["scan"], p["beams"]].tolist()
            out[drive] = {
                "pieces": len(rec),
                "on_trees": sum(all(h >= 0 for h in p["hit"]) for p in rec),
                "list": rec,
            }
    if args.real is not None:
        name, model, res, noise = (
            args.real[0],
            args.real[1],
            float(args.real[2]),
            float(args.real[3]),
        )
        ddir = require_datasets_dir(args.datasets)
        sl = load_slice(ddir, name)
        seed = 11 + list(SLICES).index(name)
        rng = np.random.default_rng(seed)
        vp = vantage_points(sl, 20, rng)
        # the LOO's noise draw: one per configuration, in FULL_SCANNERS order
        geo: dict[tuple[str, float], Any] = {}
        for m, rs, nz in FULL_SCANNERS:
            if (m, rs) not in geo:
                rule = ReturnRule(args.hit_fraction)
                geo[(m, rs)] = scene_scans(sl, vp, m, rs, "none", seed, return_rule=rule)
            ranges0, hit = geo[(m, rs)]
            batch = noisy_batch(ranges0, rs, nz, rng)
            if (m, rs, nz) == (model, res, noise):
                break
        else:
            print("error: not a configuration of FULL_SCANNERS", file=sys.stderr)
            return 2
        det = ScanTrunkDetector(matched(DetectorConfig.preset("stemmap", **setting), model, res))
        rec = _recorded(det, batch)
        for p in rec:
            p["hit"] = hit[p["scan"], p["beams"]].tolist()
            d = np.hypot(*(sl.centers - vp[p["scan"]] - np.asarray(p["centre_m"])).T)
            k = int(np.argmin(d))
            p["nearest_reference"] = [
                k,
                round(float(d[k]), 3),
                round(float(sl.diameters[k] / 2), 3),
            ]
        out["real"] = {"slice": name, "scanner": [model, res, noise], "list": rec}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
