"""The leave-one-dataset-out choice of ``real_geometry.py --loo`` (issue 11): which datasets
may train (:func:`reference_trusted`), the training objective of one dataset x scanner row, the
training score of a grid setting, the best admitted setting, its held-out rows, and
(``--by-scanner``, Dec 5) the same choice made separately per scanner family -- the
default protocol since Dec 6 (:data:`LOO_PROTOCOL_BY_SCANNER`; ``--pooled``:
:data:`LOO_PROTOCOL_POOLED`).

A helper module, not a script: ``real_geometry.py`` re-exports the names other scripts and the
tests take from it (``_objective``, ``_best_admitted``, ``reference_trusted``, ...).

The results are the benchmark's: ``per[dataset][g][row]`` is the :func:`real_geometry.score`
dict of grid setting ``g`` on scanner row ``row`` (``<model>_<step>deg_noise<cm>cm``, with
``@<rule>`` appended for the averaging rows of ``--loo-rules``), ``"all"`` holding recall,
precision and visible trunks and ``"within_10m"`` the DBH RMSE / bias at <= 10 m.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from stemmap.eval.real_slices import RealSlice, reference_jackknife

#: The scanner families of the benchmark's rows: first-echo (nearest-return) scanners, which
#: the detector is told about (``beam_footprint_deg`` > 0, ``stemmap detect --footprint``), and
#: footprint-averaging SICK-class scanners (``beam_footprint_deg`` = 0, the edge model).
FAMILIES = ("nearest", "averaging")

Rows = Mapping[str, Mapping[int, Mapping[str, Any]]]

#: The LOO's protocol since Dec 6 (docs/algorithms.md, "Decisions taken where issue 11 is
#: silent"): the issue's target row is a nearest-return (first-echo) scan, and a first-echo
#: scan does not depend on how an averaging scanner forms its range, so the setting a
#: first-echo scanner runs is chosen on the training sets' nearest-return rows and the one a
#: footprint-averaging scanner runs on their averaging rows (the detector is told its scanner
#: model at run time: ``beam_footprint_deg``, ``stemmap detect --footprint``). Each held-out
#: row is scored under the choice of its own family.
LOO_PROTOCOL_BY_SCANNER = (
    "by scanner family: the nearest-return setting chosen on the training sets' nearest-return"
    " rows, the averaging setting on their averaging rows; each held-out row under its own"
    " family's choice"
)
#: Every LOO before Dec 6 (``--pooled``): one setting chosen on every training row, both
#: families pooled, so the averaging rows -- whose benchmark scanner's return threshold is a
#: modelling choice -- also pick what a first-echo scanner runs.
LOO_PROTOCOL_POOLED = "pooled: one setting chosen on every training row (both scanner families)"


def _objective(r: Mapping[str, Any], cap: bool = False) -> float:
    """Training score of one dataset x scanner: F1 of recall and precision (false alarms on the
    real plots count, ``real_geometry.false_alarms``) minus DBH RMSE at <= 10 m in units of the
    3 cm target (a detector that finds everything, without a false alarm, with 3 cm RMSE scores
    0). Where the slice's reference is not complete (no precision) the recall stands for F1. The
    first two rounds used recall alone, which let clutter pass as trunks."""
    rec = r["all"]["recall"] or 0.0
    prec = r["all"]["precision"]
    f1 = rec  # reference not complete (no precision): recall alone
    if prec is not None:
        f1 = 2.0 * rec * prec / (rec + prec) if rec + prec > 0 else 0.0
    rmse = r["within_10m"]["rmse_cm"]
    penalty = rmse / 3.0 if rmse is not None else 1.0
    # cap=True is reported for comparison only: a penalty capped at 1 (no detection = 3 cm)
    # stops punishing fits worse than 3 cm and chose 5 % bark (rough, wrong arcs accepted)
    return float(f1 - (min(penalty, 1.0) if cap else penalty))


def _best_admitted(
    candidates: Iterable[int], score: Callable[[int], float], admitted: Callable[[int], bool]
) -> int:
    """The best-scoring admitted setting among ``candidates`` (the first in grid order on a
    tie, as ``max``), asking ``admitted`` only for the settings that rank above it."""
    for g in sorted(candidates, key=lambda g: -score(g)):
        if admitted(g):
            return g
    raise ValueError("no admitted grid setting (simulated targets)")


def family_of(row: str) -> str:
    """The scanner family of a benchmark row name (its model, before the first ``_``)."""
    model = row.split("_", 1)[0]
    if model not in FAMILIES:
        raise ValueError(f"row {row!r}: unknown scanner model {model!r}")
    return model


def train_score(per: Rows, train: Iterable[str], g: int, family: str | None = None) -> float:
    """Mean :func:`_objective` of setting ``g`` over the ``train`` datasets' rows with a visible
    trunk, pooled (every dataset x row weighs the same); only the rows of ``family`` unless it
    is None. ``-inf`` where no row counts."""
    vals = [
        _objective(r)
        for n in train
        for row, r in per[n][g].items()
        if r["all"]["visible"] and (family is None or family_of(row) == family)
    ]
    return float(np.mean(vals)) if vals else -math.inf


def objectives_by_row(rows: Mapping[int, Mapping[str, Any]], grid: Iterable[int]) -> dict:
    """Per scanner row of one dataset, :func:`_objective` of every setting in ``grid`` (in its
    order, rounded to 3 decimals; None where the row has no visible trunk and so never trains)."""
    grid = list(grid)
    names = list(rows[grid[0]]) if grid else []
    return {
        row: [
            round(_objective(rows[g][row]), 3) if rows[g][row]["all"]["visible"] else None
            for g in grid
        ]
        for row in names
    }


def choose_by_family(
    per: Rows,
    train: list[str],
    candidates: Iterable[int],
    admitted: Callable[[int], bool],
    compiled: Iterable[int] | None = None,
) -> dict[str, dict[str, Any]]:
    """The LOO choice made separately for each scanner family present in the training rows:
    per family, the best admitted setting among ``candidates`` by :func:`train_score` over that
    family's rows only (the same lazy ``admitted``, so a setting is simulated at most once for
    both), as ``{"chosen_index", "train_score"}``. For the averaging family also the choice among
    ``compiled`` (the settings the compiled path runs; a first-echo detector always runs the
    numpy path, so the nearest family has no compiled-only choice)."""
    candidates = list(candidates)
    present = {family_of(row) for n in train for row in per[n][candidates[0]]} if train else set()
    out: dict[str, dict[str, Any]] = {}
    for fam in (f for f in FAMILIES if f in present):

        def score(g: int, fam: str = fam) -> float:
            return train_score(per, train, g, fam)

        best = _best_admitted(candidates, score, admitted)
        out[fam] = {"chosen_index": best, "train_score": round(score(best), 3)}
        if fam == "averaging" and compiled is not None:
            best_c = _best_admitted(compiled, score, admitted)
            out[fam]["compiled_only"] = {
                "chosen_index": best_c,
                "train_score": round(score(best_c), 3),
            }
    return out


def family_protocol(fams: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The by-scanner protocol's choice of one fold (the default of ``real_geometry.py --loo``
    since Dec 6) from :func:`by_scanner_table`'s per-family choices: each family's choice
    (``chosen_by_family``, with its training score on that family's rows) and the held-out
    table in which every row is scored under the choice of its own family (``held_out``: the
    nearest-return rows under the nearest family's choice, the averaging rows under the
    averaging family's). ``compiled_only`` is the same with the averaging family's choice among
    the compiled settings (a first-echo detector runs the numpy path whatever its setting, so the
    nearest family keeps its choice there)."""
    out: dict[str, Any] = {
        "chosen_by_family": {f: c["chosen_index"] for f, c in fams.items()},
        "train_score_by_family": {f: c["train_score"] for f, c in fams.items()},
        "held_out": {row: v for c in fams.values() for row, v in c["held_out"].items()},
    }
    comp = {f: c.get("compiled_only", c) for f, c in fams.items()}
    out["compiled_only"] = {
        "chosen_by_family": {f: c["chosen_index"] for f, c in comp.items()},
        "held_out": {row: v for c in comp.values() for row, v in c["held_out"].items()},
    }
    return out


