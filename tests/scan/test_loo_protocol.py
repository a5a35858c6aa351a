"""The LOO's protocol (``real_geometry.py --loo``; issue 11, Dec 6, "Decisions taken where issue 11
is silent" in docs/algorithms.md): by default each fold chooses the setting for first-echo
scanners on the training sets' nearest-return rows and the setting for averaging scanners on
their averaging rows, and scores every held-out row under its own family's choice; ``--pooled``
keeps the single choice on every row (every LOO before Dec 6).

Small synthetic result dicts shaped as the benchmark's (``per[dataset][setting][row]``,
setting -1 = textbook Kasa). With recall = precision = 1 a row's objective is ``1 - RMSE /
3 cm``, so the RMSEs set the ranking exactly; the held-out dataset's RMSEs differ per setting
and family (nearest 7 / 8 / 9 cm, averaging 4 / 5 / 6 cm for settings 0 / 1 / 2), so a held-out
row names the setting it was scored under."""

import importlib.util
import sys
from pathlib import Path

import pytest

from _loo_choice import fold_choice
from _loo_greedy import greedy_table

NEAR = ("nearest_0.5deg_noise0cm", "nearest_1deg_noise3cm")
AVG = ("averaging_0.5deg_noise0cm", "averaging_1deg_noise1cm")
GRID = ({"name": "a"}, {"name": "b"}, {"name": "c"})
HELD_NEAR = (7.0, 8.0, 9.0)
HELD_AVG = (4.0, 5.0, 6.0)


def _r(rmse: float) -> dict:
    return {
        "all": {"recall": 1.0, "precision": 1.0, "visible": 10, "recall_3cm": 1.0},
        "within_10m": {"rmse_cm": rmse, "bias_cm": 0.0},
        "false_alarms_per_scan": 0.0,
        "unmatched_per_scan": 0.0,
    }


def _dataset(near, avg) -> dict:
    per = {g: {**{s: _r(near[g]) for s in NEAR}, **{s: _r(avg[g]) for s in AVG}} for g in range(3)}
    per[-1] = {s: _r(5.0) for s in (*NEAR, *AVG)}
    return per


def _per(avg1=(1.5, 3.0, 0.5), avg2=(1.5, 2.6, 1.0)) -> dict:
    """Two training sets on which the nearest rows prefer setting 1, the averaging rows (by
    default) setting 2 and the pooled rows setting 0 (the compromise), and the held-out set."""
    return {
        "t1": _dataset(near=(1.5, 0.5, 3.0), avg=avg1),
        "t2": _dataset(near=(1.5, 1.0, 2.6), avg=avg2),
        "held": _dataset(near=HELD_NEAR, avg=HELD_AVG),
    }


def _rmse(rows: dict) -> dict:
    return {row: v["rmse_cm_le10m"] for row, v in rows.items()}


def _fold(per=None, **kw) -> dict:
    kw.setdefault("compiled", [0, 1, 2])
    kw.setdefault("admitted", lambda g: True)
    return fold_choice(per or _per(), "held", ["t1", "t2"], GRID, **kw)


def test_default_protocol_scores_each_held_out_row_under_its_own_familys_choice():
    f = _fold()
    assert f["protocol"] == "by_scanner"
    assert f["chosen_by_family"] == {"nearest": 1, "averaging": 2}
    # the nearest rows under setting 1, the averaging rows under setting 2
    assert _rmse(f["held_out"]) == {**dict.fromkeys(NEAR, 8.0), **dict.fromkeys(AVG, 6.0)}
    # the pooled choice (the compromise, setting 0) is reported next to it, not used
    assert f["pooled"]["chosen_index"] == 0
    assert _rmse(f["pooled"]["held_out"]) == {
        **dict.fromkeys(NEAR, 7.0),
        **dict.fromkeys(AVG, 4.0),
    }
    assert "chosen_index" not in f
    # each family's training score is its own rows' (nearest of setting 1: 0.5 and 1.0 cm)
    assert f["train_score_by_family"]["nearest"] == pytest.approx(1.0 - 0.75 / 3.0, abs=5e-4)


def test_pooled_flag_keeps_the_single_choice_as_before():
    f = _fold(pooled=True)
    assert f["protocol"] == "pooled"
    assert f["chosen_index"] == 0 and f["chosen"] == GRID[0]
    assert _rmse(f["held_out"]) == {**dict.fromkeys(NEAR, 7.0), **dict.fromkeys(AVG, 4.0)}
    assert "by_scanner" not in f and "chosen_by_family" not in f
    # --by-scanner adds the per-family choices as a report; the fold's choice stays pooled
    g = _fold(pooled=True, by_scanner=True)
    assert g["chosen_index"] == 0
    assert g["by_scanner"]["nearest"]["chosen_index"] == 1


def test_nearest_choice_does_not_depend_on_the_averaging_model():
    # another averaging model of the benchmark (another return threshold): setting 2 is now far
    # the best on the training sets' averaging rows and the pooled choice follows it, away from
    # what the nearest rows prefer; the nearest family's choice and rows do not move
    before = _fold()
    after = _fold(_per(avg1=(9.0, 9.0, 0.0), avg2=(9.0, 9.0, 0.0)))
    assert before["pooled"]["chosen_index"] == 0 and after["pooled"]["chosen_index"] == 2
    assert after["chosen_by_family"]["nearest"] == before["chosen_by_family"]["nearest"] == 1
    near = list(NEAR)
    assert {r: after["held_out"][r] for r in near} == {r: before["held_out"][r] for r in near}


