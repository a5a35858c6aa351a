"""Benchmark: one StemConfig option against the default, cell by cell and stem by stem.

Each cell of ``cloud_robustness.py`` (cloud x transform; the random transforms -- subsamples,
noise -- with every seed of ``--seeds``; the two refused exports left out, as in
``cloud_loo.py``) goes through the benchmark's LAS round trip once with the default
configuration and once with the ``--set`` overrides, both scored by
``cloud_robustness.score_run`` against the shipped cloud's stems and the fixed ring
references. Per cell where anything differs: the scores of both runs (``fails``, full-ring
DBH RMSE, extra and matched stems) and every stem that is not bit-identical in both runs --
``added`` (only with the option), ``dropped`` (only without), each with its DBH, stated std,
``dbh_rule``, the baseline stem it pairs with (within half its diameter + 10 cm), that
stem's shipped DBH and its fixed ring (``ring_full``). ``cells_changed`` counts them;
``detect_cpu_s`` is the detection CPU per configuration.

    PYTHONPATH=src:benchmarks python benchmarks/cloud_option_cells.py --set sparse_tall_fit=true \\
        [--clouds a,b] [--transforms t1,t2] [--seeds 0,1,2,3,4]
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

import cloud_robustness as cr
from _cloud_refs import reference_of_each
from _datasets import require_datasets_dir
from cloud_loo import RANDOM, SKIP
from cloud_real import CLOUDS
from stemmap.cloud.result import CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems_file

KEYS = ("fails", "dbh_vs_ring_rmse_cm", "extra", "matched")


def _only_in(a: CloudStems, b: CloudStems) -> list[int]:
    """Indices of ``a``'s stems with no bit-identical stem (centre, DBH) in ``b``."""
    out = []
    for j in range(len(a)):
        same = len(b) and np.any(np.all(b.xy == a.xy[j], axis=1) & (b.diameter == a.diameter[j]))
        if not same:
            out.append(j)
    return out


def _stem(
    bl: cr.Baseline, refs: list[Any], det: CloudStems, j: int, prep: cr.Prepared
) -> dict[str, Any]:
    """One detection: DBH, std, rule, and the baseline stem (and ring) it pairs with."""
    xy = prep.back(np.array([[*det.xy[j], 0.0]]))[0, :2]
    d = np.hypot(*(bl.det.xy - xy).T) if len(bl.det) else np.array([np.inf])
    i = int(np.argmin(d))
    paired = bool(d[i] <= bl.det.diameter[i] / 2 + 0.1)
    ring = refs[i][1] if paired and refs[i] is not None else None
    return {
        "xy": [round(float(v), 2) for v in xy],
        "dbh_cm": round(100 * float(det.diameter[j]), 2),
        "std_cm": round(100 * float(det.diameter_std[j]), 2),
        "rule": str(det.dbh_rule[j]),
        "baseline_stem": i if paired else None,
        "shipped_dbh_cm": round(100 * float(bl.det.diameter[i]), 2) if paired else None,
        "ring_cm": None if ring is None else round(100 * ring.diameter, 2),
        "ring_full": None if ring is None else ring.full,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--transforms", default=",".join(t for t in cr.TRANSFORMS if t not in SKIP))
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--set", action="append", default=[], required=True)
    args = ap.parse_args()
    root = require_datasets_dir()
    cfgs = {"default": StemConfig(), "option": replace(StemConfig(), **cr.set_overrides(args.set))}
    cpu = dict.fromkeys(cfgs, 0.0)
    seeds = [int(s) for s in args.seeds.split(",")]
    names = args.transforms.split(",")
    cells, n_cells = [], 0
    with tempfile.TemporaryDirectory() as tmp:
        for cloud in args.clouds.split(","):
            bl = cr.run_baseline(cloud, root / CLOUDS[cloud])
            refs = reference_of_each(bl.refs, bl.det.xy)
            for name in names:
                for seed in seeds if name in RANDOM else seeds[:1]:
                    for _, prep, f in cr.transformed_files(bl, [name], Path(tmp), seed):
                        n_cells += 1
                        det, row = {}, {}
                        for lab, cfg in cfgs.items():
                            t0 = time.process_time()
                            det[lab] = detect_stems_file(f, cfg)
                            cpu[lab] += time.process_time() - t0
                            row[lab] = cr.score_run(name, bl, det[lab], prep)
                        a, b = det["default"], det["option"]
                        added, dropped = _only_in(b, a), _only_in(a, b)
                        scores = {lab: {k: row[lab].get(k) for k in KEYS} for lab in cfgs}
                        if added or dropped or scores["default"] != scores["option"]:
                            cells.append(
                                {
                                    "cell": f"{cloud}/{name}/{seed}",
                                    **scores,
                                    "added": [_stem(bl, refs, b, j, prep) for j in added],
                                    "dropped": [_stem(bl, refs, a, j, prep) for j in dropped],
                                }
                            )
    print(
        json.dumps(
            {
                "benchmark": "cloud_option_cells",
                "set": args.set,
                "cells": n_cells,
                "cells_changed": len(cells),
                "detect_cpu_s": {k: round(v, 1) for k, v in cpu.items()},
                "changed": cells,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
