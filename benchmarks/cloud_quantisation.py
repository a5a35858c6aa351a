"""Benchmark: how coarse may a cloud's coordinates be before stem diameters go wrong?

Every real cloud of ``cloud_real.py`` written to LAS at a scale factor of q (0.5-10 cm: every
coordinate rounded to q, as a coarse LAS export or float32 at map-sized values would leave
it), read back and measured by ``detect_stems_file`` (preset ours) with the quantisation
refusal off (``max_coordinate_step=None``), scored as ``cloud_robustness.py`` scores a
transform (against the shipped cloud's run and the fixed ring references; ``fails`` = the
issue-11 targets missed). The bound ``stemmap.cloud.quantisation.MAX_COORDINATE_STEP`` rests
on this table (docs/algorithms/cloud.md "Coordinate quantisation").

Prints ONE JSON object. Usage: python benchmarks/cloud_quantisation.py [--clouds a,b]
[--steps 0.005,0.01,...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cloud_robustness as cr
from _datasets import require_datasets_dir
from stemmap.cloud.stems import StemConfig, detect_stems_file

STEPS = (0.005, 0.01, 0.015, 0.02, 0.03, 0.05, 0.1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clouds", default=",".join(cr.CLOUDS))
    ap.add_argument("--steps", default=",".join(map(str, STEPS)))
    args = ap.parse_args()
    root = require_datasets_dir()
    steps = [float(s) for s in args.steps.split(",")]
    cfg = replace(StemConfig(), max_coordinate_step=None)
    t0 = time.process_time()
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as td:
        for key in args.clouds.split(","):
            bl = cr.run_baseline(key, root / cr.CLOUDS[key])
            rows: dict[str, Any] = {}
            for q in steps:
                prep = cr.Prepared(bl.xyz, scale=q)
                f = Path(td) / f"{key}_{q}.las"
                cr.write_las(f, prep.xyz, q, 1.0)
                row = cr.score_run(f"q{q}", bl, detect_stems_file(f, cfg), prep)
                f.unlink()
                keep = ("n_stems", "matched", "dbh_change_max_cm", "dbh_vs_ring_rmse_cm", "fails")
                rows[f"{q:g}"] = {k: row[k] for k in keep}
            out[key] = rows
    print(
        json.dumps(
            {
                "benchmark": "cloud_quantisation",
                "note": "each real cloud in a LAS at scale q, refusal off; changes against the "
                "shipped run, ring = fixed ring references (cloud_robustness scoring)",
                "cpu_s": round(time.process_time() - t0, 1),
                "clouds": out,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
