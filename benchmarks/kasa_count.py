"""Where the ``stemmap`` preset is worse than textbook Kasa on the real-geometry benchmark
(issue 11, "never worse than textbook Kasa on any dataset or scanner model").

Reads the JSON of ``python benchmarks/real_geometry.py --loo --vantage 20 --baseline-grid N``
(file or stdin) and compares, per held-out dataset x scanner configuration, textbook Kasa with
either the default (the grid setting that equals the ``stemmap`` preset, which ``N`` must not
exceed: its rows are in ``added_settings``), another setting of ``added_settings``
(``--setting``) or the setting the leave-one-dataset-out choice picked (``--chosen``). A
configuration *loses* on

- recall: a lower recall than Kasa (size: Kasa's minus ours, and that times the visible trunks);
- F1: a lower F1 of recall and precision (only where the slice scores precision);
- RMSE: a larger DBH RMSE at <= 10 m, or no detection within 10 m where Kasa has one;
- recall within 3 cm (like with like, Dec 5): a lower share of the visible trunks found with
  |DBH error| <= 3 cm (the issue's RMSE target; ``recall_3cm`` of ``real_geometry.py``) than
  Kasa's. The literal recall count credits Kasa with every detection within the matching gate
  (radius + 5 cm), whatever its diameter; this one credits both detectors only with the
  trunks they measure within the target (LOO JSON written before Dec 5 lacks it: None).

- fair (Dec 5, "The fair count against textbook Kasa" in scan-detection.md): Kasa is at least
  as good on both sides and better on one (Pareto): a higher recall within 3 cm with no more
  false alarms than ours, or fewer false alarms at a recall within 3 cm no lower. False alarms
  are counted on the configuration's own scans where the slice scores them (per scan:
  detections on no reference trunk, :func:`real_geometry.false_alarms`); where it does not
  (the TreeLS plot, whose reference is incomplete) on the simulator's clutter (``--sim``: each
  detector's mean over the seeds' benchmark drives, :func:`sim_sides`; without ``--sim`` the
  false-alarm side of those rows is unknown and they count on recall within 3 cm alone).
  ``fair_f1_lower`` is the stricter single-number form: the F1 of recall within 3 cm and
  precision (the same sources) lower than Kasa's, which lets no recall go for precision.

Each recall loss is also classed by what Kasa's extra trunks cost (:func:`trade_class`).
Prints one JSON object: the counts, the breakdown by dataset, noise, scanner model and angular
step, and every configuration's row.

Usage::

    python benchmarks/real_geometry.py --loo --vantage 20 --baseline-grid 59 > loo.json
    python benchmarks/kasa_count.py loo.json            # the default (grid 59)
    python benchmarks/kasa_count.py loo.json --setting 67
    python benchmarks/kasa_count.py loo.json --chosen   # the held-out choice
    python benchmarks/kasa_count.py loo.json --sim 1 2 3 4 5 6 7 8 9 10  # both sides, simulated
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

#: The issue's DBH RMSE target at <= 10 m (cm): a Kasa recall bought with larger errors than
#: this, where ours meets it, is a trade of accuracy for recall.
RMSE_TARGET_CM = 3.0


def f1(recall: float | None, precision: float | None) -> float | None:
    """F1 of recall and precision (None where the slice scores no precision)."""
    if recall is None or precision is None:
        return None
    return 2.0 * recall * precision / (recall + precision) if recall + precision > 0 else 0.0


def parse_config(name: str) -> dict[str, Any]:
    """``averaging_0.25deg_noise3cm`` -> model, step (deg), noise (cm)."""
    model, res, noise = name.split("_")
    return {
        "model": model,
        "step_deg": float(res.removesuffix("deg")),
        "noise_cm": float(noise.removeprefix("noise").removesuffix("cm")),
    }


def trade_class(row: dict[str, Any]) -> str:
    """What Kasa's higher recall costs, for a configuration that loses recall:

    - ``precision``: Kasa's F1 is not higher (its extra trunks come with as many false alarms);
    - ``accuracy``: Kasa's F1 is higher (or not scored) but its RMSE at <= 10 m is above the
      3 cm target and above ours (its extra trunks come with errors the target forbids);
    - ``shortfall``: Kasa's F1 is higher (or not scored) and its RMSE is within the target or
      not above ours: Kasa is better on both counts, a real shortfall of ours.
    """
    kf, of = row["kasa_f1"], row["ours_f1"]
    if kf is not None and of is not None and kf <= of:
        return "precision"
    kr, orr = row["kasa_rmse"], row["ours_rmse"]
    if kr is not None and kr > RMSE_TARGET_CM and (orr is None or kr > orr):
        return "accuracy"
    return "shortfall"


def rows(loo: dict[str, Any], chosen: bool, setting: str | None) -> list[dict[str, Any]]:
    """One row per held-out dataset x scanner: ours (default or chosen) next to Kasa."""
    out = []
    for held, t in loo["held_out"].items():
        base = t["held_out"]
        if chosen:
            ours = {
                sc: [
                    r["recall"],
                    r["precision"],
                    r["rmse_cm_le10m"],
                    r.get("recall_3cm"),
                    r.get("false_alarms_per_scan"),
                ]
                for sc, r in base.items()
            }
        else:
            if "added_settings" not in t:
                raise SystemExit(
                    "kasa_count: this LOO JSON holds only the held-out choices; compare them with"
                    " --chosen, or re-run real_geometry.py --loo with --baseline-grid N (N above"
                    " the preset's grid index) to score the preset or --setting"
                )
            added = t["added_settings"]
            key = setting if setting is not None else default_index(loo)
            ours = {
                sc: [*v[:3], *(v[i] if len(v) > i else None for i in (4, 5))]
                for sc, v in added[key].items()
            }
        for sc, r in base.items():
            rec, prec, rmse, rec3, fa = ours[sc]
            row = {
                "dataset": held,
                "config": sc,
                **parse_config(sc),
                "visible": r["visible"],
                "ours_recall": rec,
                "ours_precision": prec,
                "ours_rmse": rmse,
                "kasa_recall": r["textbook_kasa_recall"],
                "kasa_precision": r["textbook_kasa_precision"],
                "kasa_rmse": r["textbook_kasa_rmse_cm_le10m"],
            }
            row["kasa_f1"] = f1(row["kasa_recall"], row["kasa_precision"])
            k3 = r.get("textbook_kasa_recall_3cm")
            row["ours_recall_3cm"], row["kasa_recall_3cm"] = rec3, k3
            row["recall_3cm_loss"] = (
                round(k3 - rec3, 3) if k3 is not None and rec3 is not None and k3 > rec3 else 0.0
            )
            row["recall_3cm_scored"] = k3 is not None and rec3 is not None
            row["ours_false_alarms_per_scan"] = fa
            row["kasa_false_alarms_per_scan"] = r.get("textbook_kasa_false_alarms_per_scan")
            # no detection at all has no precision; where the slice scores it, F1 is 0
            scored = row["kasa_precision"] is not None
            row["ours_f1"] = 0.0 if scored and prec is None and not rec else f1(rec, prec)
            kr, orr = row["kasa_recall"] or 0.0, rec or 0.0
            row["recall_loss"] = round(kr - orr, 3) if kr > orr else 0.0
            row["trunks_lost"] = round((kr - orr) * r["visible"]) if kr > orr else 0
            kf, of = row["kasa_f1"], row["ours_f1"]
            row["f1_loss"] = (
                round(kf - of, 3) if kf is not None and of is not None and kf > of else 0.0
            )
            ke, oe = row["kasa_rmse"], row["ours_rmse"]
            row["rmse_loss"] = ke is not None and (oe is None or oe > ke)
            row["no_detection"] = ke is not None and oe is None
            row["rmse_excess_cm"] = (
                round(oe - ke, 2) if ke is not None and oe is not None and oe > ke else 0.0
            )
            if row["recall_loss"] > 0:
                row["trade"] = trade_class(row)
            out.append(row)
    return out


def fair_sides(row: dict[str, Any], sim: dict[str, Any] | None) -> None:
    """The fair count's two sides of one configuration (module docstring), set on ``row``:
    each detector's false alarms (``*_false_alarms_fair``: per scan on the row's own scans
    where the slice scores them, else per simulated benchmark drive from ``sim``
    (:func:`sim_sides`), else None; ``precision_from`` says which) and precision
    (``*_precision_fair``, the same sources; a detector that found nothing has no false
    alarm: precision 1 for the F1); ``fair_lower`` (Kasa measures more within 3 cm with no
    more false alarms, or as many with fewer) and the F1 of recall within 3 cm and that
    precision (``*_f1_3cm``, ``fair_f1_lower``)."""
    r_o, r_k = row["ours_recall_3cm"], row["kasa_recall_3cm"]
    p_o, p_k = row["ours_precision"], row["kasa_precision"]
    fa_o, fa_k = row["ours_false_alarms_per_scan"], row["kasa_false_alarms_per_scan"]
    src = "scans"
    if p_k is None and fa_k is None:  # the slice scores no precision (the TreeLS plot)
        p_o = p_k = fa_o = fa_k = None
        src = "none"
        if sim is not None:
            o, k = sim["ours"], sim["kasa"]
            p_o, p_k = o["precision_mean"], k["precision_mean"]
            fa_o, fa_k, src = o["benchmark_fa_mean"], k["benchmark_fa_mean"], "sim"
    elif p_o is None:  # ours detected nothing on a slice that scores precision
        p_o = 1.0
    row["ours_precision_fair"], row["kasa_precision_fair"] = p_o, p_k
    row["ours_false_alarms_fair"], row["kasa_false_alarms_fair"] = fa_o, fa_k
    row["precision_from"] = src
    row["kasa_extra_3cm_views"] = 0
    if r_o is None or r_k is None:
        row["fair_lower"] = row["fair_f1_lower"] = False
        row["ours_f1_3cm"] = row["kasa_f1_3cm"] = None
        return
    if fa_o is None or fa_k is None:
        row["fair_lower"] = r_k > r_o
    else:
        row["fair_lower"] = (r_k > r_o and fa_k <= fa_o) or (fa_k < fa_o and r_k >= r_o)
    row["ours_f1_3cm"], row["kasa_f1_3cm"] = f1(r_o, p_o), f1(r_k, p_k)
    fo, fk = row["ours_f1_3cm"], row["kasa_f1_3cm"]
    row["fair_f1_lower"] = fo is not None and fk is not None and fk > fo + 1e-9
    # Kasa's extra views within 3 cm, where it has more (whatever its false alarms)
    row["kasa_extra_3cm_views"] = round(max(r_k - r_o, 0.0) * row["visible"])


def sim_sides(seeds: list[int], overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Both detectors on the simulator's clutter (``_scan_sim``: ``scan_detection.py``'s
    400-scan benchmark drive with bushes, branches, walls, fences and rocks, and the ``stemmap
    demo`` drive; each seed a new stand): the ``stemmap`` preset (with ``overrides``) and
    textbook Kasa (:data:`_real_scanning.TEXTBOOK`), per seed and drive recall, precision,
    true and false alarms, and on the benchmark drive the DBH RMSE at <= 5 m and the recall
    within 3 cm (eligible trees found with |DBH error| <= 3 cm, :func:`_scan_sim.tree_errors`);
    the mean precision and recall of each over the seeds' benchmark drives (the fair count's
    precision where a real slice scores none)."""
    import numpy as np

    from _real_scanning import TEXTBOOK
    from _scan_sim import _runs, score, tree_errors
    from stemmap.cli._demo import demo_detection_metrics
    from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

    dets = {
        "ours": DetectorConfig.preset("stemmap", **(overrides or {})),
        "kasa": TEXTBOOK,
    }
    out: dict[str, Any] = {"seeds": seeds}
    for name, cfg in dets.items():
        det = ScanTrunkDetector(cfg)
        per = []
        for seed in seeds:
            run, demo_run = _runs(int(seed))
            obs = det.detect_batch(run.scans)
            b = score(obs, run)
            err = tree_errors(obs, run)["error"]
            elig = b["ta"] + b["fr"]
            dm = demo_detection_metrics(det.detect_batch(demo_run.scans), demo_run)
            per.append(
                {
                    "seed": int(seed),
                    "benchmark": {
                        k: b[k] for k in ("recall", "precision", "ta", "fa", "dbh_rmse_cm_le5")
                    }
                    | {
                        "recall_3cm": round(
                            float(np.sum(np.abs(err) <= RMSE_TARGET_CM / 100.0)) / elig, 4
                        )
                        if elig
                        else None
                    },
                    "demo": {
                        "recall": round(dm.recall, 4),
                        "precision": round(dm.precision, 4),
                        "ta": dm.ta,
                        "fa": dm.fa,
                    },
                }
            )
        summ: dict[str, Any] = {"per_seed": per}
        for drive in ("benchmark", "demo"):
            for k in ("precision", "recall", "fa", "ta"):
                v = [float(p[drive][k]) for p in per]
                summ[f"{drive}_{k}_mean"] = round(float(np.mean(v)), 4)
        r3 = [p["benchmark"]["recall_3cm"] for p in per if p["benchmark"]["recall_3cm"] is not None]
        summ["benchmark_recall_3cm_mean"] = round(float(np.mean(r3)), 4) if r3 else None
        summ["precision_mean"] = summ["benchmark_precision_mean"]
        out[name] = summ
    return out


