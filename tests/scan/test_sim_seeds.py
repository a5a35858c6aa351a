"""Issue 11's simulated targets over seeds (``benchmarks/_scan_sim.py``): the aggregation of
``simulated_precision_seeds`` and the per-tree DBH errors of ``tree_errors``."""

from __future__ import annotations

import math

import numpy as np
import pytest

import _scan_sim as sim  # benchmarks/ is on sys.path (tests/conftest.py)


def _row(recall, precision, rmse5, bias5, n5, demo_recall=0.98, demo_precision=0.97):
    return {
        "benchmark": {
            "recall": recall,
            "precision": precision,
            "dbh_rmse_cm_0_5": rmse5,
            "dbh_bias_cm_0_5": bias5,
            "n_0_5": n5,
            "dbh_rmse_cm_5_10": 1.7,
            "dbh_bias_cm_5_10": 0.1,
            "n_5_10": 10,
        },
        "demo": {"recall": demo_recall, "precision": demo_precision},
        "admitted": min(precision, demo_precision) >= sim.SIM_PRECISION_MIN,
    }


def test_seeds_aggregate_dbh_rmse_bias_and_name_the_failing_seeds(monkeypatch):
    """Mean / min / max per seed, the pooled RMSE weighted by each seed's pairs, and the seeds
    over the 1.2 cm target or under the recall target listed (not only the mean)."""
    table = {
        1: _row(0.98, 0.97, 1.0, -0.1, 100),
        2: _row(0.97, 0.96, 1.3, -0.3, 300),
        3: _row(0.94, 0.99, 1.1, 0.2, 100, demo_recall=0.99),
        4: _row(0.99, 0.98, None, None, 0),  # no pair within 5 m
    }
    monkeypatch.setattr(sim, "simulated_precision", lambda overrides, seed: table[seed])
    got = sim.simulated_precision_seeds({}, [1, 2, 3])
    assert got["benchmark_dbh_rmse_cm_0_5_mean"] == pytest.approx(1.133, abs=1e-3)
    assert got["benchmark_dbh_rmse_cm_0_5_min"] == 1.0
    assert got["benchmark_dbh_rmse_cm_0_5_max"] == 1.3
    pooled = math.sqrt((100 * 1.0**2 + 300 * 1.3**2 + 100 * 1.1**2) / 500)
    assert got["benchmark_dbh_rmse_cm_0_5_pooled"] == pytest.approx(pooled, abs=1e-3)
    assert got["benchmark_dbh_bias_cm_0_5_pooled"] == pytest.approx(-0.16, abs=1e-3)
    assert got["benchmark_dbh_bias_cm_0_5_min"] == -0.3
    assert got["benchmark_dbh_bias_cm_0_5_max"] == 0.2
    assert got["benchmark_dbh_rmse_cm_5_10_mean"] == 1.7
    assert got["dbh_failing_seeds"] == [2]
    assert got["recall_failing_seeds"] == [3]
    assert got["benchmark_recall_max"] == 0.98 and got["demo_recall_min"] == 0.98
    # a seed without pairs within 5 m fails the DBH target and is left out of its statistics
    got = sim.simulated_precision_seeds({}, [1, 4])
    assert got["dbh_failing_seeds"] == [4]
    assert got["benchmark_dbh_rmse_cm_0_5_mean"] == 1.0


def test_tree_errors_reproduce_the_scores_dbh_rmse_per_band():
    """The per-tree errors are a breakdown of ``score``'s pairs, not a second scorer: their
    RMSE, bias and count per band equal the score's; whole + partial = all."""
    from stemmap.scan.detect import ScanTrunkDetector

    run = sim.make_run(60, 3)
    obs = ScanTrunkDetector("stemmap").detect_batch(run.scans)
    s = sim.score(obs, run)
    err = sim.tree_errors(obs, run)
    for lo, hi, key in ((0.0, 5.0, "0_5"), (5.0, 10.0, "5_10")):
        band = (err["range"] >= lo) & (err["range"] < hi)
        e = 100.0 * err["error"][band]
        assert e.size == s[f"n_{key}"] > 0
        assert round(float(np.sqrt(np.mean(e**2))), 3) == s[f"dbh_rmse_cm_{key}"]
        assert round(float(np.mean(e)), 3) == s[f"dbh_bias_cm_{key}"]
    w = sim.worst_trees(err, n=3)
    assert w["n"] == s["n_0_5"] == w["whole_n"] + w["partial_n"]
    assert w["dbh_rmse_cm"] == s["dbh_rmse_cm_0_5"]
    assert len(w["worst"]) == 3
    shares = [r["sse_share"] for r in w["worst"]]
    assert shares == sorted(shares, reverse=True) and sum(shares) <= 1.0 + 1e-9


