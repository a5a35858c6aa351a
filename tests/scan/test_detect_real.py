"""End-to-end trunk detection on virtual 2D scans of a real TLS slice (FORTLS, full rings).

The references are the full-ring fits of ``benchmarks/scan_fits_real.py``; the virtual scanner
and the scoring are those of ``benchmarks/scan_detection.py`` (run_real_detection).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "scan_detection.py"


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("scan_detection_bench", BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["scan_detection_bench"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_real_slice_detection_beats_the_published_baseline(datasets_dir):
    res = _bench().run_real_detection(datasets_dir, seed=1)
    assert res is not None
    ours = res["footprint_corrected"]["ours"]
    raw = res["uncorrected"]["ours"]
    kasa = res["uncorrected"]["kasa"]
    # >= 100 arcs of 20 real trunks (22-60 cm) from 17 vantage points
    assert ours["eligible"] >= 100
    assert ours["recall"] >= 0.95 and ours["unmatched_detections"] <= 2
    # the yardstick: a classic detector and textbook Kasa land near 13 cm RMSE on such
    # scans; our default must be several times better (measured 2.1 cm; allow 3.5 cm = 3.7x)
    assert ours["dbh_rmse_cm"] < 3.5 and abs(ours["dbh_bias_cm"]) < 1.0
    # without the footprint correction every fit over-estimates by most of a footprint
    assert raw["dbh_bias_cm"] > 4.0 and kasa["dbh_bias_cm"] > 4.0
