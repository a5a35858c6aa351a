"""benchmarks/diameter_rho_real.py: the passes run the default detector, set up for the
scanner as real_geometry.py does, and the per-scan breakdown bins what it is given."""

from __future__ import annotations

from dataclasses import replace

import pytest

from _real_scanning import matched
from diameter_rho_real import SCAN_BANDS, pass_detector, scan_breakdown
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector


def test_pass_detector_is_the_default_detector() -> None:
    # Before Dec 5 the passes ran a bare DetectorConfig() (Kasa fit, no plausibility tests,
    # footprint never set since its fit is not "ours"): +13.6 cm median |mean error| per pass.
    default = ScanTrunkDetector().config
    assert pass_detector("averaging") == default
    near = pass_detector("nearest")
    assert near == replace(default, beam_footprint_deg=0.5)
    assert near == matched(DetectorConfig.preset("stemmap"), "nearest", 0.5)
    assert pass_detector("nearest", None).fit_method == "kasa"


def test_scan_breakdown_bins_and_stats() -> None:
    scans = [
        {"dataset": "a", "range_m": 3.0, "returns": 20, "arc_deg": 100.0, "err": 0.02},
        {"dataset": "a", "range_m": 12.0, "returns": 5, "arc_deg": 40.0, "err": -0.04},
        {"dataset": "b", "range_m": 16.0, "returns": 40, "arc_deg": 130.0, "err": 0.10},
    ]
    out = scan_breakdown(scans)
    assert out["all"]["n"] == 3
    assert out["all"]["bias_cm"] == pytest.approx(100 * 0.08 / 3, abs=0.01)
    rmse = 100 * ((0.0004 + 0.0016 + 0.01) / 3) ** 0.5
    assert out["all"]["rmse_cm"] == pytest.approx(rmse, abs=0.01)
    one = {"n": 1, "bias_cm": -4.0, "rmse_cm": 4.0, "median_abs_cm": 4.0}
    assert out["range_m"]["10-15"] == one
    assert out["range_m"]["15-20"]["n"] == 1
    assert out["returns"]["0-8"]["n"] == 1 and out["returns"]["32-1000"]["n"] == 1
    assert out["arc_deg"]["90-120"]["n"] == 1
    assert out["b"]["all"]["n"] == 1 and out["a"]["all"]["n"] == 2
    # every band of every key appears, empty ones with n = 0
    assert set(out["b"]["range_m"]) == {f"{lo:g}-{hi:g}" for lo, hi in SCAN_BANDS["range_m"]}
    assert out["b"]["range_m"]["0-5"] == {"n": 0}