def default_index(loo: dict[str, Any]) -> str:
    """Index (as ``added_settings`` keys it) of the grid setting that equals the ``stemmap``
    preset."""
    from stemmap.scan.detect import DetectorConfig

    preset = DetectorConfig.preset("stemmap")
    for g, setting in enumerate(loo["scenario"]["grid"]):
        if DetectorConfig.preset("stemmap", **setting) == preset:
            return str(g)
    raise SystemExit("no grid setting equals the stemmap preset")


def compared_label(loo: dict[str, Any], chosen: bool, setting: str | None) -> str:
    """What the output's ``ours`` side is: the held-out choices, a named grid setting, or the
    preset's grid setting."""
    if chosen:
        return "chosen"
    if setting is not None:
        return f"grid {setting}"
    return f"default (grid {default_index(loo)})"


def tally(rs: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts and sizes of the losses over ``rs``."""
    rec = [r for r in rs if r["recall_loss"] > 0]
    f1s = [r for r in rs if r["ours_f1"] is not None]
    f1l = [r for r in f1s if r["f1_loss"] > 0]
    rml = [r for r in rs if r["rmse_loss"]]
    trades: dict[str, int] = defaultdict(int)
    for r in rec:
        trades[r["trade"]] += 1
    return {
        "configs": len(rs),
        "recall_lower": len(rec),
        "recall_loss_median": _median([r["recall_loss"] for r in rec]),
        "recall_loss_max": max((r["recall_loss"] for r in rec), default=None),
        "trunks_lost": sum(r["trunks_lost"] for r in rec),
        "recall_lower_by_001_or_less": sum(r["recall_loss"] <= 0.01 for r in rec),
        "f1_scored": len(f1s),
        "f1_lower": len(f1l),
        "f1_loss_median": _median([r["f1_loss"] for r in f1l]),
        "rmse_larger_or_none": len(rml),
        "no_detection": sum(r["no_detection"] for r in rml),
        "rmse_excess_median_cm": _median(
            [r["rmse_excess_cm"] for r in rml if not r["no_detection"]]
        ),
        "recall_loss_trade": dict(trades),
        "recall_3cm_scored": sum(r["recall_3cm_scored"] for r in rs),
        "recall_3cm_lower": sum(r["recall_3cm_loss"] > 0 for r in rs),
        "recall_3cm_trunks_lost": sum(
            round(r["recall_3cm_loss"] * r["visible"]) for r in rs if r["recall_3cm_loss"] > 0
        ),
        # the fair count (module docstring): Kasa better on one side, not worse on the other
        "fair_lower": sum(bool(r.get("fair_lower")) for r in rs),
        "fair_lower_views": sum(
            r.get("kasa_extra_3cm_views", 0) for r in rs if r.get("fair_lower")
        ),
        "fair_lower_by_precision_source": dict(
            Counter(r["precision_from"] for r in rs if r.get("fair_lower"))
        ),
        "fair_f1_lower": sum(bool(r.get("fair_f1_lower")) for r in rs),
        # the other side: where Kasa measures more within 3 cm, does it pay in false alarms?
        "kasa_more_3cm_lower_precision": sum(
            r["recall_3cm_loss"] > 0
            and r.get("kasa_precision_fair") is not None
            and r["kasa_precision_fair"] < (r.get("ours_precision_fair") or 0.0)
            for r in rs
        ),
    }


def _median(v: list[float]) -> float | None:
    if not v:
        return None
    s = sorted(v)
    m = len(s) // 2
    return round(s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m]), 3)


def breakdown(rs: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`tally` overall and by dataset, noise, scanner model, step and model x noise."""
    by: dict[str, Any] = {"all": tally(rs)}
    keys = {
        "dataset": lambda r: r["dataset"],
        "noise_cm": lambda r: f"{r['noise_cm']:g}",
        "model": lambda r: r["model"],
        "step_deg": lambda r: f"{r['step_deg']:g}",
        "model_noise": lambda r: f"{r['model']} {r['noise_cm']:g}cm",
    }
    for name, key in keys.items():
        groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for r in rs:
            groups[key(r)].append(r)
        by[name] = {k: tally(v) for k, v in groups.items()}
    return by


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("loo_json", nargs="?", default="-", help="real_geometry.py --loo output")
    ap.add_argument("--chosen", action="store_true", help="the held-out choice, not the default")
    ap.add_argument(
        "--setting", default=None, help="grid index in added_settings (default: the preset's)"
    )
    ap.add_argument(
        "--sim",
        type=int,
        nargs="*",
        default=None,
        help="seeds of the simulator's clutter drives for both detectors' precision where the"
        " slice scores none (the TreeLS plot), and their simulated sides in the output",
    )
    ap.add_argument(
        "--sim-set",
        type=json.loads,
        default=None,
        help="--sim: preset overrides of ours on the simulator (default: the compared"
        " setting's grid point with --setting, else the preset)",
    )
    ap.add_argument(
        "--sim-json",
        type=Path,
        default=None,
        help="the simulated sides from a file instead of --sim (the 'simulated' object of an"
        " earlier run, or sim_sides' own JSON)",
    )
    args = ap.parse_args(argv)
    if args.loo_json == "-":
        text = sys.stdin.read()
    else:
        with open(args.loo_json) as fh:
            text = fh.read()
    loo = json.loads(text)
    rs = rows(loo, args.chosen, args.setting)
    sim = None
    if args.sim_json is not None:
        sim = json.loads(args.sim_json.read_text())
        sim = sim.get("simulated", sim)
    elif args.sim:
        over = args.sim_set
        if over is None and args.setting is not None:
            over = loo["scenario"]["grid"][int(args.setting)]
        sim = sim_sides(args.sim, over)
    for r in rs:
        fair_sides(r, sim)
    out: dict[str, Any] = {"compared": compared_label(loo, args.chosen, args.setting)}
    if sim is not None:
        out["simulated"] = {
            k: (v if k == "seeds" else {x: y for x, y in v.items() if x != "per_seed"})
            for k, v in sim.items()
        }
        out["simulated_per_seed"] = {
            k: v["per_seed"] for k, v in sim.items() if k != "seeds" and "per_seed" in v
        }
    print(json.dumps({**out, **breakdown(rs), "rows": rs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
