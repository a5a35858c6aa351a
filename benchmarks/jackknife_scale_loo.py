"""The factor of ``dbh_sd_jackknife`` chosen leave one dataset out (issue 11, Dec 6, "Junction
merges on lidR" in docs/algorithms/scan-detection.md).

Reads two row files of ``first_echo_dbh_z.py --rows-out`` over the same views: the preset's
(``BASE``: its std is ``sqrt(s_k^2 + b0^2)``, ``b0`` the preset's outline term) and the plain
jackknife's (``JACK``: ``--set '{"dbh_sd_jackknife": 1.0, "dbh_sd_outline": 0}'``, whose std is
``max(s_k, s_J)``), recovers per view the fit's scaled std ``s_k`` and, where the plain
jackknife exceeded it, the jackknife std ``s_J``, and for the form
``max(sqrt(s_k^2 + b^2), c s_J)`` chooses ``c`` in [0, 1] by the rule of "First-echo DBH
standard error": the pooled median |z| of the *other* real-bark datasets (TreeLS plot, TreeLS
pine, lidR; FORTLS's synthetic circles and aRchi's untrusted reference never train) equals
0.674. Reports per held-out dataset and noise level the median |z| and its 90th percentile.

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/jackknife_scale_loo.py base.json jack1.json --b 0
    ... the same with --b 0.013 (the preset's outline term kept)

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

BARK = ("treels_pine_plot", "treels_pine", "lidr_dbh")
REPORT = (*BARK, "fortls_slice", "archi_tree1")


def views(base: list[dict], jack: list[dict], b0: float) -> list[dict[str, Any]]:
    """Per view: dataset, noise, error, the fit's scaled std and the jackknife std (0 where
    the plain jackknife did not exceed the fit's std)."""
    if len(base) != len(jack):
        raise SystemExit("the two row files hold different views")
    out = []
    for a, j in zip(base, jack, strict=True):
        if (a["dataset"], a["scan"], a["step"], a["noise"]) != (
            j["dataset"],
            j["scan"],
            j["step"],
            j["noise"],
        ) or abs(a["err"] - j["err"]) > 1e-12:
            raise SystemExit("the two row files hold different detections")
        s_k = float(np.sqrt(max(a["sd"] ** 2 - b0 * b0, 0.0)))
        s_j = j["sd"] if j["sd"] > s_k * (1.0 + 1e-9) else 0.0
        out.append({"ds": a["dataset"], "noise": a["noise"], "err": a["err"], "sk": s_k, "sj": s_j})
    return out


def std(r: dict[str, Any], b: float, c: float) -> float:
    return max(float(np.hypot(r["sk"], b)), c * r["sj"])


def median_z(rows: list[dict[str, Any]], b: float, c: float) -> float:
    return float(np.median([abs(r["err"]) / std(r, b, c) for r in rows]))


def choose_c(train: list[dict[str, Any]], b: float, target: float = 0.674) -> float:
    """The ``c`` in [0, 1] whose pooled median |z| on ``train`` is ``target`` (bisection; 0
    when even ``c`` = 0 is below it, 1 when even ``c`` = 1 is above)."""
    lo, hi = 0.0, 1.0
    if median_z(train, b, lo) <= target:
        return 0.0
    if median_z(train, b, hi) >= target:
        return 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if median_z(train, b, mid) > target else (lo, mid)
    return 0.5 * (lo + hi)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("base", type=Path)
    ap.add_argument("jack", type=Path)
    ap.add_argument("--b0", type=float, default=0.013, help="the BASE rows' outline term (m)")
    ap.add_argument("--b", type=float, default=0.0, help="the outline term kept (m)")
    args = ap.parse_args(argv)
    rows = views(json.loads(args.base.read_text()), json.loads(args.jack.read_text()), args.b0)
    out: dict[str, Any] = {"benchmark": "jackknife_scale_loo", "b": args.b, "held_out": {}}
    for held in REPORT:
        c = choose_c([r for r in rows if r["ds"] in BARK and r["ds"] != held], args.b)
        cells = {}
        for noise in (0.0, 0.01, 0.03):
            q = [r for r in rows if r["ds"] == held and r["noise"] == noise]
            z = [abs(r["err"]) / std(r, args.b, c) for r in q]
            if z:
                cells[f"{100 * noise:g}cm"] = {
                    "n": len(z),
                    "med_z": round(float(np.median(z)), 2),
                    "p90_z": round(float(np.quantile(z, 0.9)), 2),
                }
        out["held_out"][held] = {"c": round(c, 3), **cells}
    out["c_all_three"] = round(choose_c([r for r in rows if r["ds"] in BARK], args.b), 3)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