def family_rows(rows: Mapping[str, Any], family: str) -> dict[str, Any]:
    """The entries of a per-row dict (a held-out table) that belong to ``family``."""
    return {row: v for row, v in rows.items() if family_of(row) == family}


def by_scanner_table(
    per: Rows,
    held: str,
    train: list[str],
    grid: Sequence[Mapping[str, Any]],
    admitted: Callable[[int], bool],
    compiled: Iterable[int] | None = None,
    n_candidates: int | None = None,
) -> dict[str, dict[str, Any]]:
    """``held_out[held]["by_scanner"]`` of ``real_geometry.py --loo --by-scanner``:
    :func:`choose_by_family` on the ``train`` datasets among the first ``n_candidates`` settings
    of ``grid`` (default every one; ``--baseline-grid``: the grid before a round's additions),
    each choice with its setting and the held-out dataset's rows of its own family
    (:func:`_held_out_rows`, next to textbook Kasa's, ``per[held][-1]``)."""
    n = len(grid) if n_candidates is None else n_candidates
    if compiled is not None:
        compiled = [g for g in compiled if g < n]
    fams = choose_by_family(per, train, range(n), admitted, compiled)
    for fam, ch in fams.items():
        for c in (ch, ch.get("compiled_only")):
            if c:
                c["chosen"] = dict(grid[c["chosen_index"]])
                c["held_out"] = family_rows(_held_out_rows(per[held], c["chosen_index"]), fam)
    return fams


