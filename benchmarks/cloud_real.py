"""Benchmark: every real cloud in ../shared/datasets through ``detect_stems_file`` (preset ours,
heights on), each stem against the fixed reference circle of the cloud's own ring at breast
height that it pairs with (``_cloud_refs``: converged from 15 start circles about a committed
seed, never from the detector; with its RMS, arc and spread over the starts), the tree height
against the cloud's top above the stem's base, and the stem profile's reach.

Prints ONE JSON object. Usage: python benchmarks/cloud_real.py [--set key=value ...] (a
StemConfig option, as cloud_robustness.py)
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from typing import Any

import numpy as np

from _cloud_refs import CLOUDS, fixed_references, load_seeds, reference_of_each
from _datasets import require_datasets_dir
from stemmap.cloud.result import BASE_SLICE
from stemmap.cloud.stems import StemConfig, detect_stems_file
from stemmap.io.clouds import read_cloud
from stemmap.products.forestry import stem_profiles, stem_volume

__all__ = ["CLOUDS", "run_one"]  # CLOUDS: the clouds measured (cloud_robustness.py uses them)


def _r(v: float, nd: int = 4) -> float | None:
    return round(float(v), nd) if np.isfinite(v) else None


def run_one(path: str, key: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    xyz = read_cloud(path).xyz
    refs = fixed_references(xyz, load_seeds()[key])
    t0 = time.perf_counter()
    det = detect_stems_file(path, replace(StemConfig(), estimate_height=True, **(overrides or {})))
    dt = time.perf_counter() - t0
    profs = stem_profiles(xyz, det) if det.base != BASE_SLICE else []
    stems = []
    errs_full = []
    paired = reference_of_each(refs, det.xy)
    for i, hit in enumerate(paired):
        base_z = float(det.z[i] - det.dbh_height[i])
        row: dict[str, Any] = {
            "x": _r(det.xy[i, 0], 3),
            "y": _r(det.xy[i, 1], 3),
            "dbh_cm": _r(100 * det.diameter[i], 2),
            "dbh_std_cm": _r(100 * det.diameter_std[i], 3),
            "dbh_height_m": _r(det.dbh_height[i], 2),
            "dbh_rule": str(det.dbh_rule[i]),
        }
        if hit is not None:
            k, ref = hit
            row |= {
                "ring_id": k,
                "ring_dbh_cm": _r(100 * ref.diameter, 2),
                "ring_spread_cm": _r(100 * ref.spread, 2),
                "ring_rms_cm": _r(100 * ref.rms, 2),
                "ring_arc_deg": _r(ref.arc_deg, 0),
                "ring_points": ref.n,
                "ring_full": ref.full,
                "err_cm": _r(100 * (det.diameter[i] - ref.diameter), 2),
            }
            if ref.full:
                errs_full.append(det.diameter[i] - ref.diameter)
        if det.base != BASE_SLICE:
            near = np.hypot(*(xyz[:, :2] - det.xy[i]).T) <= 1.0
            row["height_m"] = _r(det.height[i], 2)
            row["top_above_base_m"] = _r(float(xyz[near, 2].max()) - base_z, 2)
            pr = profs[i]
            vol, to_h = stem_volume(pr, float(det.height[i]))
            row["profile_levels"] = int(pr.height.size)
            row["profile_to_m"] = _r(to_h, 1)
            row["volume_m3"] = _r(vol, 4)
        stems.append(row)
    e = np.asarray(errs_full)
    used = {h[0] for h in paired if h is not None}
    return {
        "file": path,
        "n_points": int(xyz.shape[0]),
        "n_stems": len(det),
        "base": det.base,
        "reason": det.reason,
        "time_s": round(dt, 3),
        "full_ring_stems": int(e.size),
        "dbh_rmse_vs_full_rings_cm": _r(100 * float(np.sqrt(np.mean(e**2))), 2) if e.size else None,
        "dbh_bias_vs_full_rings_cm": _r(100 * float(np.mean(e)), 2) if e.size else None,
        "references": len(refs),
        "references_unpaired": [
            {"ring_id": k, "ring_dbh_cm": _r(100 * r.diameter, 2), "ring_full": r.full}
            for k, r in enumerate(refs)
            if r is not None and k not in used
        ],
        "stems": stems,
    }


def main() -> None:
    import argparse

    from cloud_robustness import set_overrides

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    overrides = set_overrides(ap.parse_args().set)
    root = require_datasets_dir()
    out = {
        "benchmark": "cloud_real",
        "note": "ring references share the points with the detector, not its machinery nor "
        "its stems (fixed seeds, benchmarks/_cloud_ring_seeds.json); ring_spread_cm = range "
        "of the ring fits from 15 start circles; times from a loaded shared machine",
        "set": overrides,
        "clouds": {k: run_one(str(root / v), k, overrides) for k, v in CLOUDS.items()},
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