def test_compiled_only_keeps_the_nearest_choice_and_restricts_the_averaging_one():
    # a first-echo detector runs the numpy path whatever its setting: the nearest family has
    # no compiled-only choice; the averaging family chooses among the compiled settings 0, 1
    f = _fold(compiled=[0, 1])
    c = f["compiled_only"]
    assert c["chosen_by_family"] == {"nearest": 1, "averaging": 0}
    assert _rmse(c["held_out"]) == {**dict.fromkeys(NEAR, 8.0), **dict.fromkeys(AVG, 4.0)}
    assert f["chosen_by_family"] == {"nearest": 1, "averaging": 2}


def test_admission_and_baseline_apply_per_family():
    f = _fold(admitted=lambda g: g != 1)  # the nearest rows' best breaks the simulated targets
    assert f["chosen_by_family"] == {"nearest": 0, "averaging": 2}
    # --baseline-grid 2: the same protocol among settings 0 and 1 only
    b = _fold(baseline=2)["baseline"]
    assert b["protocol"] == "by_scanner"
    assert b["chosen_by_family"] == {"nearest": 1, "averaging": 0}
    assert b["pooled"]["chosen_index"] == 0
    assert _rmse(b["held_out"]) == {**dict.fromkeys(NEAR, 8.0), **dict.fromkeys(AVG, 4.0)}


def test_held_out_dataset_never_trains_under_the_protocol():
    per = _per()
    per["held"] = _dataset(near=(0.1, 9.0, 9.0), avg=(9.0, 9.0, 0.1))  # would pick 0 / 2
    per["held"][1] = {s: _r(0.0) for s in (*NEAR, *AVG)}  # ... or setting 1 everywhere
    assert _fold(per)["chosen_by_family"] == _fold()["chosen_by_family"]


def _real_geometry():
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "real_geometry.py"
    spec = importlib.util.spec_from_file_location("real_geometry_protocol", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["real_geometry_protocol"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(("flags", "pooled"), [([], False), (["--pooled"], True)])
def test_cli_loo_default_is_the_by_scanner_protocol(tmp_path, monkeypatch, capsys, flags, pooled):
    rg = _real_geometry()
    seen = {}

    def fake_loo(*args, **kw):
        seen.update(kw)
        return {"held_out": {}}

    monkeypatch.setattr(rg, "leave_one_out", fake_loo)
    assert rg.main(["--loo", "--datasets", str(tmp_path), *flags]) == 0
    assert seen["pooled"] is pooled
    out = capsys.readouterr().out
    expect = rg.LOO_PROTOCOL_POOLED if pooled else rg.LOO_PROTOCOL_BY_SCANNER
    assert f'"protocol": "{expect}"' in out


def test_cli_help_explains_the_protocol(capsys):
    rg = _real_geometry()
    with pytest.raises(SystemExit):
        rg.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--pooled" in text
    assert "nearest-return rows" in text and "averaging rows" in text


# -- the greedy selection under the protocol -------------------------------------------------

START = {"a": 0, "b": False}


def _greedy_rows(settings):
    """Setting a=1 helps the nearest rows only (3 -> 1.5 cm), b=True the averaging rows only
    (3 -> 0.75 cm) and costs the nearest rows 0.375 cm: pooled, b=True wins the first step."""
    out = []
    for s in settings:
        near = 3.0 - 1.5 * (s["a"] == 1) + 0.375 * bool(s["b"])
        avg = 3.0 - 2.25 * bool(s["b"])
        rows = {**{r: _r(near) for r in NEAR}, **{r: _r(avg) for r in AVG}}
        out.append(dict.fromkeys(("t1", "t2", "held"), rows))
    return out


def test_greedy_selects_one_path_per_family_and_joins_the_held_out_rows():
    args = (["held"], ["t1", "t2", "held"], START, [("a", 1), ("b", True)], _greedy_rows)
    kw = {"eps": 0.0, "folds": ["held"]}
    held_rows = lambda n, rows: _held(rows)  # noqa: E731
    fam = greedy_table(*args, lambda s: True, held_rows, families=("nearest", "averaging"), **kw)
    assert fam["held"]["nearest"]["path"] == [["a", 1]]  # b=True costs the nearest rows
    assert fam["held"]["averaging"]["path"] == [["b", True]]  # a=1 moves no averaging row
    assert fam["held"]["nearest"]["family"] == "nearest"
    assert fam["held"]["held_out"] == {**dict.fromkeys(NEAR, 1.5), **dict.fromkeys(AVG, 0.75)}
    pooled = greedy_table(*args, lambda s: True, held_rows, **kw)
    assert pooled["held"]["path"] == [["b", True], ["a", 1]]
    assert pooled["held"]["family"] == "pooled"


def _held(rows):
    return {row: r["within_10m"]["rmse_cm"] for row, r in rows.items()}