def test_pair_bounds_put_the_fit_of_whole_trunks_near_its_cramer_rao_bound():
    """``sim_dbh_causes.pair_crlb``: every whole trunk within 5 m has a finite bound, and the
    default's errors on them are about the bound (error / bound RMS 0.97-1.30 on the 400-scan
    and demo drives of seeds 1-20, docs/algorithms/scan-detection.md "Why some seeds miss
    1.2 cm"); partial trunks (an edge hidden) have larger bounds than whole ones.

    On the SICK that returns when half its footprint hits, the scanner the bound was
    calibrated on and the detector's default edge model assumes: at the ``sick_lms`` preset's
    0.3 (Dec 6) the default's errors here are 1.56 x the bound (mean +0.49: the edge model's
    mismatch, which the bound does not model; 1.47 / +0.29 with the edge model at 0.25-0.38),
    scan-detection.md "One return threshold for the simulator and the benchmark"."""
    import sim_dbh_causes as causes
    from stemmap.scan.detect import ScanTrunkDetector

    try:
        sim.set_sim_hit_fraction(0.5)
        run = sim.make_run(120, 3)
    finally:
        sim.set_sim_hit_fraction(None)
    err = sim.tree_errors(ScanTrunkDetector("stemmap").detect_batch(run.scans), run)
    near = err["range"] < 5.0
    bound = np.array(
        [
            causes.pair_crlb(run, int(k), int(j))
            for k, j in zip(err["scan"][near], err["tree"][near], strict=True)
        ]
    )
    whole = err["whole"][near].astype(bool)
    assert whole.sum() >= 30 and np.all(np.isfinite(bound[whole]))
    z = err["error"][near][whole] / bound[whole]
    assert 0.7 < float(np.sqrt(np.mean(z**2))) < 1.5
    part = ~whole & np.isfinite(bound)
    if part.any():
        assert np.median(bound[part]) > np.median(bound[whole])


def test_edge_priors_against_the_true_tangent():
    """``sim_dbh_causes.edge_priors``: where the beam beyond an end returned nothing the true
    tangent is uniform over one beam spacing (RMS about the prior's 1/2 is 1/sqrt(12)); a
    mixed pixel whose footprint holds trunk places it within the prior's std; the ends read as
    mixed pixels whose footprint holds no trunk are counted apart and are off by more."""
    import sim_dbh_causes as causes

    out = causes.edge_priors(sim.make_run(120, 3), {})
    d = out["default"]
    assert d["ends"] >= 50
    assert abs(d["rms_true_minus_prior"] - 1.0 / math.sqrt(12.0)) < 0.06
    m = out["mixed"]
    assert m["ends"] > m["beam_beyond_holds_no_trunk"] > 0
    assert m["rms_true_minus_prior_others"] < m["prior_std"]
    assert m["rms_true_minus_prior_those"] > 2 * m["prior_std"]


def test_the_simulated_scanners_threshold_reaches_both_drives():
    """``set_sim_hit_fraction`` (``--sim-hit-fraction``, Dec 6) gives both simulated drives a
    SICK that returns when that share of its footprint hits, and ``None`` the preset's own;
    the drives already drawn are dropped, not served with the old scanner."""
    from stemmap.sim.scanner import scanner_preset

    own = scanner_preset("sick_lms").min_hit_fraction
    other = 0.5 if own != 0.5 else 0.3  # a threshold that is not the preset's own
    try:
        sim.set_sim_hit_fraction(other)
        assert sim.make_run(2, 1).scanner.min_hit_fraction == other
        assert sim._runs.cache_info().currsize == 0
        assert sim._scanner("sick_lms").min_hit_fraction == other
    finally:
        sim.set_sim_hit_fraction(None)
    assert sim.make_run(2, 1).scanner.min_hit_fraction == own
