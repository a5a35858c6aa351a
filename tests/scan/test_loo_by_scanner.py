"""The leave-one-dataset-out choice per scanner family (``real_geometry.py --loo --by-scanner``;
issue 11, Dec 5, "The LOO by scanner family" in docs/algorithms/scan-detection.md).

The bookkeeping on small synthetic result dicts shaped as the benchmark's
(``per[dataset][setting][row]``, setting -1 = textbook Kasa): which rows belong to which family,
that each family's choice is the pooled choice restricted to its own rows, that the held-out
dataset and rows without a visible trunk never train, that the admission is shared and lazy,
and that each family's held-out table holds only its own rows of the chosen setting. With
recall = precision = 1 a row's objective is ``1 - RMSE / 3 cm``, so the RMSEs below set the
ranking exactly."""

import math

import pytest

from _loo_choice import (
    _objective,
    by_scanner_table,
    choose_by_family,
    family_of,
    objectives_by_row,
    train_score,
)

NEAR = ("nearest_0.5deg_noise0cm", "nearest_1deg_noise3cm")
AVG = ("averaging_0.5deg_noise0cm", "averaging_0.5deg_noise1cm@0.5:uniform:20")
GRID = ({"name": "a"}, {"name": "b"}, {"name": "c"})


def _r(rmse: float | None, visible: int = 10, bias: float = 0.0) -> dict:
    """One row's score dict: every visible trunk found, no false alarm, this DBH RMSE (cm); no
    recall where no trunk is visible (as ``real_geometry.score``)."""
    rec = 1.0 if visible else None
    return {
        "all": {"recall": rec, "precision": 1.0, "visible": visible, "recall_3cm": rec},
        "within_10m": {"rmse_cm": rmse, "bias_cm": bias},
        "false_alarms_per_scan": 0.0,
        "unmatched_per_scan": 0.0,
    }


def _dataset(near: tuple[float, float, float], avg: tuple[float, float, float]) -> dict:
    """Settings 0-2 with these RMSEs on every nearest / averaging row; textbook Kasa 5 cm."""
    per = {g: {**{s: _r(near[g]) for s in NEAR}, **{s: _r(avg[g]) for s in AVG}} for g in range(3)}
    per[-1] = {s: _r(5.0) for s in (*NEAR, *AVG)}
    return per


def _per() -> dict:
    """Two training sets on which the nearest rows prefer setting 1, the averaging rows setting
    2 and the pooled rows setting 0 (the compromise: 1.5 cm on both), and a held-out set that
    would prefer setting 0 on every row if it trained."""
    return {
        "t1": _dataset(near=(1.5, 0.5, 3.0), avg=(1.5, 3.0, 0.5)),
        "t2": _dataset(near=(1.5, 1.0, 2.6), avg=(1.5, 2.6, 1.0)),
        "held": _dataset(near=(0.1, 9.0, 9.0), avg=(0.1, 9.0, 9.0)),
    }


def test_family_is_the_scanner_model_before_the_first_underscore():
    assert [family_of(s) for s in NEAR] == ["nearest", "nearest"]
    # the averaging rows of --loo-rules keep their family under the @rule suffix
    assert [family_of(s) for s in AVG] == ["averaging", "averaging"]
    with pytest.raises(ValueError, match="unknown scanner model"):
        family_of("sick_0.5deg_noise0cm")


def test_train_score_pools_only_the_familys_visible_rows():
    per = _per()
    # nearest rows of setting 1: RMSE 0.5, 0.5 (t1) and 1.0, 1.0 (t2)
    assert train_score(per, ["t1", "t2"], 1, "nearest") == pytest.approx(1.0 - 0.75 / 3.0)
    assert train_score(per, ["t1", "t2"], 1, "averaging") == pytest.approx(1.0 - 2.8 / 3.0)
    # pooled: every dataset x row weighs the same
    assert train_score(per, ["t1", "t2"], 1) == pytest.approx(1.0 - (0.75 + 2.8) / 2.0 / 3.0)
    # a row without a visible trunk never trains (its objective would be -1, no RMSE)
    per["t1"][1][NEAR[0]] = _r(None, visible=0)
    assert _objective(per["t1"][1][NEAR[0]]) == -1.0
    assert train_score(per, ["t1"], 1, "nearest") == pytest.approx(1.0 - 0.5 / 3.0)
    for s in NEAR:
        per["t1"][1][s] = _r(None, visible=0)
    assert train_score(per, ["t1"], 1, "nearest") == -math.inf


def test_each_family_chooses_on_its_own_rows_where_the_pooled_choice_compromises():
    per = _per()
    train = ["t1", "t2"]
    pooled = max(range(3), key=lambda g: train_score(per, train, g))
    assert pooled == 0
    got = choose_by_family(per, train, range(3), lambda g: True)
    assert {f: c["chosen_index"] for f, c in got.items()} == {"nearest": 1, "averaging": 2}
    assert got["nearest"]["train_score"] == round(train_score(per, train, 1, "nearest"), 3)
    # no compiled settings given: no compiled-only choice
    assert "compiled_only" not in got["averaging"]


