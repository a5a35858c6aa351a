"""``benchmarks/scan_detection.py``'s verdict on the simulated targets: recall, precision and the
DBH RMSE at <= 5 m each judged on the mean over seeds (``meets_targets.all``; precision's
documented rule since Dec 3, the grid admission's since Dec 5) and on every seed
(``all_every_seed``), this run's seed reported beside them under its own name."""

from __future__ import annotations

import scan_detection as sd  # benchmarks/ is on sys.path (tests/conftest.py)


def _ours(precision: float) -> dict[str, float]:
    return {
        "recall": 0.97,
        "precision": precision,
        "dbh_rmse_cm_le5": 1.1,
        "dbh_rmse_cm_5_10": 1.8,
        "dbh_bias_cm_le5": 0.2,
        "dbh_bias_cm_5_10": -0.3,
    }


SPEED = {"scans_per_second_361": 40000, "latency_ms_1081": 0.2}


def _over_seeds(
    bench: list[float],
    demo: list[float],
    recall: list[float] | None = None,
    dbh: list[float | None] | None = None,
) -> dict:
    """simulated_precision_seeds' fields that the verdict reads (the per-seed precisions,
    recalls (both drives the same) and benchmark DBH RMSEs at <= 5 m, and the precision summary;
    its ``admitted``, the grid's rule of every target, is not read: None)."""
    recall = recall or [0.97] * len(bench)
    dbh = dbh or [1.1] * len(bench)
    rows = [
        {
            "seed": i + 1,
            "benchmark": {"precision": b, "recall": r, "dbh_rmse_cm_0_5": e},
            "demo": {"precision": d, "recall": r},
        }
        for i, (b, d, r, e) in enumerate(zip(bench, demo, recall, dbh, strict=True))
    ]
    out: dict = {"seeds": [r["seed"] for r in rows], "per_seed": rows}
    for drive, v in (("benchmark", bench), ("demo", demo)):
        out[f"{drive}_precision_mean"] = sum(v) / len(v)
        out[f"{drive}_precision_min"] = min(v)
        out[f"{drive}_precision_max"] = max(v)
    out["failing_seeds"] = [r["seed"] for r in rows if min(r["benchmark"]["precision"],
                            r["demo"]["precision"]) < 0.95]  # fmt: skip
    out["admitted"] = None
    return out


def test_a_seed_below_the_target_does_not_fail_a_mean_that_keeps_it():
    # seed 1's benchmark drive 0.9488 (the Dec 5 default), the mean over the seeds 0.9589
    over = _over_seeds([0.9488, 0.97, 0.9579], [0.97, 0.98, 0.975])
    met = sd.meets_targets(_ours(0.9488), SPEED, over, seed=1)
    assert met["precision_this_seed"] is False
    assert met["precision_mean_over_seeds"] is True
    assert not {"precision", "recall", "dbh_rmse_le5"} & set(met)  # no ambiguous key
    assert met["all"] is True and met["failing"] == []
    assert met["precision_every_seed"] is False and met["all_every_seed"] is False
    assert met["failing_every_seed"] == ["precision_every_seed"]
    assert met["failing_seeds"]["precision"] == [1]
    summary = sd.precision_summary(_ours(0.9488), over, seed=1)
    assert summary["this_seed"] == {"seed": 1, "benchmark": 0.9488}
    assert abs(summary["over_seeds"]["benchmark_mean"] - 0.9589) < 1e-9
    assert summary["over_seeds"]["failing_seeds"] == [1]


def test_a_mean_below_the_target_on_either_drive_fails_even_if_this_seed_keeps_it():
    for bench, demo in (([0.96, 0.93], [0.97, 0.97]), ([0.96, 0.96], [0.96, 0.93])):
        over = _over_seeds(bench, demo)
        met = sd.meets_targets(_ours(0.96), SPEED, over, seed=1)
        assert met["precision_this_seed"] is True
        assert met["precision_mean_over_seeds"] is False
        assert met["all"] is False and met["failing"] == ["precision_mean_over_seeds"]
        assert met["failing_every_seed"] == ["precision_every_seed"]


def test_every_other_target_still_decides():
    over = _over_seeds([0.97], [0.97])
    met = sd.meets_targets(_ours(0.97), {**SPEED, "scans_per_second_361": 20000}, over, seed=1)
    assert met["all"] is False and met["failing"] == ["speed_361"]


def test_recall_and_dbh_are_judged_on_the_mean_and_per_seed_alike():
    # seed 2 misses recall (0.94) and the DBH target (1.39 cm, the Dec 5 default's worst seed);
    # the means (0.9567; 1.14 cm) keep both
    over = _over_seeds([0.97] * 3, [0.97] * 3, recall=[0.97, 0.94, 0.96], dbh=[1.03, 1.39, 1.0])
    met = sd.meets_targets(_ours(0.97), SPEED, over, seed=1)
    for target in ("recall", "dbh_rmse_le5"):
        assert met[f"{target}_this_seed"] is True  # seed 1 itself keeps both
        assert met[f"{target}_mean_over_seeds"] is True
        assert met[f"{target}_every_seed"] is False
        assert met["failing_seeds"][target] == [2]
    assert met["all"] is True and met["failing"] == []
    assert met["failing_every_seed"] == ["recall_every_seed", "dbh_rmse_le5_every_seed"]
    v = sd.seed_verdicts(over)
    assert abs(v["dbh_rmse_le5"]["benchmark_mean_cm"] - 1.14) < 1e-9
    assert v["recall"]["benchmark_min"] == 0.94


def test_a_mean_above_the_dbh_target_or_a_seed_without_pairs_fails_the_mean():
    over = _over_seeds([0.97] * 2, [0.97] * 2, dbh=[1.1, 1.35])  # mean 1.225 cm
    met = sd.meets_targets(_ours(0.97), SPEED, over, seed=1)
    assert met["dbh_rmse_le5_mean_over_seeds"] is False
    assert met["failing"] == ["dbh_rmse_le5_mean_over_seeds"]
    over = _over_seeds([0.97] * 2, [0.97] * 2, dbh=[1.1, None])
    v = sd.seed_verdicts(over)["dbh_rmse_le5"]
    assert v["met_on_mean"] is False and v["failing_seeds"] == [2]
