"""Öhman 2007 §2.3: diameter error against distance (benchmarks/ohman_camera.py), at two
distances with three trunks each, simulated frames and scans (no real data set with trunk
diameters and ranges exists; docs/algorithms/vision-fusion.md has the full table)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "ohman_camera.py"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("ohman_camera_bench", BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_paper_line_is_1cm_at_1m_to_6cm_at_10m(bench: ModuleType) -> None:
    assert bench.paper_max_error_cm(1.0) == 1.0
    assert bench.paper_max_error_cm(10.0) == 6.0
    assert bench.paper_max_error_cm(5.5) == 3.5
    assert bench.paper_max_error_cm(12.0) is None


def test_camera_and_laser_within_the_papers_line_at_3_and_6_m(bench: ModuleType) -> None:
    """Measured (seed 0, 3 trunks per distance): ours 0.35 / 0.27 cm max error at 3 / 6 m,
    the laser 0.92 / 1.41 cm, against the paper's 2.11 / 3.78 cm; Öhman's camera method
    under-reads by 6.7 / 12.4 cm on average (its projection locks onto bark edges inside the
    trunk). Fails if the edge diameter, its cylinder conversion, or the laser detector's
    diameter is off by more than the paper's own maximum error."""
    res = bench.run(3, 0, (3.0, 6.0))
    for row in res["rows"]:
        line = row["paper_max_error_cm"]
        ours, laser, ohman = (
            row["camera_ours"],
            row["laser_stemmap_0p5deg"],
            row["camera_ohman2007"],
        )
        assert ours["n"] == laser["n"] == 3 and ours["failed"] == laser["failed"] == 0
        assert ours["max_abs_cm"] < line, row
        assert laser["max_abs_cm"] < line, row
        assert ohman["bias_cm"] < 0.0, row  # under-reads (documented, not a target)
