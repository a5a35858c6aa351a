"""Benchmark: where a stem's DBH comes from, stage by stage, against its fixed full-ring reference
(docs/algorithms/cloud.md "Breast-height DBH, stage by stage").

For every real cloud of ``_cloud_refs`` the detector runs as in cloud_real.py (preset ours,
heights on, default or ``--set`` options) with its per-stem measurement
(:func:`stemmap.cloud.slicestem._stem_at`) and its slice agreement
(:func:`stemmap.cloud.slicestem._consistent_slices`) recorded, not changed. Per detected stem
that pairs with a reference ring (``reference_of_each``), in cm of diameter:

* ``slices``: each kept slice's height (m above ground), fitted diameter, RMS, arc, inliers,
  and the plain least-squares ring of the same cloud at that slice's height and thickness
  (``converged_ring_reference`` from the detected circle: the reference's estimator, moved
  to the slice) -- the slice fit's own error at its height;
* ``consensus``: the agreement's consensus diameter (the median / weighted median of the
  agreeing slices);
* ``slice_bh``: the kept slice holding the measurement height;
* ``line``: the Theil-Sen radius line at the measurement height before the lean correction,
  ``lean_factor`` that correction, and ``dbh``: the output;
* ``ring``: the reference (diameter, RMS, arc, start spread, points) and ``ring_slices``: the
  plain ring at every kept slice's height, through which the same Theil-Sen line gives
  ``ring_line`` (the line's effect on the reference's own estimator);
* ``final_from``: "band" or "thin" (a thin re-measure's slices) -- which call gave the row.

Prints ONE JSON object; per cloud the stems and a summary (bias and RMSE of each stage over
the full rings). Usage: python benchmarks/cloud_dbh_trace.py [--clouds a,b] [--set key=value]
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from typing import Any

import numpy as np

from _cloud_refs import CLOUDS, fixed_references, load_seeds, reference_of_each
from _datasets import require_datasets_dir
from cloud_robustness import set_overrides
from stemmap.cloud import slicestem
from stemmap.cloud.reference import converged_ring_reference
from stemmap.cloud.result import BASE_SLICE
from stemmap.cloud.slicefit import _theil_sen
from stemmap.cloud.stems import StemConfig, detect_stems_file
from stemmap.io.clouds import read_cloud


def _cm(v: float) -> float | None:
    return round(100 * float(v), 2) if math.isfinite(v) else None


class _Recorder:
    """Wraps ``_consistent_slices`` and ``_stem_at`` of :mod:`stemmap.cloud.slicestem`: every
    call's inputs and result are kept (the detector runs unchanged)."""

    def __init__(self) -> None:
        self.calls: list[dict[str, Any]] = []
        self._last_agree: Any = None
        self._orig_cons = slicestem._consistent_slices
        self._orig_at = slicestem._stem_at

    def __enter__(self) -> _Recorder:
        rec = self

        def cons(*a: Any, **k: Any) -> Any:
            out = rec._orig_cons(*a, **k)
            rec._last_agree = out
            return out

        def at(fits: Any, c: int, m: Any, hh: Any, cfg: Any, at_slice: bool = False) -> Any:
            out = rec._orig_at(fits, c, m, hh, cfg, at_slice)
            if out is not None:
                rec.calls.append(
                    {
                        "radii": fits.radii[c, m].copy(),
                        "rms": fits.rms[c, m].copy(),
                        "arcs": fits.arcs[c, m].copy(),
                        "n_in": fits.n_in[c, m].copy(),
                        "centers": fits.centers[c, m].copy(),
                        "hh": np.asarray(hh, dtype=float).copy(),
                        "half": cfg.slice_thickness / 2,
                        "consensus_r": float(rec._last_agree.radius)
                        if rec._last_agree is not None
                        else math.nan,
                        "at_slice": at_slice,
                        "r_out": out[0],
                        "xy": np.asarray(out[1]).copy(),
                        "thin": cfg.slice_thickness,
                    }
                )
            return out

        slicestem._consistent_slices = cons  # type: ignore[assignment]
        slicestem._stem_at = at  # type: ignore[assignment]
        return self

    def __exit__(self, *exc: object) -> None:
        slicestem._consistent_slices = self._orig_cons  # type: ignore[assignment]
        slicestem._stem_at = self._orig_at  # type: ignore[assignment]


def _call_of(calls: list[dict[str, Any]], xy: np.ndarray, d: float) -> dict[str, Any] | None:
    """The last recorded call whose result is this output row (same diameter and centre)."""
    for call in reversed(calls):
        if abs(2 * call["r_out"] - d) < 1e-9 and np.hypot(*(call["xy"] - xy)) < 1e-9:
            return call
    return None


