"""The count against textbook Kasa (benchmarks/kasa_count.py; issue 11, sixteenth round)."""

import importlib.util
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def kc():
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "kasa_count.py"
    spec = importlib.util.spec_from_file_location("kasa_count_bench", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _loo(ours, kasa, precision_scored=True):
    """A one-dataset, one-scanner LOO JSON: ours / kasa = (recall, precision, rmse)."""
    sc = "nearest_0.5deg_noise3cm"
    kp = kasa[1] if precision_scored else None
    return {
        "scenario": {"grid": [{}, {"bark_roughness": 0.0}]},
        "held_out": {
            "d": {
                "held_out": {
                    sc: {
                        "recall": ours[0],
                        "precision": ours[1],
                        "visible": 100,
                        "rmse_cm_le10m": ours[2],
                        "bias_cm_le10m": 0.0,
                        "textbook_kasa_recall": kasa[0],
                        "textbook_kasa_precision": kp,
                        "textbook_kasa_rmse_cm_le10m": kasa[2],
                        "textbook_kasa_bias_cm_le10m": 0.0,
                    }
                },
                "added_settings": {"0": {sc: [ours[0], ours[1], ours[2], 0.0]}},
            }
        },
    }


@pytest.mark.parametrize(
    ("ours", "kasa", "trade"),
    [
        ((0.90, 1.0, 2.0), (0.95, 0.80, 9.0), "precision"),  # Kasa's F1 0.87 < ours 0.95
        ((0.90, 1.0, 2.0), (0.95, 1.0, 9.0), "accuracy"),  # F1 higher, 9 cm RMSE
        ((0.90, 1.0, 2.0), (0.95, 1.0, 2.5), "shortfall"),  # better on both, within 3 cm
        ((0.90, 1.0, 12.0), (0.95, 1.0, 9.0), "shortfall"),  # both beyond 3 cm, Kasa less so
    ],
)
def test_each_recall_loss_is_classed_by_what_kasa_pays(kc, ours, kasa, trade):
    (row,) = kc.rows(_loo(ours, kasa), chosen=False, setting="0")
    assert row["recall_loss"] == pytest.approx(0.05)
    assert row["trunks_lost"] == 5
    assert row["trade"] == trade


def test_no_detection_counts_as_f1_zero_and_an_rmse_loss(kc):
    (row,) = kc.rows(_loo((0.0, None, None), (0.5, 0.6, 11.0)), chosen=False, setting="0")
    assert row["ours_f1"] == 0.0 and row["f1_loss"] > 0
    assert row["rmse_loss"] and row["no_detection"]
    t = kc.tally([row])
    assert (t["recall_lower"], t["f1_lower"], t["rmse_larger_or_none"]) == (1, 1, 1)


def test_the_default_is_the_grid_setting_that_equals_the_preset(kc):
    assert kc.default_index(_loo((1, 1, 1), (1, 1, 1))) == "0"
