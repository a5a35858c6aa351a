"""Greedy forward selection for ``real_geometry.py --loo --greedy`` (issue 11, Dec 5, "Greedy
forward selection from the preset" in docs/algorithms/scan-detection.md).

A fixed grid lets a held-out fold choose only what someone thought to add, and adding a grid
point after seeing a held-out row leaks the held-out data into the protocol. This procedure is
declared before any run and reads training rows only:

1. the *ingredients* are every (option, value) that some existing grid point sets differently
   from the start setting (the ``stemmap`` preset, grid 85), in the order they first appear in
   the grid (:func:`ingredients`; derived from the grid, not picked from any dataset's rows);
2. from the start, each step scores the current setting with each ingredient not yet on the
   path (one value per option: an option already set by the path is not offered again) by the
   LOO's own training score (:func:`_loo_choice.train_score`: mean :func:`_loo_choice._objective`
   over the training datasets' visible rows), best first;
3. the best candidate whose gain over the current score exceeds ``eps`` is asked the simulated
   admission (the LOO's lazy ``admitted``) and accepted only if admitted; a candidate that is
   not admitted is passed over for the next best that still gains more than ``eps``;
4. the search stops when no admitted candidate gains more than ``eps``.

The per-row results of a setting do not depend on the fold, so ``evaluate`` runs each setting
once (cached by the caller) and every fold reads its own training rows from the cache.

Since Dec 6 the selection follows the LOO's protocol (``real_geometry.py --loo``, default
``by_scanner``): one path per scanner family, each scored on that family's training rows only
(nearest-return rows choose what a first-echo scanner runs, averaging rows what a SICK-class
scanner runs), each held out on its family's rows; ``--pooled`` keeps the single path on every
row (the Dec 5 runs).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from _loo_choice import _objective, family_of, family_rows

#: Settings run together with ``cache_dir`` (the scans of a dataset are drawn once per batch,
#: which costs more than a setting's detections: a batch of 3 ran about 10 CPU s a setting)
_CHUNK = 12

Ingredient = tuple[str, Any]
Setting = Mapping[str, Any]

#: The declared stopping threshold of the greedy search (training-score units: the objective
#: is F1 - RMSE / 3 cm, so 0.001 is 0.1 % of F1 or 0.003 cm of RMSE pooled over every training
#: row). It is the resolution at which the LOO reports and compares training scores (3
#: decimals, ``train_score`` in its JSON): a gain below it is not distinguishable from a tie in
#: any table the choice has been argued from, and it lies far below the 0.003-0.05 gains that
#: changed a fold's choice in the Dec 5 rounds.
GREEDY_EPS = 0.001


def ingredients(
    grid: Sequence[Setting], start: Setting, preset_value: Callable[[str], Any]
) -> list[Ingredient]:
    """Every (option, value) that some setting of ``grid`` sets differently from ``start``,
    in the order of first appearance (grid order, then the setting's own key order), each
    once. An option ``start`` does not name takes the preset's value (``preset_value``), as a
    grid setting's overrides do."""
    out: list[Ingredient] = []
    seen: set[tuple[str, str]] = set()
    for s in grid:
        for k, v in s.items():
            ref = start[k] if k in start else preset_value(k)
            key = (k, repr(v))
            if _same(v, ref) or key in seen:
                continue
            seen.add(key)
            out.append((k, v))
    return out


def _same(a: Any, b: Any) -> bool:
    """Equal values of one option (``True`` is not ``1.0``: a switch is not a threshold)."""
    return type(a) is type(b) and bool(a == b)


def with_ingredients(start: Setting, path: Iterable[Ingredient]) -> dict[str, Any]:
    """``start`` with the path's (option, value) pairs set."""
    return {**start, **dict(path)}


def train_score_rows(
    rows: Mapping[str, Mapping[str, Any]], train: Iterable[str], family: str | None = None
) -> float:
    """Mean :func:`_objective` over the ``train`` datasets' rows with a visible trunk (every
    dataset x row weighs the same: :func:`_loo_choice.train_score` of one setting's rows
    ``rows[dataset][row]``), only the rows of scanner ``family`` unless it is None; ``-inf``
    where no row counts."""
    vals = [
        _objective(r)
        for n in train
        for row, r in rows[n].items()
        if r["all"]["visible"] and (family is None or family_of(row) == family)
    ]
    return float(np.mean(vals)) if vals else -float("inf")


def greedy_select(
    start: Setting,
    candidates: Sequence[Ingredient],
    rows_of: Callable[[Sequence[Setting]], list[Mapping[str, Mapping[str, Any]]]],
    train: Sequence[str],
    admitted: Callable[[Setting], bool],
    eps: float = GREEDY_EPS,
    max_steps: int | None = None,
    valid: Callable[[Setting], bool] = lambda s: True,
    family: str | None = None,
) -> dict[str, Any]:
    """Greedy forward selection (module docstring) on the ``train`` datasets (their rows of
    scanner ``family`` only, unless it is None).

    ``rows_of(settings)`` gives each setting's per-dataset rows (``[dataset][row]`` score dicts;
    it is called once per step with every candidate of the step, so the caller can run them in
    one batch and cache them); only the ``train`` datasets' rows are read. ``admitted(setting)``
    is the simulated admission, asked only for a candidate about to be accepted (and for the
    start where the search ends on it). Returns the path (each step's ingredient, training
    score, gain, and the better-scoring candidates that were not admitted), the final setting
    and its training score, and the candidates' scores of the last step (the stopping
    evidence). A candidate that is not a ``valid`` configuration (an option that needs another
    the path does not set, ``DetectorConfig``'s own checks) is not offered (listed per step)."""
    train = list(train)
    path: list[Ingredient] = []
    current = dict(start)
    (rows0,) = rows_of([current])
    cur = train_score_rows(rows0, train, family)
    steps: list[dict[str, Any]] = [{"added": None, "train_score": round(cur, 4)}]
    last: list[tuple[Ingredient, float]] = []
    while max_steps is None or len(path) < max_steps:
        used = {k for k, _ in path}
        offer = [(k, v) for k, v in candidates if k not in used and not _same(current.get(k), v)]
        invalid = [ing for ing in offer if not valid(with_ingredients(current, [ing]))]
        offer = [ing for ing in offer if ing not in invalid]
        steps[-1]["invalid_next"] = [list(i) for i in invalid]
        if not offer:
            break
        settings = [with_ingredients(current, [ing]) for ing in offer]
        scores = [train_score_rows(r, train, family) for r in rows_of(settings)]
        # best first; equal scores keep the ingredients' declared order (a stable sort)
        order = sorted(range(len(offer)), key=lambda i: -scores[i])
        last = [(offer[i], scores[i]) for i in order]
        best3 = [(list(ing), round(sc - cur, 4)) for ing, sc in last[:3]]
        print(
            f"greedy {train} {family or 'pooled'}: after {len(path)} scored, best {best3}",
            file=sys.stderr,
            flush=True,
        )
        passed_over: list[dict[str, Any]] = []
        accepted = None
        for i in order:
            if scores[i] - cur <= eps:
                break
            if admitted(settings[i]):
                accepted = i
                break
            passed_over.append({"ingredient": list(offer[i]), "train_score": round(scores[i], 4)})
        if accepted is None:
            steps[-1]["not_admitted_above_eps"] = passed_over
            break
        path.append(offer[accepted])
        current = settings[accepted]
        steps.append(
            {
                "added": list(offer[accepted]),
                "train_score": round(scores[accepted], 4),
                "gain": round(scores[accepted] - cur, 4),
                "not_admitted_before": passed_over,
            }
        )
        cur = scores[accepted]
        print(
            f"greedy {train} {family or 'pooled'}: step {len(path)} {steps[-1]}",
            file=sys.stderr,
            flush=True,
        )
    if not path and not admitted(current):
        raise ValueError("the start setting is not admitted (simulated targets)")
    return {
        "path": [list(p) for p in path],
        "steps": steps,
        "setting": current,
        "train_score": round(cur, 4),
        "eps": eps,
        "family": family or "pooled",
        "last_step_best": [
            {"ingredient": list(ing), "gain": round(s - cur, 4)} for ing, s in last[:5]
        ],
    }


def greedy_table(
    scored: Sequence[str],
    trains: Sequence[str],
    start: Setting,
    candidates: Sequence[Ingredient],
    rows_of: Callable[[Sequence[Setting]], list[Mapping[str, Mapping[str, Any]]]],
    admitted: Callable[[Setting], bool],
    held_rows: Callable[[str, Mapping[str, Any]], Any],
    eps: float = GREEDY_EPS,
    valid: Callable[[Setting], bool] = lambda s: True,
    folds: Sequence[str] | None = None,
    families: Sequence[str] | None = None,
) -> dict[str, Any]:
    """``held_out[name]["greedy"]`` of ``real_geometry.py --loo --greedy``: per ``scored``
    dataset, :func:`greedy_select` on the ``trains`` datasets other than it, with
    ``held_rows(name, rows)`` of the selected setting's rows on it; and under
    ``"all_trusted"`` the selection on every ``trains`` dataset (the candidate default); only
    the ``folds`` named (default every one).

    With ``families`` (the LOO's by-scanner protocol) each fold holds one selection per family
    (``out[name][family]``, scored on that family's training rows only, its ``held_out`` the
    held-out dataset's rows of that family), and ``out[name]["held_out"]`` joins them: every
    held-out row under the selection of its own family (``held_rows`` must then return a
    per-row dict)."""
    out: dict[str, Any] = {}

    def select(train: list[str], fam: str | None) -> dict[str, Any]:
        return greedy_select(
            start, candidates, rows_of, train, admitted, eps, valid=valid, family=fam
        )

    for held in (n for n in scored if folds is None or n in folds):
        train = [n for n in trains if n != held]
        if families is None:
            sel = select(train, None)
            (rows,) = rows_of([sel["setting"]])
            out[held] = {**sel, "held_out": held_rows(held, rows[held])}
            continue
        out[held] = {"held_out": {}}
        for fam in families:
            sel = select(train, fam)
            (rows,) = rows_of([sel["setting"]])
            mine = family_rows(held_rows(held, rows[held]), fam)
            out[held][fam] = {**sel, "held_out": mine}
            out[held]["held_out"].update(mine)
    if folds is None or "all_trusted" in folds:
        if families is None:
            out["all_trusted"] = select(list(trains), None)
        else:
            out["all_trusted"] = {fam: select(list(trains), fam) for fam in families}
    return out


def greedy_loo(
    grid: Sequence[Setting],
    per: Mapping[str, Mapping[int, Mapping[str, Any]]],
    slices: Mapping[str, Any],
    run_rows: Callable[[Any, dict[str, Any]], dict[str, Any]],
    key: Callable[[Setting], str],
    admitted: Callable[[Setting], bool],
    scored: Sequence[str],
    trains: Sequence[str],
    eps: float = GREEDY_EPS,
    start: int | None = None,
    folds: Sequence[str] | None = None,
    cache_dir: Path | None = None,
    families: Sequence[str] | None = None,
) -> dict[str, Any]:
    """``greedy`` of ``real_geometry.py --loo --greedy``: :func:`greedy_table` from the grid
    setting that is the ``stemmap`` preset (``key`` is a setting's effective configuration;
    the preset is ``key({})``) over :func:`ingredients` of ``grid``. ``per`` holds the LOO's
    rows of every grid setting (``per[dataset][index][row]``, reused); any other setting is
    run once on every slice (``run_rows(slice, {name: DetectorConfig})``, the LOO's scans)
    and cached, whichever fold asks; with ``cache_dir`` also on disk (one pickle per setting,
    twelve settings per batch, each process starting at a different place in the candidate
    list), so folds run as parallel processes share what they have run. ``families``: one
    selection per scanner family (:func:`greedy_table`; the LOO's by-scanner protocol)."""
    from stemmap.errors import ConfigError
    from stemmap.scan.detect import DetectorConfig

    cache = {key(grid[g]): {n: per[n][g] for n in per} for g in next(iter(per.values())) if g >= 0}

    def on_disk(k: str) -> bool:
        if cache_dir is None:
            return False
        f = cache_dir / (hashlib.sha1(k.encode()).hexdigest()[:20] + ".pkl")
        if f.exists():
            cache[k] = pickle.loads(f.read_bytes())
            return True
        return False

    def run(new: dict[str, Setting]) -> None:
        for name, sl in slices.items():
            res = run_rows(sl, {k: DetectorConfig.preset("stemmap", **s) for k, s in new.items()})
            for k in new:
                cache.setdefault(k, {})[name] = {sc: conf[k] for sc, conf in res.items()}
        for k in new if cache_dir is not None else ():
            f = cache_dir / (hashlib.sha1(k.encode()).hexdigest()[:20] + ".pkl")
            tmp = f.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(pickle.dumps(cache[k]))
            tmp.replace(f)

    rot = sum(map(ord, ",".join(folds or ()))) if cache_dir is not None else 0

    def rows_of(settings: Sequence[Setting]) -> list[Mapping[str, Mapping[str, Any]]]:
        new = list({key(s): s for s in settings if key(s) not in cache}.items())
        if new and cache_dir is not None:
            r = rot % len(new)
            new = new[r:] + new[:r]
            for i in range(0, len(new), _CHUNK):
                part = {k: s for k, s in new[i : i + _CHUNK] if not on_disk(k)}
                if part:
                    run(part)
        elif new:
            run(dict(new))
        return [cache[key(s)] for s in settings]

    preset = DetectorConfig.preset("stemmap")
    if start is None:
        start = next(g for g in range(len(grid)) if key(grid[g]) == key({}))
    ings = ingredients(grid, grid[start], lambda k: getattr(preset, k))
    n_grid = len(cache)

    def held_rows(n: str, rows: Mapping[str, Any]) -> Any:
        from _loo_choice import _held_out_rows

        return _held_out_rows({0: rows, -1: per[n][-1]}, 0)

    def valid(s: Setting) -> bool:
        try:
            DetectorConfig.preset("stemmap", **s)
        except ConfigError:
            return False
        return True

    table = greedy_table(
        scored, trains, grid[start], ings, rows_of, admitted, held_rows, eps, valid, folds, families
    )
    return {
        "start_index": start,
        "eps": eps,
        "protocol": "pooled" if families is None else "by_scanner",
        "ingredients": [list(i) for i in ings],
        "settings_run": len(cache) - n_grid,
        "folds": table,
    }