def fold_choice(
    per: Rows,
    held: str,
    train: list[str],
    grid: Sequence[Mapping[str, Any]],
    admitted: Callable[[int], bool],
    compiled: Sequence[int],
    baseline: int | None = None,
    pooled: bool = False,
    by_scanner: bool = False,
) -> dict[str, Any]:
    """One fold of ``real_geometry.py --loo`` (``held`` held out, the ``train`` datasets
    training): the choice among ``grid`` by the LOO's protocol, with the held-out rows.

    By default (the protocol since Dec 6, :data:`LOO_PROTOCOL_BY_SCANNER`) the choice is made
    per scanner family (``by_scanner``: :func:`by_scanner_table`) and the fold's ``held_out`` /
    ``compiled_only`` / ``chosen_by_family`` are :func:`family_protocol`'s (every held-out row
    under its own family's choice); the pooled choice is reported under ``"pooled"``. With
    ``pooled`` (:data:`LOO_PROTOCOL_POOLED`, every LOO before Dec 6) the pooled choice is the
    fold's ``chosen_index`` / ``chosen`` / ``train_score`` / ``held_out`` / ``compiled_only``
    as before, and ``by_scanner`` adds the per-family report. The pooled choice is also made
    among the ``compiled`` settings (a default must run compiled). With ``baseline`` the same
    among the first ``baseline`` settings, under ``"baseline"``."""

    def score(g: int) -> float:
        return train_score(per, train, g)

    def pooled_choice(n: int) -> dict[str, Any]:
        best = _best_admitted(range(n), score, admitted)
        return {
            "chosen_index": best,
            "chosen": dict(grid[best]),
            "train_score": round(score(best), 3),
            "held_out": _held_out_rows(per[held], best),
        }

    def protocol(n: int) -> dict[str, Any]:
        ch = pooled_choice(n)
        if n == len(grid):
            best_c = _best_admitted([g for g in compiled if g < n], score, admitted)
            ch["compiled_only"] = {
                "chosen_index": best_c,
                "chosen": dict(grid[best_c]),
                "train_score": round(score(best_c), 3),
                "held_out": _held_out_rows(per[held], best_c),
            }
        out: dict[str, Any] = {"protocol": "pooled" if pooled else "by_scanner"}
        out.update(ch if pooled else {"pooled": ch})
        if by_scanner or not pooled:
            fams = by_scanner_table(per, held, train, grid, admitted, compiled, n)
            out["by_scanner"] = fams
            if not pooled:
                out.update(family_protocol(fams))
        return out

    table = protocol(len(grid))
    if baseline is not None:
        table["baseline"] = protocol(baseline)
    return table


#: A slice's references are trusted for choosing parameters when the RMS over its reference
#: trunks of the largest change of the diameter with one 30-degree sector of the ring left out
#: (:func:`stemmap.eval.real_slices.reference_jackknife`) is at most this much (cm; the issue's
#: DBH bias target: a reference that uncertain cannot check it).
TRUSTED_REFERENCE_CM = 1.0


def reference_trusted(sl: RealSlice) -> tuple[bool, float]:
    """Whether the references of ``sl`` are trusted (:data:`TRUSTED_REFERENCE_CM`) and the RMS
    over its reference trunks of the largest jackknife change of the diameter, cm (the DBH
    errors are scored over trunks, so one uncertain ring of ten weighs a tenth)."""
    worst = []
    for t in range(len(sl.refs)):
        jk = reference_jackknife(sl, t)["jackknife_change_cm"]
        worst.append(math.inf if jk is None else max(abs(jk[0]), abs(jk[1])))
    rms = float(np.sqrt(np.mean(np.square(worst)))) if worst else math.inf
    return rms <= TRUSTED_REFERENCE_CM, rms


def _held_out_rows(per: Mapping[int, Mapping[str, Any]], g: int) -> dict[str, Any]:
    """Held-out results of grid setting ``g`` per scanner, next to textbook Kasa's."""
    return {
        sc: {
            "recall": r["all"]["recall"],
            "precision": r["all"]["precision"],
            "visible": r["all"]["visible"],
            "rmse_cm_le10m": r["within_10m"]["rmse_cm"],
            "bias_cm_le10m": r["within_10m"]["bias_cm"],
            "textbook_kasa_recall": per[-1][sc]["all"]["recall"],
            "recall_3cm": r["all"].get("recall_3cm"),
            "textbook_kasa_recall_3cm": per[-1][sc]["all"].get("recall_3cm"),
            "textbook_kasa_precision": per[-1][sc]["all"]["precision"],
            "textbook_kasa_rmse_cm_le10m": per[-1][sc]["within_10m"]["rmse_cm"],
            "textbook_kasa_bias_cm_le10m": per[-1][sc]["within_10m"]["bias_cm"],
            # both sides of kasa_count.py's fair count (Dec 5): detections per scan that are
            # false alarms (None where the slice scores no precision) or matched to no trunk
            "false_alarms_per_scan": r["false_alarms_per_scan"],
            "unmatched_per_scan": r["unmatched_per_scan"],
            "textbook_kasa_false_alarms_per_scan": per[-1][sc]["false_alarms_per_scan"],
            "textbook_kasa_unmatched_per_scan": per[-1][sc]["unmatched_per_scan"],
        }
        for sc, r in per[g].items()
    }
