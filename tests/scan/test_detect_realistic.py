"""The 2D detector on simulated stands with what real stands have (issue 11): bark ridges,
elliptic, leaning and buttressed stems, understory and low branches, SICK-class mixed pixels.

The bounds come from the real slices (benchmarks/real_geometry.py, docs/algorithms/
scan-detection.md): held out at 0.5 deg the detector keeps recall 0.82-1.0 with DBH RMSE
1.4-3.5 cm and bias -0.6..+2.8 cm on the real trunks without merged branches (FORTLS, TreeLS
pine and pine plot, both scanner models); these tests check that the simulator's versions of
those features do not push it outside that range, and that the (optional) corner cuts recover
trunks merged with a branch (real lidR slice: recall 0.31 -> 0.69).
"""

import numpy as np
import pytest
from tests.scan._stand_scans import scans, stand, visible_dbh_errors

from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.sim import add_understory, make_trunks_noncircular


def _run(shape=None, understory=None, seed=3, n=60, **overrides):
    """Recall and DBH error (cm) of the stemmap preset on SICK-class scans (0.5 deg, 1 cm
    noise, 0.25 deg footprint with mixed pixels) from ``n`` random poses in a 40-tree stand;
    a trunk counts when it has >= 5 returns within 10 m."""
    st = stand(seed)
    if shape:
        st = make_trunks_noncircular(st, rng=seed + 1, **shape)
    if understory:
        st = add_understory(st, rng=seed + 2, **understory)
    poses, batch, hit = scans(st, seed, n)
    obs = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides)).detect_batch(batch)
    total, e = visible_dbh_errors(st, poses, hit, obs, 5, 10.0)
    return {
        "visible": total,
        "recall": e.size / total,
        "bias": float(e.mean()),
        "rmse": float(np.sqrt(np.mean(e * e))),
    }


@pytest.mark.parametrize(
    ("name", "shape", "rmse_max"),
    [
        # 5 mm bark ridges (the real ring references: 3.6-7 mm about their circles)
        ("bark", {"ellipticity": 0.0, "roughness": 0.0, "bark_rms": 0.005, "n_vertices": 240}, 3.0),
        # leaning up to 15 deg: the horizontal section is <= 3.5 % wider along the lean
        ("lean", {"ellipticity": 0.0, "roughness": 0.0, "lean_deg": 15.0}, 3.0),
        # 8 % elliptic + 2 % out-of-round: a one-sided arc of an ellipse has a radius of
        # curvature between b^2/a and a^2/b (+-16 %), so a single view cannot be better than
        # ~ 2 e D / sqrt(2) ~ 4 cm RMS at D = 35 cm: the bound is 5 cm
        ("ellipse", {"ellipticity": 0.08, "roughness": 0.02}, 5.0),
    ],
)
def test_detector_holds_on_real_bark_shapes(name, shape, rmse_max):
    r = _run(shape)
    assert r["visible"] > 250
    assert r["recall"] >= 0.93, r
    # bark ridges read wide (the fit follows the ridges' envelope): measured +0.95 cm on the
    # half-threshold SICK, +1.52 cm since the sick_lms preset returns at the real LMS200's
    # threshold (0.3, Dec 6), of which +0.5 cm is the preset's half-threshold edge model
    # (+1.02 cm with --edge-hit 0.25 0.38 --edge-hit-window); the real slices held out read
    # -0.6..+2.8 cm (module docstring). The others measure |bias| <= 1.5 cm.
    assert abs(r["bias"]) <= (2.0 if name == "bark" else 1.5), r
    assert r["rmse"] <= rmse_max, r


def test_buttressed_stems_are_found_and_measured_between_dbh_and_lobe_envelope():
    # 15 % lobes: the section's silhouette lies between the DBH circle and r (1 + 0.15), so
    # the bias is >= 0 and below the lobes' 15 % of a 35 cm trunk (5 cm)
    r = _run({"ellipticity": 0.0, "roughness": 0.0, "buttress": 0.15, "n_vertices": 96})
    assert r["recall"] >= 0.93, r
    assert 0.0 <= r["bias"] <= 0.15 * 35.0, r


def test_corner_cuts_recover_trunks_merged_with_a_low_branch():
    branches = {"stems_per_tree": 0.0, "branches_per_tree": 1.0}
    # the corner cuts are an option (off by default: they cost precision in clutter); with
    # convex segments cut at 10 cm, measured 0.60 vs 0.52 of ~260 visible trunks (paired
    # scans); the cut must not cost accuracy on the trunks found
    on = _run(understory=branches, split_corners=True, corner_depth_convex=0.10)
    off = _run(understory=branches, refit_pieces=False)
    assert on["recall"] >= off["recall"] + 0.05, (on, off)
    # RMSE of the trunks found, on / off / split: 2.53 / 2.65 / 2.50 cm on the half-threshold
    # SICK, 3.11 / 3.25 / 3.10 cm at the sick_lms preset's threshold since Dec 6 (0.3, the real
    # LMS200's: the footprint now returns on thinner slivers of the merged branch; 3.08 / 3.42 /
    # 3.07 with the edge model at that threshold, so the scanner, not the edge model); the real
    # slices held out read 1.4-3.5 cm (module docstring)
    assert on["rmse"] <= 3.5 and abs(on["bias"]) <= 1.0, on
    assert on["rmse"] <= off["rmse"], (on, off)
    # the default's validated corner split of rejected candidates (eleventh round): measured
    # 0.57 vs 0.52, same accuracy
    split = _run(understory=branches)
    assert split["recall"] >= off["recall"] + 0.03, (split, off)
    assert split["rmse"] <= 3.5 and abs(split["bias"]) <= 1.0, split
    assert split["rmse"] <= off["rmse"], (split, off)


def test_understory_stems_beside_trunks_keep_most_trunks():
    # thin stems 2-50 cm from the trunk surface merge with it or occlude it: measured 0.84
    r = _run(understory={"stems_per_tree": 1.0, "branches_per_tree": 0.0})
    assert r["recall"] >= 0.8, r
    assert abs(r["bias"]) <= 1.0 and r["rmse"] <= 3.0, r