def _stage_row(
    xyz: np.ndarray | None, call: dict[str, Any], zbh: float, h_meas: float, dbh: float
) -> dict[str, Any]:
    hh, radii, cen = call["hh"], call["radii"], call["centers"]
    row: dict[str, Any] = {"final_from": "thin" if call["thin"] <= 0.2 + 1e-9 else "thick"}
    slices = []
    ring_r = []
    for k in range(hh.size):
        # the slice's absolute z: breast-height z + (its height - breast height)
        z = zbh + (hh[k] + h_meas - 1.3)
        ring = (
            None
            if xyz is None  # a pre-cut slice: no heights to ring at
            else converged_ring_reference(
                xyz,
                (float(cen[k, 0]), float(cen[k, 1])),
                z,
                float(radii[k]),
                half_thickness=call["half"],
            )
        )
        ring_r.append(math.nan if ring is None else ring.diameter / 2)
        slices.append(
            {
                "h_m": round(float(hh[k] + h_meas), 2),
                "fit_cm": _cm(2 * radii[k]),
                "plain_ring_cm": None if ring is None else _cm(ring.diameter),
                "rms_mm": round(1000 * float(call["rms"][k]), 1),
                "arc_deg": round(float(call["arcs"][k])),
                "n_in": int(call["n_in"][k]),
            }
        )
    row["slices"] = slices
    row["consensus_cm"] = _cm(2 * call["consensus_r"])
    on = np.flatnonzero(np.abs(hh) <= call["half"] + 1e-9)
    row["slice_bh_cm"] = _cm(2 * radii[on[np.argmin(np.abs(hh[on]))]]) if on.size else None
    if hh.size >= 3 and np.ptp(hh) >= 0.3:
        a, b = _theil_sen(hh, radii)
        row["line_cm"] = _cm(2 * a)
        row["taper_mm_per_m"] = round(1000 * b, 1)
        row["lean_factor"] = round(dbh / (2 * a), 5) if not call["at_slice"] else None
        rr = np.asarray(ring_r)
        ok = np.isfinite(rr)
        if ok.sum() >= 3 and np.ptp(hh[ok]) >= 0.3:
            row["ring_line_cm"] = _cm(2 * _theil_sen(hh[ok], rr[ok])[0])
    else:
        row["line_cm"] = None
        row["mean_cm"] = _cm(2 * float(np.average(radii)))
    row["weighted_mean_cm"] = _cm(
        2 * float(np.average(radii, weights=call["n_in"] / np.maximum(call["rms"], 1e-4) ** 2))
    )
    row["median_cm"] = _cm(2 * float(np.median(radii)))
    return row


STAGES = ("slice_bh_cm", "consensus_cm", "line_cm", "median_cm", "weighted_mean_cm", "dbh_cm")


def run_cloud(root: Any, key: str, overrides: dict[str, Any]) -> dict[str, Any]:
    path = str(root / CLOUDS[key])
    xyz = read_cloud(path).xyz
    refs = fixed_references(xyz, load_seeds()[key])
    with _Recorder() as rec:
        det = detect_stems_file(path, replace(StemConfig(), estimate_height=True, **overrides))
    stems = []
    for i, hit in enumerate(reference_of_each(refs, det.xy)):
        if hit is None:
            continue
        k, ref = hit
        d = float(det.diameter[i])
        row: dict[str, Any] = {
            "ring_id": k,
            "ring_cm": _cm(ref.diameter),
            "ring_rms_mm": round(1000 * ref.rms, 1),
            "ring_arc_deg": round(ref.arc_deg),
            "ring_spread_cm": _cm(ref.spread),
            "ring_points": ref.n,
            "ring_full": ref.full,
            "dbh_cm": _cm(d),
            "dbh_height_m": round(float(det.dbh_height[i]), 2),
        }
        call = _call_of(rec.calls, det.xy[i], d)
        if call is not None:
            pts = None if det.base == BASE_SLICE else xyz
            row |= _stage_row(pts, call, float(det.z[i]), float(det.dbh_height[i]), d)
        stems.append(row)
    summary: dict[str, Any] = {}
    full = [s for s in stems if s["ring_full"]]
    for st in (*STAGES, "ring_line_cm"):
        e = np.array([s[st] - s["ring_cm"] for s in full if s.get(st) is not None])
        if e.size:
            summary[st] = {
                "n": int(e.size),
                "bias_cm": round(float(e.mean()), 2),
                "rmse_cm": round(float(np.sqrt(np.mean(e**2))), 2),
            }
    e_sl = np.array(
        [
            sl["fit_cm"] - sl["plain_ring_cm"]
            for s in full
            for sl in s.get("slices", [])
            if sl["plain_ring_cm"] is not None
        ]
    )
    if e_sl.size:
        summary["slice_fit_vs_plain_ring"] = {
            "n": int(e_sl.size),
            "bias_cm": round(float(e_sl.mean()), 2),
            "rmse_cm": round(float(np.sqrt(np.mean(e_sl**2))), 2),
        }
    return {"n_stems": len(det), "summary": summary, "stems": stems}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    args = ap.parse_args()
    overrides = set_overrides(args.set)
    root = require_datasets_dir()
    out = {
        "benchmark": "cloud_dbh_trace",
        "set": overrides,
        "clouds": {k: run_cloud(root, k, overrides) for k in args.clouds.split(",")},
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
