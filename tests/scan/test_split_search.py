"""Split search (``split_search``, issue 11, fifteenth round): every cut of a merged candidate
scored from running Kasa (1976) moments, the number of pieces chosen by the BIC, the pieces
validated as the corner split's; a trunk merged with a branch running away behind its
silhouette (no concave corner) is found with its own radius."""

import numpy as np
import pytest
from tests.scan.test_arcs import TRUNK, TRUNK_AND_BRANCH, _branch, _scan

from stemmap.scan._split_search import best_cuts, kasa_prefix, run_score, seen_through
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.segment import Segments
from stemmap.types import ScanBatch

ON = {"split_search": True}
# a 30 cm trunk at 5 m and a branch leaving just beyond its silhouette edge and running away
# behind it: one segment, no concave corner (lidR's view 2, scan-detection-history.md)
TRUNK_AND_BRANCH_BEHIND = [TRUNK, *_branch((5.12, 0.18), (5.5, 0.9))]


def _kasa_direct(x, y):
    """Kasa's fit by least squares: the algebraic RSS over 4 R^2, and the TLS line's RSS."""
    a = np.column_stack((x, y, np.ones_like(x)))
    z = x * x + y * y
    p, *_ = np.linalg.lstsq(a, -z, rcond=None)
    alg = float(np.sum((z + a @ p) ** 2))
    r2 = 0.25 * (p[0] ** 2 + p[1] ** 2) - p[2]
    q = np.column_stack((x - x.mean(), y - y.mean()))
    line = float(np.linalg.eigvalsh(q.T @ q)[0])
    return alg / (4.0 * r2), np.sqrt(r2), line


def test_run_scores_are_the_kasa_and_line_fits_of_every_run():
    rng = np.random.default_rng(3)
    t = np.linspace(0.3, 1.4, 30)
    x = 5.0 + 0.2 * np.cos(t) + rng.normal(0, 0.004, t.size)
    y = 0.2 * np.sin(t) + rng.normal(0, 0.004, t.size)
    x[20:] = np.linspace(5.1, 5.6, 10)  # a straight run: the line scores it
    y[20:] = np.linspace(0.2, 0.5, 10) + rng.normal(0, 0.002, 10)
    xc, yc = x - x.mean(), y - y.mean()
    pre = kasa_prefix(xc, yc)
    for a, b in ((0, 20), (5, 17), (0, 30), (20, 30), (3, 7), (0, 3)):
        score, radius = run_score(pre, a, b)
        if b - a <= 3:
            assert score == 0.0
            continue
        circ, r, line = _kasa_direct(xc[a:b], yc[a:b])
        # (the RSS from differences of moment sums loses ~6 of 16 digits to cancellation)
        assert score == pytest.approx(min(circ, line), rel=1e-4, abs=1e-12)
        assert radius == pytest.approx(r, rel=1e-6)


def test_an_exact_circle_scores_zero():
    t = np.linspace(0, 2.0, 12)
    x, y = 0.3 * np.cos(t), 0.3 * np.sin(t)
    score, radius = run_score(kasa_prefix(x, y), 0, 12)
    assert score == pytest.approx(0.0, abs=1e-14)
    assert radius == pytest.approx(0.3)


def _returns(scene, noise=0.0, seed=0):
    batch = _scan(scene, noise, seed)
    r = batch.ranges[0]
    a = batch.angle_min + batch.angle_increment * np.arange(r.size)
    ok = np.isfinite(r)
    return r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])


def _cuts(x, y, cfg):
    return best_cuts(x, y, 0.01, cfg.min_points, cfg.min_radius, cfg.max_radius, 0.03)


def test_the_cut_falls_between_the_trunk_and_the_branch():
    x, y = _returns(TRUNK_AND_BRANCH_BEHIND)
    # the trunk's returns are those within 2 mm of its circle
    own = np.abs(np.hypot(x - TRUNK[0], y - TRUNK[1]) - TRUNK[2]) < 0.002
    cfg = DetectorConfig.preset("stemmap")
    cuts = _cuts(x, y, cfg)
    assert cuts[1] == -1
    first_foreign = int(np.flatnonzero(~own)[0]) if not own[0] else int(np.flatnonzero(own)[-1]) + 1
    assert cuts[0] == first_foreign


@pytest.mark.parametrize("seed", range(4))
def test_one_noisy_arc_is_not_cut(seed):
    x, y = _returns([TRUNK], noise=0.01, seed=seed)
    assert _cuts(x, y, DetectorConfig.preset("stemmap")) == (-1, -1)


