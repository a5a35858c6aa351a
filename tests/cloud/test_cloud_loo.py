"""The leave-one-dataset-out selection of benchmarks/cloud_loo.py (docs/algorithms/cloud.md
"Leave-one-dataset-out check of the cloud defaults"): the rule is most training cells passed,
then the lowest ring RMSE over the cells every remaining value measured (within 0.05 cm a
tie), then the least intervention; the held-out cloud never enters its own choice."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import cloud_loo
from cloud_loo import OPTIONS, Cell, Outcome, choose, config_key, default_label, loo

ROOT = Path(__file__).resolve().parents[2]
VALUES = [("off", "a"), ("on", "b")]  # least intervention first


def _cell(cloud: str, a: tuple[bool, float | None], b: tuple[bool, float | None]) -> Cell:
    return Cell(cloud, "t", 0, {"a": Outcome(*a), "b": Outcome(*b)})


def test_passes_decide_before_rmse() -> None:
    cells = [_cell("x", (True, 0.1), (True, 0.9)), _cell("y", (False, 0.2), (True, 1.4))]
    pick = choose(cells, VALUES)
    assert pick["chosen"] == "on" and pick["decided_by"] == "passes"
    assert pick["train_passed"] == {"off": 1, "on": 2}


def test_rmse_decides_a_pass_tie_over_common_cells_only() -> None:
    # "on" has the larger error on the cell both measured; its missing error on the other
    # cell is not counted in its favour (nor the 3 cm of "off" there against it)
    cells = [_cell("x", (True, 0.3), (True, 0.6)), _cell("y", (True, 3.0), (True, None))]
    pick = choose(cells, VALUES)
    assert pick["chosen"] == "off" and pick["decided_by"] == "rmse"
    assert pick["train_rmse_cm"] == {"off": 0.3, "on": 0.6}
    cells = [_cell("x", (True, 0.6), (True, 0.3))]
    assert choose(cells, VALUES)["chosen"] == "on"


def test_near_equal_rmse_goes_to_the_least_intervention() -> None:
    # 0.04 cm apart: below the 0.05 cm tie, so the first listed value
    pick = choose([_cell("x", (True, 0.54), (True, 0.50))], VALUES)
    assert pick["chosen"] == "off" and pick["decided_by"] == "tie: least intervention"


def test_the_held_out_cloud_never_enters_its_own_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(OPTIONS, "toy", (("off", {"core_refits": False}), ("on", {})))
    a, b = config_key({"core_refits": False}), "default"

    def cell(cloud: str, off: bool, on: bool) -> Cell:
        return Cell(cloud, "t", 0, {a: Outcome(off, None), b: Outcome(on, None)})

    # "on" wins only on treels_spruce: held out, the others tie and choose "off"
    cells = [
        cell("treels_spruce", False, True),
        cell("treels_pine", True, True),
        cell("lidr_dbh", True, True),
    ]
    res = loo(cells, "toy", "cloud")
    assert res["default"] == "on"
    spruce = res["folds"]["treels_spruce"]
    assert spruce["chosen"] == "off"
    assert (spruce["held_out"]["chosen_passed"], spruce["held_out"]["default_passed"]) == (0, 1)
    assert res["folds"]["lidr_dbh"]["chosen"] == "on"  # spruce in the training set
    assert (res["held_out_passed_loo"], res["held_out_passed_default"]) == (2, 3)
    # by source: both treels clouds held out together, the rest ties -> "off"
    src = loo(cells, "toy", "source")
    assert set(src["folds"]) == {"treels", "lidr_dbh"}
    assert src["folds"]["treels"]["chosen"] == "off"
    assert src["folds"]["treels"]["held_out"]["cells"] == 2


def test_each_option_lists_its_current_default() -> None:
    assert {o: default_label(o) for o in OPTIONS} == {
        "tighter_refits": "on",
        "thin_remeasure": "<=4 slices",
        "core_refits": "on",
        "ransac_lo": "on",
        "slice_fit_window": "3",
        "slice_stub_trim": "off",
        "slice_stub_surface": "off",
        "single_tree_ladder": "on",
        "continues_above": "on",
        "axis_fallback": "off",
        "thick_dbh_slice": "on",
        "thin_refit_points": "off",
        "consensus_floor": "off",
        "consensus_radius_se": "off",
        "guided_taper": "off",
        "ladder_found_rms": "on",
        "sparse_tall_fit": "off",
        "dbh_from": "median",
        "density_slice_points": "on",
        "thin_remeasure_by": "error",
        "ladder_by": "tolerance",
    }
    # every value is a distinct config; the off values of options that are on by default
    # really switch something off (axis_fallback is off by default: its off is the default;
    # slice_fit_window is a width, its current value listed first as the least intervention;
    # thin_remeasure_by's former rule, "slices", is listed first as the least intervention)
    for opt, vals in OPTIONS.items():
        assert len({config_key(ov) for _, ov in vals}) == len(vals), opt
        if default_label(opt) not in ("off", "3", "line", "slices", "tolerance"):
            assert config_key(vals[0][1]) != "default", opt


def test_crop_cells_read_the_error_their_pass_test_reads() -> None:
    row = {
        "dbh_vs_ring_rmse_cm": 3.0,
        "dbh_vs_own_ring_max_cm": -0.4,
        "dbh_vs_tracked_ring_rmse_cm": 0.6,
    }
    assert cloud_loo.cell_error(row, "crop_0.3", single=True) == 0.4
    # a plot's crop: the rings followed up to each detection's height
    assert cloud_loo.cell_error(row, "crop_0.3", single=False) == 0.6
    assert cloud_loo.cell_error(row, "noise_1cm", single=False) == 3.0
    assert cloud_loo.cell_error({"dbh_vs_ring_rmse_cm": None}, "noise_1cm", True) is None


@pytest.mark.slow
def test_quick_run(datasets_dir: Path) -> None:
    """``--quick`` end to end (3 small clouds x 3 transforms; ~3 s CPU): every option has a
    fold per cloud and per source, and the default config passes every quick cell."""
    env = os.environ | {
        "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "benchmarks")]),
        "STEMMAP_DATASETS": str(datasets_dir),
    }
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "cloud_loo.py"), "--quick", "--json"],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    res = json.loads(out.stdout)
    assert res["cells"] == 9
    for opt in OPTIONS:
        r = res["options"][opt]
        assert set(r["loo_cloud"]["folds"]) == set(cloud_loo.QUICK["clouds"])
        assert set(r["loo_source"]["folds"]) == {"treels", "archi", "lidr_dbh"}
        assert r["loo_cloud"]["held_out_passed_default"] == 9
