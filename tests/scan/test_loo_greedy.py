"""The greedy forward selection of ``real_geometry.py --loo --greedy`` (issue 11, Dec 5,
"Greedy forward selection from the preset" in docs/algorithms/scan-detection.md).

Small synthetic settings and rows shaped as the benchmark's (``rows[dataset][row]`` score
dicts): the ingredients are the grid's option values that differ from the start, the held-out
dataset never trains (its rows are absent or changed at will and its fold's path does not
move), the simulated admission is asked before a candidate is accepted and never for a
candidate whose gain does not pass the threshold, and the search stops exactly at the
declared threshold. With recall = precision = 1 a row's objective is ``1 - RMSE / 3 cm``; the
RMSEs below are multiples of 0.375 cm, so every objective and gain is exact in binary."""

import pytest

from _loo_greedy import greedy_select, greedy_table, ingredients, train_score_rows

ROWS = ("nearest_0.5deg_noise0cm", "averaging_0.5deg_noise1cm")
START = {"a": 0, "b": False, "c": 0.0}


def _r(rmse: float) -> dict:
    """One row: every visible trunk found, no false alarm, this DBH RMSE (cm)."""
    return {
        "all": {"recall": 1.0, "precision": 1.0, "visible": 10, "recall_3cm": 1.0},
        "within_10m": {"rmse_cm": rmse, "bias_cm": 0.0},
        "false_alarms_per_scan": 0.0,
        "unmatched_per_scan": 0.0,
    }


def _model(effects: dict[str, dict[tuple[str, object], float]], base: float = 3.0):
    """``rows_of`` for per-dataset additive RMSE effects of (option, value) pairs set away from
    START (cm; negative = better), and the list of every batch it was asked for."""
    calls: list[list[dict]] = []

    def rows_of(settings):
        calls.append([dict(s) for s in settings])
        out = []
        for s in settings:
            on = [(k, v) for k, v in s.items() if START.get(k) != v]
            out.append(
                {
                    n: {row: _r(base + sum(eff.get(p, 0.0) for p in on)) for row in ROWS}
                    for n, eff in effects.items()
                }
            )
        return out

    return rows_of, calls


def _cands():
    return ingredients(
        [START, {**START, "a": 1}, {**START, "b": True}, {**START, "c": 2.0}], START, {}.get
    )


def test_ingredients_are_the_grid_values_that_differ_from_the_start():
    grid = [
        {"a": 0, "b": False},  # the start itself: nothing
        {"a": 1, "b": False},
        {"a": 1, "b": True, "x": 5},  # a=1 again: listed once
        {"a": 2, "b": False, "x": 7},  # x=7 is the preset's value of x: not an ingredient
        {"a": 1.0},  # a float threshold is not the integer switch value
    ]
    preset = {"x": 7}
    ings = ingredients(grid, {"a": 0, "b": False}, preset.get)
    assert ings == [("a", 1), ("b", True), ("x", 5), ("a", 2), ("a", 1.0)]


def test_path_adds_the_best_gain_then_stops():
    # t1 and t2 both gain most from a=1 (0.75 cm), then c=2.0 (0.375 cm); b=True hurts
    eff = {("a", 1): -0.75, ("c", 2.0): -0.375, ("b", True): 0.75}
    rows_of, _ = _model({"t1": eff, "t2": eff})
    sel = greedy_select(START, _cands(), rows_of, ["t1", "t2"], lambda s: True, eps=0.0)
    assert sel["path"] == [["a", 1], ["c", 2.0]]
    assert sel["setting"] == {"a": 1, "b": False, "c": 2.0}
    assert sel["train_score"] == pytest.approx(1.0 - (3.0 - 1.125) / 3.0)
    assert [s["gain"] for s in sel["steps"][1:]] == [0.25, 0.125]
    # the last step's evidence: b=True, the only ingredient left, loses
    assert sel["last_step_best"] == [{"ingredient": ["b", True], "gain": -0.25}]


def test_one_value_per_option():
    cands = [("a", 1), ("a", 2), ("c", 2.0)]
    eff = {("a", 1): -0.75, ("a", 2): -0.375, ("c", 2.0): -0.375}
    rows_of, calls = _model({"t1": eff})
    sel = greedy_select(START, cands, rows_of, ["t1"], lambda s: True, eps=0.0)
    assert sel["path"] == [["a", 1], ["c", 2.0]]
    # after a=1, the second step offers c=2.0 only (a=2 would replace the accepted a=1)
    assert [s["a"] for s in calls[2]] == [1]


