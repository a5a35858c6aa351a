"""Fold by fold, why the leave-one-dataset-out choice takes or leaves a setting (issue 11, Dec 4,
"step split, fold by fold").

Same slices, vantage points, seeds and scanner configurations as ``benchmarks/real_geometry.py
--loo`` (seed 11 + the dataset's index in :data:`stemmap.eval.real_slices.SLICES`, every
configuration of ``FULL_SCANNERS``), but only a few settings: ``--grid`` indices of
:data:`_loo_grid.LOO_GRID` and ``--set`` overrides of the ``stemmap`` preset (each one more
setting, named ``set0``, ``set1``, ...). Per dataset and scanner configuration the row of each
setting (recall, precision, RMSE / bias cm at <= 10 m, the LOO objective) and, per held-out
dataset, each setting's training score (mean objective over the trusted training datasets x
scanners, exactly as the LOO) and how much each training dataset and configuration moves it
against the first setting (``--grid`` first: the reference, e.g. the default 36).

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    python benchmarks/real_geometry_folds.py --grid 36 40 --vantage 20
    python benchmarks/real_geometry_folds.py --grid 36 --set '{"step_split": true}'

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _loo_grid import LOO_GRID
from _real_scanning import ANY_HIT, FULL_SCANNERS, ReturnRule, add_hit_fraction
from real_geometry import _objective, reference_trusted, run_dataset
from stemmap.eval.real_slices import SLICES, load_slice
from stemmap.scan.detect import DetectorConfig


def _row(r: dict[str, Any]) -> list[Any]:
    """recall, precision, RMSE cm <= 10 m, bias cm <= 10 m, objective."""
    return [
        r["all"]["recall"],
        r["all"]["precision"],
        r["within_10m"]["rmse_cm"],
        r["within_10m"]["bias_cm"],
        round(_objective(r), 3),
    ]


def folds(
    ddir: Path,
    settings: dict[str, dict[str, Any]],
    names: list[str],
    n_vantage: int,
    seed: int,
    min_returns: int = 4,
    return_rule: ReturnRule = ANY_HIT,
) -> dict[str, Any]:
    """Per dataset x scanner the rows of every setting, per held-out dataset the training
    scores and the per-dataset / per-configuration changes against the first setting."""
    per: dict[str, dict[str, dict[str, Any]]] = {}
    trusted: dict[str, bool] = {}
    order = list(SLICES)
    for name in names:
        sl = load_slice(ddir, name)
        if not sl.refs:
            continue
        trusted[name] = reference_trusted(sl)[0]
        dets = {k: DetectorConfig.preset("stemmap", **v) for k, v in settings.items()}
        per[name] = run_dataset(
            sl,
            FULL_SCANNERS,
            dets,
            n_vantage=n_vantage,
            min_returns=min_returns,
            seed=seed + order.index(name),
            return_rule=return_rule,
        )
    keys = list(settings)
    ref = keys[0]
    scored = [n for n in per if any(c[ref]["all"]["visible"] for c in per[n].values())]
    trains = [n for n in scored if trusted[n]]

    def obj(n: str, k: str) -> list[float]:
        return [_objective(c[k]) for c in per[n].values() if c[k]["all"]["visible"]]

    table = {}
    for held in scored:
        train = [n for n in trains if n != held]
        table[held] = {
            "train": train,
            "score": {
                k: round(float(np.mean([v for n in train for v in obj(n, k)])), 3) for k in keys
            },
            # each training dataset's share of the change (its sum over configurations / the
            # number of training rows): the shares add up to the change of the score
            "change_by_dataset": {
                k: {
                    n: round(
                        (sum(obj(n, k)) - sum(obj(n, ref))) / sum(len(obj(m, ref)) for m in train),
                        4,
                    )
                    for n in train
                }
                for k in keys[1:]
            },
        }
    rows = {
        n: {
            sc: {k: _row(c[k]) for k in keys}
            for sc, c in per[n].items()
            if any(_row(c[k])[:4] != _row(c[ref])[:4] for k in keys)
        }
        for n in per
    }
    return {
        "trusted": trusted,
        "by_dataset_mean_objective": {
            n: {k: round(float(np.mean(obj(n, k))), 3) for k in keys} for n in scored
        },
        "folds": table,
        "changed_rows": rows,
        "row": "recall, precision, RMSE cm <= 10 m, bias cm <= 10 m, objective",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", type=Path, default=None)
    ap.add_argument("--grid", type=int, nargs="*", default=[36], help="LOO_GRID indices")
    ap.add_argument("--set", type=json.loads, action="append", default=[])
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--vantage", type=int, default=20)
    ap.add_argument("--seed", type=int, default=11)
    add_hit_fraction(ap, ANY_HIT)
    args = ap.parse_args(argv)
    ddir = require_datasets_dir(args.datasets)
    settings = {f"grid{g}": LOO_GRID[g] for g in args.grid}
    base = LOO_GRID[args.grid[0]] if args.grid else {}
    settings |= {f"set{i}": {**base, **s} for i, s in enumerate(args.set)}
    t0 = time.perf_counter()
    rule = ReturnRule(args.hit_fraction)
    out = folds(
        ddir, settings, args.only or list(SLICES), args.vantage, args.seed, return_rule=rule
    )
    out["settings"] = {k: str(v) for k, v in settings.items()}
    out["set_on_top_of"] = f"grid{args.grid[0]}" if args.grid else "the stemmap preset"
    out["runtime_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