def test_the_held_out_dataset_never_trains():
    per = _per()
    before = by_scanner_table(per, "held", ["t1", "t2"], GRID, lambda g: True)
    # the held-out set's own rows changed to favour setting 2 everywhere: the choice stays
    per["held"] = _dataset(near=(9.0, 9.0, 0.1), avg=(9.0, 9.0, 0.1))
    after = by_scanner_table(per, "held", ["t1", "t2"], GRID, lambda g: True)
    assert {f: c["chosen_index"] for f, c in after.items()} == {
        f: c["chosen_index"] for f, c in before.items()
    }


def test_admission_is_shared_and_asked_only_above_the_choice():
    per = _per()
    asked: list[int] = []

    def admitted(g: int) -> bool:
        asked.append(g)
        return g != 1  # setting 1 breaks the simulated targets

    got = choose_by_family(per, ["t1", "t2"], range(3), admitted)
    # nearest: 1 is not admitted, its next best (0 at 1.5 cm against 2 at 2.8) is taken
    assert got["nearest"]["chosen_index"] == 0
    assert got["averaging"]["chosen_index"] == 2
    # nearest asks 1 then 0; averaging asks 2 and stops (0 and 1 rank below it)
    assert asked == [1, 0, 2]
    with pytest.raises(ValueError, match="no admitted"):
        choose_by_family(per, ["t1", "t2"], range(3), lambda g: False)


def test_compiled_only_choice_is_made_for_the_averaging_family_alone():
    per = _per()
    got = by_scanner_table(per, "held", ["t1", "t2"], GRID, lambda g: True, compiled=[0, 1])
    # a first-echo detector runs the numpy path whatever the setting: no compiled-only choice
    assert "compiled_only" not in got["nearest"]
    c = got["averaging"]["compiled_only"]
    assert c["chosen_index"] == 0  # 2 is not compiled; 0 (1.5 cm) beats 1 (2.8 cm)
    assert c["chosen"] == GRID[0]
    assert set(c["held_out"]) == set(AVG)


def test_each_familys_held_out_table_has_its_own_rows_of_its_choice():
    per = _per()
    per["held"][1][NEAR[1]] = _r(0.7, visible=7, bias=-0.3)
    got = by_scanner_table(per, "held", ["t1", "t2"], GRID, lambda g: True)
    near, avg = got["nearest"], got["averaging"]
    assert near["chosen"] == GRID[1] and avg["chosen"] == GRID[2]
    assert set(near["held_out"]) == set(NEAR) and set(avg["held_out"]) == set(AVG)
    row = near["held_out"][NEAR[1]]
    assert (row["rmse_cm_le10m"], row["bias_cm_le10m"], row["visible"]) == (0.7, -0.3, 7)
    assert row["textbook_kasa_rmse_cm_le10m"] == 5.0
    assert avg["held_out"][AVG[0]]["rmse_cm_le10m"] == 9.0  # the held set's setting 2


def test_objectives_by_row_lists_every_setting_per_row_and_none_where_nothing_is_visible():
    per = _per()
    per["t1"][2][AVG[1]] = _r(None, visible=0)
    got = objectives_by_row(per["t1"], range(3))
    assert set(got) == {*NEAR, *AVG}
    assert got[NEAR[0]] == [0.5, round(1 - 0.5 / 3, 3), 0.0]
    assert got[AVG[1]] == [0.5, 0.0, None]


def test_loo_rows_splits_a_folds_score_difference_by_family_and_noise():
    """``loo_rows.py``: each group's share of the difference adds up to the training score's
    difference; the held-out dataset and rows without a visible trunk stay out."""
    from loo_rows import compare

    per = _per()
    per["t2"][0][NEAR[1]] = _r(None, visible=0)
    loo = {
        "training_datasets": ["t1", "t2", "held"],
        "grid_score_by_dataset_scanner": {n: objectives_by_row(per[n], range(3)) for n in per},
    }
    got = compare(loo, "held", 1, 0)
    train = ["t1", "t2"]
    # the pooled training score over the rows both settings count (t2's NEAR[1] dropped)
    assert got["training_datasets"] == train and len(got["rows"]) == 7
    for key in ("by_family", "by_noise_cm", "by_family_noise", "by_dataset_family"):
        shares = sum(v["share_of_difference"] for v in got[key].values())
        assert shares == pytest.approx(got["score_difference"], abs=2e-3)
    near, avg = got["by_family"]["nearest"], got["by_family"]["averaging"]
    assert near["rows"] == 3 and avg["rows"] == 4
    assert near["mean_a_minus_b"] > 0 > avg["mean_a_minus_b"]  # 1 is the nearest rows' setting
    assert set(got["by_noise_cm"]) == {"0.0", "1.0", "3.0"}


def test_baseline_by_scanner_chooses_among_the_first_settings_only():
    """``--baseline-grid N --by-scanner``: each family's choice among settings 0..N-1 (the grid
    before a round's additions), the compiled-only choice too."""
    per = _per()
    got = by_scanner_table(
        per, "held", ["t1", "t2"], GRID, lambda g: True, compiled=[0, 2], n_candidates=2
    )
    assert got["nearest"]["chosen_index"] == 1
    assert got["averaging"]["chosen_index"] == 0  # 2 (its best) is not among the first two
    assert got["averaging"]["compiled_only"]["chosen_index"] == 0
