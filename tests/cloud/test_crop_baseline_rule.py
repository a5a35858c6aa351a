"""A single tree's crop fails on its own-height ring only where the baseline meets that ring
(``cloud_robustness.baseline_misses_too``; docs/algorithms/cloud.md "archi Tree_1 cropped at
0.3 m: the baseline at the same height").

The crop moves the measurement up by the cut; its yardstick is the cropped cloud's ring at
the height the detection states. Where the shipped cloud, measured by the baseline's preset
at that same absolute height, misses that ring by more than the issue-11 tolerance too, and
the crop's DBH is within the tolerance of the baseline's there, the miss is the detector's at
that height on the data as shipped, not what the export did: listed, not failed -- as a
plot's stem the baseline does not give is not counted against a transform.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from cloud_robustness import SINGLE_TREE_TOL_CM, baseline_misses_too, single_tree_dbh_fails


def test_listed_only_where_the_baseline_misses_too_and_the_crop_did_not_move_it() -> None:
    # archi Tree_1 at 0.3 m: ring 61.33 cm (a swelling), crop 55.78, baseline there 55.78
    assert baseline_misses_too(61.33, 0.5578, 0.5578) == pytest.approx(-5.55)
    # the baseline meets the ring: the crop's miss is the crop's
    assert baseline_misses_too(61.33, 0.5578, 0.6100) is None
    # both miss, but the crop moved the DBH by more than the tolerance: the export did it
    assert baseline_misses_too(61.33, 0.5578, 0.5578 - (SINGLE_TREE_TOL_CM + 0.1) / 100) is None
    # no baseline at that height: nothing to compare, the miss stands
    assert baseline_misses_too(61.33, 0.5578, None) is None


@pytest.mark.slow
def test_archi_tree_1_cropped_at_0_3_m(datasets_dir: Path) -> None:
    """The benchmark's cell: the crop measures 1.6 m above the true base, where the tree
    swells (the ring 61.3 cm, 55.9-56.1 cm 0.2-0.3 m below); the shipped cloud measured at
    that height gives the crop's DBH (within 0.1 cm) and misses the ring by ~5.5 cm too:
    listed, not failed. The crop at 0.8 m meets its ring (no listing)."""
    import cloud_robustness as cr
    from _cloud_refs import CLOUDS
    from stemmap.cloud.stems import StemConfig, detect_stems_file

    bl = cr.run_baseline("archi_tree_1", datasets_dir / CLOUDS["archi_tree_1"])
    rows = {}
    with tempfile.TemporaryDirectory() as td:
        for name, prep, f in cr.transformed_files(bl, ["crop_0.3", "crop_0.8"], Path(td), 0):
            rows[name] = cr.score_run(name, bl, detect_stems_file(f, StemConfig()), prep)
    low, high = rows["crop_0.3"], rows["crop_0.8"]
    assert low["dbh_vs_own_ring_max_cm"] > 5.0  # the crop's miss is real and reported
    assert low["fails"] == [] and low["baseline_misses_too_cm"] < -5.0
    assert high["fails"] == [] and "baseline_misses_too_cm" not in high


def test_a_single_tree_without_a_ring_fails_when_the_export_moves_its_dbh() -> None:
    """aRchi Tree_1 has no full ring at breast height: an export that moves its DBH by more
    than the single-tree tolerance from the shipped tree's fails (it used to pass unjudged);
    a crop is judged by its own-height ring or not at all (its change is taper)."""
    fails = single_tree_dbh_fails
    assert fails("subsample_20", None, 13.49) == [
        "DBH moved 13.49 cm from the shipped tree's (no ring)"
    ]
    assert fails("subsample_20", None, 1.2) == []
    assert fails("crop_0.3", None, 5.0) == []
    assert fails("noise_1cm", 1.88, 0.3) == ["DBH 1.88 cm off the ring"]
    assert fails("noise_1cm", -1.0, 9.0) == []