def test_held_out_dataset_never_trains():
    eff = {("a", 1): -0.75, ("c", 2.0): -0.375}
    rows_of, _ = _model({"t1": eff, "t2": eff})
    # rows_of has no "held" dataset at all: reading it would raise
    sel = greedy_select(START, _cands(), rows_of, ["t1", "t2"], lambda s: True, eps=0.0)
    assert sel["path"] == [["a", 1], ["c", 2.0]]

    def folds(held_eff):
        rows_of, _ = _model({"t1": eff, "t2": eff, "held": held_eff})
        return greedy_table(
            ["t1", "t2", "held"],
            ["t1", "t2", "held"],
            START,
            _cands(),
            rows_of,
            lambda s: True,
            lambda n, rows: rows[ROWS[0]]["within_10m"]["rmse_cm"],
            eps=0.0,
        )

    # the held-out set would take b=True by a wide margin if it trained ...
    poisoned = folds({("b", True): -2.25, ("a", 1): 3.0})
    clean = folds({})
    # ... its own fold's path and training score do not move
    assert poisoned["held"]["path"] == clean["held"]["path"] == [["a", 1], ["c", 2.0]]
    assert poisoned["held"]["train_score"] == clean["held"]["train_score"]
    # its held-out row: its own rows of the chosen setting (3 + 3 cm: a=1 hurts it)
    assert poisoned["held"]["held_out"] == 6.0
    assert clean["held"]["held_out"] == 3.0  # no effect on it
    # where it trains (t1's fold, every training set) it moves the choice: the poison is real
    assert poisoned["t1"]["path"][0] == ["b", True]
    assert poisoned["all_trusted"]["path"][0] == ["b", True]


def test_admission_is_asked_before_acceptance():
    eff = {("a", 1): -0.75, ("c", 2.0): -0.375, ("b", True): -0.0}
    rows_of, _ = _model({"t1": eff})
    asked: list[dict] = []

    def admitted(s):
        asked.append(dict(s))
        return s.get("a") != 1  # the best ingredient breaks the simulated targets

    sel = greedy_select(START, _cands(), rows_of, ["t1"], admitted, eps=0.0)
    # a=1 ranks first but is not admitted: c=2.0 is accepted instead, a=1 reported passed over
    assert sel["path"] == [["c", 2.0]]
    assert sel["steps"][1]["not_admitted_before"] == [{"ingredient": ["a", 1], "train_score": 0.25}]
    # asked in rank order, the accepted setting asked (and admitted) before it is on the path
    assert asked[:2] == [{**START, "a": 1}, {**START, "c": 2.0}]
    # second step: a=1 again (not admitted), b=True gains nothing: never asked
    assert asked[2:] == [{**START, "a": 1, "c": 2.0}]
    assert {"b": True} not in [{k: s[k] for k in ("b",) if s[k]} for s in asked]
    assert sel["steps"][-1]["not_admitted_above_eps"] == [
        {"ingredient": ["a", 1], "train_score": 0.375}
    ]


def test_start_must_be_admitted_when_nothing_is_added():
    rows_of, _ = _model({"t1": {}})
    with pytest.raises(ValueError, match="start setting is not admitted"):
        greedy_select(START, _cands(), rows_of, ["t1"], lambda s: False, eps=0.0)
    # an admitted start with no gaining ingredient is the selection, asked once
    asked = []
    sel = greedy_select(START, _cands(), rows_of, ["t1"], lambda s: asked.append(s) or True)
    assert sel["path"] == [] and sel["setting"] == START and asked == [START]


@pytest.mark.parametrize(("gain_cm", "added"), [(0.75, False), (1.125, True)])
def test_stops_when_no_gain_exceeds_eps(gain_cm, added):
    # eps = 0.25 of training score = 0.75 cm of RMSE: a gain of exactly eps stops the search,
    # one above it is accepted
    rows_of, _ = _model({"t1": {("a", 1): -gain_cm}})
    asked = []
    sel = greedy_select(
        START, [("a", 1)], rows_of, ["t1"], lambda s: asked.append(s) or True, eps=0.25
    )
    assert sel["path"] == ([["a", 1]] if added else [])
    # at the threshold the candidate is not even asked for admission (only the start is)
    assert asked == ([{**START, "a": 1}] if added else [START])


def test_train_score_rows_pools_visible_rows_of_the_training_sets():
    rows = {"t1": {ROWS[0]: _r(0.75), ROWS[1]: _r(1.5)}, "t2": {ROWS[0]: _r(3.0)}}
    rows["t2"][ROWS[1]] = {**_r(0.0), "all": {**_r(0.0)["all"], "visible": 0}}
    assert train_score_rows(rows, ["t1", "t2"]) == pytest.approx(1.0 - (0.75 + 1.5 + 3.0) / 9.0)
    assert train_score_rows(rows, []) == float("-inf")


def test_invalid_configurations_are_not_offered():
    # b=True needs a=1 (as stub_runs_snoop needs stub_runs): offered only once a=1 is on the path
    eff = {("a", 1): -0.375, ("b", True): -0.75}
    rows_of, calls = _model({"t1": eff})
    sel = greedy_select(
        START,
        [("a", 1), ("b", True)],
        rows_of,
        ["t1"],
        lambda s: True,
        eps=0.0,
        valid=lambda s: not s["b"] or s["a"] == 1,
    )
    assert sel["path"] == [["a", 1], ["b", True]]
    assert sel["steps"][0]["invalid_next"] == [["b", True]]
    assert all(not s["b"] or s["a"] == 1 for batch in calls for s in batch)
