"""Which returns bias a real trunk's fit: per detected view, the returns the detector fitted and
their residuals along the arc (issue 11, seventeenth round, "Branch stubs at the arc end").

Same slices, vantage points and seeds as ``benchmarks/real_geometry.py --loo`` (seed 11 + the
dataset's index in :data:`stemmap.eval.real_slices.SLICES`), 0.5 deg nearest-return without
noise, the ``stemmap`` preset with a :data:`_loo_grid.LOO_GRID` setting (``--grid``, default
37) and ``--set`` overrides. For each visible trunk (>= 4 own returns, <= 15 m, 10-100 cm) of
each scan: the DBH error of its detection (or ``missed``) and, per fitted return in bearing
order, its beam, whether the virtual scanner hit that trunk's own ring points (``own``; a
return that is not is a branch, stub or neighbour), and its residual ``|p - c| - r`` (mm) to
the detected circle and to the reference circle (positive: outside). The fitted returns are
read from the rows the detector writes out (``_output_columns``, called by
:mod:`stemmap.scan.detect` for the main fits and by :mod:`stemmap.scan._pieces` for split pieces
and arcs), so they are those of the fit that made the detection (main fit, split piece or arc),
after the footprint correction.

Usage::

    python benchmarks/real_geometry_arc_residuals.py                     # lidR, grid 37
    python benchmarks/real_geometry_arc_residuals.py --set '{"stub_sigmas": 2}'
    python benchmarks/real_geometry_arc_residuals.py --only archi_tree1 --grid 36

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

import stemmap.scan._pieces as pieces_module
import stemmap.scan.detect as detect_module
from _datasets import require_datasets_dir
from _loo_grid import LOO_GRID
from _real_scanning import greedy_match, matched, scene_scans, vantage_points
from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.types import StemObservations


def _recording(rows: list[dict[str, Any]]) -> Any:
    """``_output_columns`` that also keeps every output row's returns and circle."""
    original = detect_module._output_columns

    def wrapped(segs: Any, fitted: Any, ok: np.ndarray, cfg: Any = None) -> Any:
        p = segs.points
        for k in np.flatnonzero(ok):
            s = slice(int(segs.start[k]), int(segs.stop[k]))
            rows.append(
                {
                    "scan": int(segs.scan[k]),
                    "beam": p.beam[s].copy(),
                    "xy": np.column_stack((p.x[s], p.y[s])),
                    "center": fitted.centers[k].copy(),
                    "radius": float(fitted.radii[k]),
                }
            )
        return original(segs, fitted, ok, cfg)

    return original, wrapped


def detect_recording(
    det: ScanTrunkDetector, batch: Any
) -> tuple[StemObservations, list[dict[str, Any]]]:
    """``det.detect_batch(batch)`` and, per output row, its returns and circle
    (:func:`_recording` on every module that writes output rows)."""
    rows: list[dict[str, Any]] = []
    original, wrapped = _recording(rows)
    writers = (detect_module, pieces_module)
    for mod in writers:
        mod._output_columns = wrapped
    try:
        obs = det.detect_batch(batch)
    finally:
        for mod in writers:
            mod._output_columns = original
    return obs, rows


def views(ddir: Path, name: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """Every visible trunk view of slice ``name`` (module docstring)."""
    i = list(SLICES).index(name)
    sl = load_slice(ddir, name)
    rng = np.random.default_rng(11 + i)
    vp = vantage_points(sl, 20, rng)
    ranges0, hit = scene_scans(sl, vp, "nearest", 0.5, "none", 11 + i)
    batch = noisy_batch(ranges0, 0.5, 0.0, rng)
    cfg = matched(DetectorConfig.preset("stemmap", **overrides), "nearest", 0.5)
    obs, rows = detect_recording(ScanTrunkDetector(cfg), batch)
    out: list[dict[str, Any]] = []
    for s in range(vp.shape[0]):
        rel = sl.centers - vp[s]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        m = obs.index == s
        match = greedy_match(obs.centers[m], rel, sl.diameters / 2.0 + 0.05)
        for t in range(len(sl.refs)):
            own_n = int((hit[s] == t).sum())
            if not (own_n >= 4 and dist[t] <= 15.0 and 0.1 <= sl.diameters[t] <= 1.0):
                continue
            view: dict[str, Any] = {"scan": s, "trunk": t, "range_m": round(float(dist[t]), 2)}
            view["own_returns"] = own_n
            if match[t] < 0:
                out.append({**view, "missed": True})
                continue
            c, r = obs.centers[m][match[t]], float(obs.radii[m][match[t]])
            view["dbh_error_cm"] = round(100.0 * (2.0 * r - sl.diameters[t]), 2)
            rec = [q for q in rows if q["scan"] == s and np.allclose(q["center"], c)]
            if rec:
                q = rec[0]
                res_det = np.hypot(*(q["xy"] - c).T) - r
                res_ref = np.hypot(*(q["xy"] - rel[t]).T) - sl.diameters[t] / 2.0
                view["returns"] = [
                    {
                        "beam": int(b),
                        "own": bool(hit[s][b] == t),
                        "res_fit_mm": round(1000.0 * float(a), 1),
                        "res_ref_mm": round(1000.0 * float(e), 1),
                    }
                    for b, a, e in zip(q["beam"], res_det, res_ref, strict=True)
                ]
            out.append(view)
    err = np.array([v.get("dbh_error_cm", math.nan) for v in out])
    near = np.array([v["range_m"] <= 10.0 for v in out])
    ok = np.isfinite(err) & near
    return {
        "views": out,
        "recall": round(float(np.isfinite(err).mean()), 3) if err.size else None,
        "rmse_cm_le10m": round(float(np.sqrt(np.mean(err[ok] ** 2))), 2) if ok.any() else None,
        "bias_cm_le10m": round(float(np.mean(err[ok])), 2) if ok.any() else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", type=Path, default=None)
    ap.add_argument("--only", nargs="*", default=["lidr_dbh"])
    ap.add_argument("--grid", type=int, default=37, help="LOO_GRID setting (default 37)")
    ap.add_argument("--set", type=json.loads, default={}, help="overrides on top of --grid")
    args = ap.parse_args(argv)
    ddir = require_datasets_dir(args.datasets)
    over = {**LOO_GRID[args.grid], **args.set}
    result = {
        "benchmark": "real_geometry_arc_residuals",
        "scanner": "nearest-return 0.5 deg, no noise, 20 vantage points",
        "grid": args.grid,
        "set": args.set,
        "datasets": {name: views(ddir, name, over) for name in args.only},
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