def test_the_trunk_merged_with_a_branch_behind_is_found_with_its_radius():
    batch = _scan(TRUNK_AND_BRANCH_BEHIND)
    # the default since Dec 5 finds it with the step split (the step to the branch behind)
    found = ScanTrunkDetector("stemmap").detect_batch(batch)
    assert len(found) == 1
    assert found.radii[0] == pytest.approx(TRUNK[2], abs=0.005)
    off = {"step_split": False}  # the search alone below
    default = ScanTrunkDetector(DetectorConfig.preset("stemmap", **off))
    # without it the merged candidate is rejected (RMS test); no concave corner to cut at
    assert len(default.detect_batch(batch)) == 0
    assert "rms" in default.rejected(batch)["reason"]
    # the merged outline is convex towards the sensor as a whole (it passed the depth
    # filter): the search cuts it only with split_search_convex (sixteenth round)
    search = ScanTrunkDetector(DetectorConfig.preset("stemmap", **ON, **off))
    assert len(search.detect_batch(batch)) == 0
    convex = DetectorConfig.preset("stemmap", **ON, **off, split_search_convex=True)
    obs = ScanTrunkDetector(convex).detect_batch(batch)
    assert len(obs) == 1
    assert obs.radii[0] == pytest.approx(TRUNK[2], abs=0.005)
    assert np.hypot(*(obs.centers[0] - TRUNK[:2])) < 0.01


def test_a_merge_that_is_not_convex_is_cut_without_split_search_convex():
    # a branch leaving the silhouette edge towards the sensor: the outline turns away from
    # the sensor at the junction (rejected as not convex, depth); without the corner split
    # and the arcs, the search alone finds the trunk
    batch = _scan(TRUNK_AND_BRANCH)
    alone = {"refit_pieces": False, "arc_refit": False}
    assert (
        len(ScanTrunkDetector(DetectorConfig.preset("stemmap", **alone)).detect_batch(batch)) == 0
    )
    obs = ScanTrunkDetector(DetectorConfig.preset("stemmap", **alone, **ON)).detect_batch(batch)
    assert len(obs) == 1
    assert obs.radii[0] == pytest.approx(TRUNK[2], abs=0.005)


def test_a_piece_rougher_than_the_range_noise_fails_the_arcs_chi_square_test():
    # the trunk's 7 returns of the merge behind it, alternately 1.8 cm nearer and farther
    # (1 cm scanner, no scan estimate): the RMS test with its bark allowance passes the
    # piece, the arcs' upper 1 % chi-square test over n - 3 degrees of freedom does not
    batch = _scan(TRUNK_AND_BRANCH_BEHIND)
    r = batch.ranges[0].copy()
    a = batch.angle_min + batch.angle_increment * np.arange(r.size)
    d = np.hypot(r * np.cos(a) - TRUNK[0], r * np.sin(a) - TRUNK[1]) - TRUNK[2]
    own = np.flatnonzero(np.isfinite(r) & (np.abs(d) < 0.002))
    assert own.size == 7
    r[own] += 0.018 * (-1.0) ** np.arange(own.size)
    rough = ScanBatch(
        ranges=r[None, :],
        times=batch.times,
        angle_min=batch.angle_min,
        angle_increment=batch.angle_increment,
        range_max=batch.range_max,
    )
    cfg = {**ON, "split_search_convex": True, "sigma_from_scan": False}
    assert len(ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg)).detect_batch(rough)) == 0
    no_chi2 = DetectorConfig.preset("stemmap", **cfg, arc_chi2=False)
    assert len(ScanTrunkDetector(no_chi2).detect_batch(rough)) == 1


@pytest.mark.parametrize("seed", range(4))
def test_accepted_trunks_are_left_as_they_were(seed):
    batch = _scan([TRUNK, (6.0, 1.5, 0.2)], 0.01, seed)
    off = ScanTrunkDetector("stemmap").detect_batch(batch)
    on = ScanTrunkDetector(DetectorConfig.preset("stemmap", **ON)).detect_batch(batch)
    np.testing.assert_array_equal(on.n_points, off.n_points)
    np.testing.assert_allclose(on.radii, off.radii, rtol=0, atol=1e-12)


def test_a_return_seen_through_the_circle_vetoes_the_piece():
    batch = _scan([TRUNK])
    det = ScanTrunkDetector("stemmap")
    segs = det.candidates(batch.ranges, batch.angle_min, batch.angle_increment)
    assert isinstance(segs, Segments) and len(segs) == 1
    centre = np.array([TRUNK[:2]])
    one = np.zeros(1, dtype=np.int64)
    ok = np.ones(1, dtype=bool)
    sig = np.array([0.01])
    # the trunk's own circle: every return on its near side
    assert not seen_through(segs, one, centre, np.array([TRUNK[2]]), sig, ok, 3.0)[0]
    # a circle 10 cm nearer: the trunk's returns lie behind it, seen through it
    nearer = centre - np.array([[0.1, 0.0]])
    assert seen_through(segs, one, nearer, np.array([TRUNK[2]]), sig, ok, 3.0)[0]


def test_the_option_is_off_by_default_and_runs_on_the_numpy_path():
    assert not DetectorConfig.preset("stemmap").split_search
    assert not DetectorConfig.preset("stemmap").split_search_convex
    assert ScanTrunkDetector("stemmap")._compiled(None, None)
    assert not ScanTrunkDetector(DetectorConfig.preset("stemmap", **ON))._compiled(None, None)
