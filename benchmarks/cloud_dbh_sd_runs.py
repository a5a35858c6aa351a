"""Benchmark runner: the stated cloud DBH standard deviation, stem by stem, on the real clouds.

Every cloud of ``cloud_real.py`` as shipped (the baseline: default preset, as
``cloud_robustness.py``) and under the transforms of ``cloud_robustness.py`` (its LAS round
trip, its seeds), with, per detected stem: its DBH and stated ``diameter_std``, the fixed ring
reference it pairs with (``_cloud_refs``: diameter, spread over 15 start circles, full or not)
and, for a transform, the baseline stem it pairs with (the benchmark's matching, through the
rigid map back). Where the radius came from the stem's kept slices (the median about breast
height, the slice holding it, the line, or a weighted mean) the inputs of the slices'
variance's parts are recorded too (:func:`stemmap.cloud.dbhsd.dbh_variance`: the path's
stated radius variance, the kept slices' radii, fit variances, weights and heights relative to
the measurement height, the path; every stem measured through its slices, a pre-cut slice's
sub-slices included), read from the call, not changed: the calibration of the term can then
be computed for any value of it from one run (``cloud_dbh_sd.py``). ``sd_cm`` is the std as
the run's config (``--set``) had it.

Prints ONE JSON object. Usage: python benchmarks/cloud_dbh_sd_runs.py [--clouds a,b]
[--transforms t1,t2] [--seed N] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

import stemmap.cloud.slicestem as slicestem
from _cloud_refs import match_stems, reference_of_each
from _datasets import require_datasets_dir
from cloud_real import CLOUDS
from cloud_robustness import TRANSFORMS, run_baseline, set_overrides, transformed_files
from stemmap.cloud.quantisation import QuantisedCoordinatesError
from stemmap.cloud.result import BASE_SLICE, CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems_file

#: refused for every configuration alike (cloud_loo.SKIP)
SKIP = ("utm_ply_float32", "las_scale_10cm")

_CALLS: dict[float, dict[str, Any]] = {}


def _recording(fn: Any) -> Any:
    """``dbh_variance`` that also records its inputs by the variance it returns."""

    def wrapped(var_r, radii, fit_var, hh, path, thickness, scatter, weights=None):  # type: ignore[no-untyped-def]
        out = fn(var_r, radii, fit_var, hh, path, thickness, scatter, weights)
        _CALLS[float(out)] = {
            "var_r": float(var_r),
            "radii": [float(v) for v in radii],
            "fit_var": [float(v) for v in fit_var],
            "hh": [float(v) for v in hh],
            "path": path,
            "thickness": float(thickness),
            "weights": None if weights is None else [float(v) for v in weights],
        }
        return out

    return wrapped


slicestem.dbh_variance = _recording(slicestem.dbh_variance)  # type: ignore[assignment]


def _inputs_of(sd: float) -> dict[str, Any] | None:
    """The recorded inputs of the stem whose stated DBH std is ``sd`` (m), or None (not
    measured from its slices: a pooled or axis fit)."""
    if not np.isfinite(sd):
        return None
    for v, rec in _CALLS.items():
        if np.isfinite(v) and abs(2 * np.sqrt(v) - sd) <= 1e-12 * max(sd, 1e-9):
            return rec
    return None


def _stems(det: CloudStems, refs: list[Any], xy_back: np.ndarray) -> list[dict[str, Any]]:
    rows = []
    hits = reference_of_each(refs, xy_back)
    for i in range(len(det)):
        row: dict[str, Any] = {
            "dbh_cm": 100 * float(det.diameter[i]),
            "sd_cm": 100 * float(det.diameter_std[i]),
            "rule": str(det.dbh_rule[i]),
            "slices": _inputs_of(float(det.diameter_std[i])),
        }
        h = hits[i]
        if h is not None:
            row |= {
                "ring_id": h[0],
                "ring_cm": 100 * h[1].diameter,
                "ring_spread_cm": 100 * h[1].spread,
                "ring_full": bool(h[1].full),
            }
        rows.append(row)
    return rows


def run_cloud(
    key: str, path: Path, names: list[str], tmp: Path, seed: int, overrides: dict[str, Any]
) -> dict[str, Any]:
    cfg = replace(StemConfig(), **overrides)
    _CALLS.clear()
    bl = run_baseline(key, path, cfg)
    base = _stems(bl.det, bl.refs, bl.det.xy)
    out: dict[str, Any] = {"baseline": base, "single": len(bl.det) == 1, "transforms": {}}
    for name, prep, f in transformed_files(bl, names, tmp, seed):
        _CALLS.clear()
        try:
            det = detect_stems_file(f, cfg)
        except QuantisedCoordinatesError:
            continue
        zbh = det.z if det.base != BASE_SLICE else np.full(len(det), np.nan)
        back = prep.back(np.column_stack((det.xy, np.nan_to_num(zbh))))
        rows = _stems(det, bl.refs, back[:, :2])
        for i, j in match_stems(bl.det.xy, bl.det.diameter, back[:, :2]):
            rows[j]["base_index"] = i
        out["transforms"][name] = {"n_points": int(prep.xyz.shape[0]), "stems": rows}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--transforms", default=",".join(t for t in TRANSFORMS if t not in SKIP))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    args = ap.parse_args()
    overrides = set_overrides(args.set)
    root = require_datasets_dir()
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as td:
        clouds = {
            k: run_cloud(
                k, root / CLOUDS[k], args.transforms.split(","), Path(td), args.seed, overrides
            )
            for k in args.clouds.split(",")
        }
    out = {
        "benchmark": "cloud_dbh_sd_runs",
        "seed": args.seed,
        "set": overrides,
        "cpu_s": round(time.process_time() - t0, 1),
        "clouds": clouds,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
