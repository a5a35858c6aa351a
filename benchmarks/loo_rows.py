"""Which training rows make a leave-one-dataset-out fold prefer one grid setting over another
(issue 11, Dec 5, "The LOO by scanner family" in docs/algorithms/scan-detection.md).

Reads the JSON of ``real_geometry.py --loo`` (its ``grid_score_by_dataset_scanner``: the
objective of every setting per dataset x scanner row) and, for the fold that holds ``--held``
out, lists per training dataset and row the objectives of settings ``A`` and ``B`` and their
difference, then the mean difference by scanner family, by noise level and by family x noise
(the training score is the pooled mean over training datasets x rows with a visible trunk, so
a group's share of the score difference is its sum of differences over the pooled count).

Usage::

    python benchmarks/real_geometry.py --loo --vantage 20 --by-scanner > loo.json
    python benchmarks/loo_rows.py loo.json --held lidr_dbh 72 80

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

from _loo_choice import family_of

_NOISE = re.compile(r"noise([0-9.]+)cm")


def compare(loo: dict[str, Any], held: str, a: int, b: int) -> dict[str, Any]:
    """Settings ``a`` against ``b`` in the fold holding ``held`` out, row by row (see the
    module docstring); ``share_of_difference``: each group's part of the training score's
    difference ``score(a) - score(b)`` (the groups of one key add up to it)."""
    by_row = loo["grid_score_by_dataset_scanner"]
    train = [n for n in loo["training_datasets"] if n != held]
    rows: list[dict[str, Any]] = []
    for n in train:
        for row, vals in by_row[n].items():
            if vals[a] is None or vals[b] is None:
                continue  # no visible trunk: the row never trains
            rows.append(
                {
                    "dataset": n,
                    "row": row,
                    "family": family_of(row),
                    "noise_cm": float(_NOISE.search(row).group(1)),  # type: ignore[union-attr]
                    "a": vals[a],
                    "b": vals[b],
                    "a_minus_b": round(vals[a] - vals[b], 3),
                }
            )
    total = len(rows)

    def groups(key: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for r in rows:
            g = out.setdefault(str(key(r)), {"rows": 0, "sum": 0.0})
            g["rows"] += 1
            g["sum"] += r["a_minus_b"]
        return {
            k: {
                "rows": v["rows"],
                "mean_a_minus_b": round(v["sum"] / v["rows"], 3),
                "share_of_difference": round(v["sum"] / total, 3),
            }
            for k, v in sorted(out.items())
        }

    return {
        "held_out": held,
        "training_datasets": train,
        "a": a,
        "b": b,
        "score_difference": round(sum(r["a_minus_b"] for r in rows) / total, 3) if total else None,
        "by_family": groups(lambda r: r["family"]),
        "by_noise_cm": groups(lambda r: r["noise_cm"]),
        "by_family_noise": groups(lambda r: f"{r['family']} {r['noise_cm']:g} cm"),
        "by_dataset_family": groups(lambda r: f"{r['dataset']} {r['family']}"),
        "rows": sorted(rows, key=lambda r: r["a_minus_b"], reverse=True),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("loo", type=Path, help="JSON of real_geometry.py --loo")
    ap.add_argument("--held", required=True, help="the fold: the dataset held out")
    ap.add_argument("a", type=int, help="grid setting A (its LOO_GRID index)")
    ap.add_argument("b", type=int, help="grid setting B")
    args = ap.parse_args(argv)
    loo = json.loads(args.loo.read_text())
    print(json.dumps(compare(loo, args.held, args.a, args.b)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
