"""Step split (``step_split``, issue 11, seventeenth round): a candidate that fails the RMS test
cut at its largest range step, its pieces judged as the arcs of ``arc_refit``."""

import numpy as np
import pytest
from tests.scan.test_gaps_refit import _scan as _circles_scan
from tests.scan.test_gaps_refit import _segment

from stemmap.scan._step_split import front_dips, front_spikes, largest_steps, step_refit
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import scan_noise
from stemmap.scan.segment import Segments
from stemmap.types import ScanBatch

#: A 20 cm stem at 5.45 m: exactly 4 beams of 0.5 deg return from it (thin beams).
STEM = (5.45, 0.02, 0.10)


def _stem_and_neighbour(steps):
    """:data:`STEM` and returns of another object on the beams after its last one, each
    ``steps[i]`` farther than the one before (the first relative to the stem's last return):
    one segment (the range-adaptive threshold is 0.1 + 3 r dtheta = 0.24 m there)."""
    batch = _circles_scan([STEM])
    r = batch.ranges[0].copy()
    on = np.flatnonzero(np.isfinite(r))
    assert on.size == 4
    for j, s in enumerate(np.cumsum(steps), start=1):
        r[on[-1] + j] = r[on[-1]] + s
    return _with_ranges(batch, r)


def _with_ranges(batch, r):
    """``batch`` (one scan) with the ranges ``r``."""
    return ScanBatch(
        ranges=r[None, :],
        times=batch.times,
        angle_min=batch.angle_min,
        angle_increment=batch.angle_increment,
        range_max=batch.range_max,
    )


#: A branch behind the stem's silhouette edge: the steps of the TreeLS plot, scan 6 of the
#: sixteenth round (+6.8, +4.0, -0.7 cm; below max_jump = 0.1 m).
BEHIND = (0.068, 0.040, -0.007)


def test_a_stem_with_a_branch_behind_it_is_found_with_step_split():
    batch = _stem_and_neighbour(BEHIND)
    plain = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=False))
    # one candidate of 7 returns that fails the RMS test: no corner, not an arc candidate
    assert len(plain.detect_batch(batch)) == 0
    assert plain.rejected(batch)["reason"] == ["rms"]
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=True))
    obs = det.detect_batch(batch)
    # the stemmap preset's step split since Dec 5 (step_noise_pool="batch": this one scan has
    # no noise estimate, so the configured sigma stands, as with step_split alone)
    assert len(ScanTrunkDetector("stemmap").detect_batch(batch)) == 1
    assert len(obs) == 1
    assert obs.n_points[0] == 4
    # noise-free, 4 returns over ~60 deg of the stem: within 1 cm of the radius
    assert obs.radii[0] == pytest.approx(STEM[2], abs=0.01)
    assert np.hypot(*(obs.centers[0] - STEM[:2])) < 0.02


def _every(det, batch):
    """Every candidate of ``batch`` before the segment filters, the range grid, wrap."""
    return det._candidates(
        batch.ranges,
        batch.angle_min,
        batch.angle_increment,
        batch.range_min,
        batch.range_max,
        None,
        None,
        apply_filters=False,
    )


def _pieces(batch, cfg):
    det = ScanTrunkDetector(cfg)
    every, grid, wrap = _every(det, batch)
    assert len(every) == 1
    got = step_refit(det, every, np.ones(1, dtype=bool), grid, wrap)
    assert len(got) <= 1
    return got[0] if got else None


def test_a_cut_end_is_occluded_only_by_a_nearer_return():
    cfg = DetectorConfig.preset("stemmap", step_split=True)
    # behind: the stem's 4 returns are not partial (min_points = 4 suffices)
    got = _pieces(_stem_and_neighbour(BEHIND), cfg)
    assert got is not None and got.ok.sum() == 1
    i = int(np.flatnonzero(got.ok)[0])
    assert got.segs.counts[i] == 4
    assert not got.segs.occluded_end[i]
    # 22 cm nearer (> occlusion_margin 0.2 m, within the segment): the stem is partial and
    # needs min_points_partial (5) returns, as a segment of its own would
    got = _pieces(_stem_and_neighbour((-0.22, 0.01, 0.01)), cfg)
    assert got is None or not np.any(got.ok & (got.segs.counts == 4))


def test_largest_steps_per_segment():
    # one segment: the largest absolute step is the drop of 30 cm before the 4th return
    segs = _segment([5.0, 5.02, 5.1, 4.8, 4.81])
    assert largest_steps(segs).tolist() == [3]
    one = _segment([5.0])
    assert largest_steps(one).tolist() == [-1]
    # two segments: no step across their boundary (4.8 -> 9.0 m)
    pts = _segment([5.0, 5.02, 5.1, 4.8, 9.0, 9.05, 9.01]).points
    z = np.zeros(2, dtype=bool)
    two = Segments(pts, np.array([0, 4]), np.array([4, 7]), np.array([0, 0]), z, z, z, z)
    assert largest_steps(two).tolist() == [3, 5]


def test_step_split_runs_compiled_but_step_twigs_on_the_numpy_path():
    # the step split and its pooled step noise are compiled (_fast_step_split); dropping every
    # dip (step_twigs) is numpy-only
    for pool in (False, True, "batch"):
        cfg = DetectorConfig.preset("stemmap", step_split=True, step_noise_pool=pool)
        assert ScanTrunkDetector(cfg)._compiled(None, None)
    twigs = DetectorConfig.preset("stemmap", step_split=True, step_twigs=True)
    assert not ScanTrunkDetector(twigs)._compiled(None, None)
    assert ScanTrunkDetector("stemmap")._compiled(None, None)


@pytest.mark.parametrize("pool", [False, True, "batch"])
def test_compiled_step_split_equals_numpy_on_the_pooled_noise_batches(pool):
    # the batches whose pooled step noise decides whether the stem is cut (the two tests
    # above and below), a twig in front (the spike dropped) and the stem alone with its branch
    # behind: the compiled kernel's detections are the numpy pipeline's, bit for bit
    from tests.scan.test_detect_fast import _both, assert_same

    twig = _circles_scan([(4.5, 0.0, 0.09)])
    r = twig.ranges[0].copy()
    r[np.flatnonzero(np.isfinite(r))[1]] -= 0.06
    batches = [
        _with_walls(_stem_and_neighbour(BEHIND)),
        _with_walls(_stem_and_neighbour(BEHIND), n_walls=3, seed=2, per_scan=2),
        _with_ranges(twig, r),
        _stem_and_neighbour(BEHIND),
    ]
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=True, step_noise_pool=pool))
    found = 0
    for batch in batches:
        fast, ref = _both(det, batch)
        assert_same(fast, ref)
        found += int(np.sum(ref.index == 0))
    assert found >= 2  # the step split's pieces were found (the twig, the stem alone)


def test_a_twig_in_front_of_a_stem_is_dropped_not_cut():
    # an 18 cm stem at 4.5 m seen by 5 beams; a twig 6 cm in front of it on the 2nd beam (the
    # TreeLS plot, scan 1 of the sixteenth round: 5.7 cm in front, between the 2nd and 3rd)
    stem = (4.5, 0.0, 0.09)
    batch = _circles_scan([stem])
    r = batch.ranges[0].copy()
    on = np.flatnonzero(np.isfinite(r))
    assert on.size == 5
    r[on[1]] -= 0.06
    batch = _with_ranges(batch, r)
    plain = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=False))
    assert len(plain.detect_batch(batch)) == 0
    assert plain.rejected(batch)["reason"] == ["rms"]
    obs = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=True)).detect_batch(batch)
    # the stem's other 4 returns, one piece: a cut at the twig would leave pieces of 2 and 2
    assert len(obs) == 1
    assert obs.n_points[0] == 4
    assert obs.radii[0] == pytest.approx(stem[2], abs=0.01)
    assert np.hypot(*(obs.centers[0] - stem[:2])) < 0.02


def test_front_spikes_needs_both_neighbours_farther_than_the_limit():
    segs = _segment([5.0, 5.01, 4.94, 5.02, 5.03])
    first = largest_steps(segs)  # +8 cm after the dip
    assert first.tolist() == [3]
    assert np.flatnonzero(front_spikes(segs, first, np.array([0.05]))).tolist() == [2]
    # a limit above the smaller side (7 cm): no spike
    assert not front_spikes(segs, first, np.array([0.075])).any()
    # a dip at the segment's end has one neighbour only
    end = _segment([5.0, 5.01, 5.02, 4.9])
    assert not front_spikes(end, largest_steps(end), np.array([0.01])).any()


def _with_walls(batch, n_walls=5, noise=0.03, seed=1, per_scan=1):
    """``batch`` (one scan) followed by ``n_walls`` scans of ``per_scan`` flat walls each (12
    beams at ~6 m, Gaussian range noise ``noise``). One wall: 8 interior beam triples per scan,
    too few for a noise estimate of its own (16), enough together (the batch's pooled
    estimate). Two: 16 per scan, no run holding more than half, an estimate of its own."""
    rng = np.random.default_rng(seed)
    n = batch.ranges.shape[1]
    rows = [batch.ranges[0]]
    for k in range(n_walls):
        r = np.full(n, np.inf)
        for w in range(per_scan):
            lo = 10 + 20 * k + 50 * w
            r[lo : lo + 12] = 6.0 + rng.normal(0.0, noise, 12)
        rows.append(r)
    return ScanBatch(
        ranges=np.vstack(rows),
        times=np.arange(len(rows), dtype=np.float64),
        angle_min=batch.angle_min,
        angle_increment=batch.angle_increment,
        range_max=batch.range_max,
    )


def test_step_noise_pool_reads_the_step_against_the_batch_noise():
    # the stem with the branch behind (a 6.8 cm step) in a batch whose other scans show 3 cm
    # range noise: no scan has a noise estimate of its own (< 16 interior triples each), the
    # pool of all five reads 2.4 cm (40 wall triples and the stem's 3 noise-free ones; the
    # MAD of so few has a spread of about a quarter), so the step is below 3 sqrt(2) sigma
    # (> 7 cm for any pooled sigma above 1.7 cm) and may be noise: no cut. Read against the
    # configured 1 cm (4.2 cm) it is cut and the stem found, as without the walls.
    batch = _with_walls(_stem_and_neighbour(BEHIND))
    on = DetectorConfig.preset("stemmap", step_split=True, step_noise_pool=True)
    det = ScanTrunkDetector(on)
    every = _every(det, batch)[0]
    pts = every.points
    assert pts.noise is not None and pts.step_noise is not None
    # no scan's own estimate (the configured sigma stands); the pooled one near the walls' 3 cm
    assert np.all(pts.noise == 0.0)
    assert 0.017 < pts.step_noise[0] < 0.04
    configured = DetectorConfig.preset("stemmap", step_split=True, step_noise_pool=False)
    found = ScanTrunkDetector(configured).detect_batch(batch)
    assert int(np.sum(found.index == 0)) == 1
    assert int(np.sum(det.detect_batch(batch).index == 0)) == 0
    # off unless step_split: the points carry no step noise
    off = DetectorConfig.preset("stemmap", step_split=False, step_noise_pool=True)
    plain = ScanTrunkDetector(off)
    got = _every(plain, batch)[0]
    assert got.points.step_noise is None


def test_a_stem_cut_to_4_returns_by_a_nearer_object_stays_partial():
    # the TreeLS plot's held-out misses, scans 10 and 15: a stem seen by 5 beams, its first
    # hidden by a 10 cm stem 1.5 m nearer (another segment: a step far above max_jump). Its 4
    # returns are partial (the beam beside them hit something nearer), so min_points_partial
    # (5) drops them; no step is cut, so step_split cannot help. Even with 4 allowed the
    # 4-return arc without its hidden silhouette fails radius_width_ratio: one side of the
    # circle is unconstrained (and on the simulator min_points_partial 4 lowers the seed-1
    # precision to 0.959 / 0.939, docs/algorithms/scan-detection.md, "step split, fold by
    # fold").
    stem = (4.5, 0.0, 0.09)
    alone = _circles_scan([stem])
    on = np.flatnonzero(np.isfinite(alone.ranges[0]))
    assert on.size == 5
    bearing = alone.angle_min + alone.angle_increment * (on[0] - 1.5)
    batch = _circles_scan([stem, (3.0 * np.cos(bearing), 3.0 * np.sin(bearing), 0.05)])
    assert np.sum(np.abs(batch.ranges[0] - 4.45) < 0.1) == 4
    for extra, reason in (
        ({}, "min_points_partial"),
        ({"min_points_partial": 4}, "radius_width_ratio"),
    ):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=True, **extra))
        obs = det.detect_batch(batch)
        # only the occluder is found
        assert len(obs) == 1 and obs.centers[0][0] < 3.1
        assert det.rejected(batch)["reason"] == [reason]


def test_twigs_on_several_beams_are_no_one_return_spike():
    # the TreeLS plot's scan 7: twigs in front of a stem on several of its beams. The spike
    # rule drops one return nearer than both neighbours at the candidate's largest step;
    # with twigs 6 cm in front on the 1st, 3rd and 5th of 5 beams the largest step's dip is
    # the 3rd return, the other two twig returns stay, and the candidate fails as before.
    # step_twigs does not help either: the stem's edge returns lie 3.7 cm beyond their
    # neighbours, so an end twig 6 cm in front lies 2.4 cm before its neighbour (below the
    # 4.2 cm noise step: no dip), and dropping all three would leave 2 returns.
    stem = (4.5, 0.0, 0.09)
    batch = _circles_scan([stem])
    r = batch.ranges[0].copy()
    on = np.flatnonzero(np.isfinite(r))
    r[on[[0, 2, 4]]] -= 0.06
    batch = _with_ranges(batch, r)
    for extra in ({}, {"step_split": True}, {"step_split": True, "step_twigs": True}):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **extra))
        assert len(det.detect_batch(batch)) == 0
        assert det.rejected(batch)["reason"] == ["rms"]


#: A 30 cm stem at 3 m: 11 beams of 0.5 deg return from it (thin beams).
WIDE = (3.0, 0.0, 0.15)


def _wide_with_twigs(beams, front=0.06):
    """:data:`WIDE` with twigs ``front`` metres in front of its returns on ``beams`` (indices
    among its 11 beams): each twig takes the place of the stem's return on its beam."""
    batch = _circles_scan([WIDE])
    r = batch.ranges[0].copy()
    on = np.flatnonzero(np.isfinite(r))
    assert on.size == 11
    r[on[list(beams)]] -= front
    return _with_ranges(batch, r)


def test_twigs_on_several_beams_are_dropped_with_step_twigs():
    # twigs 6 cm in front on the 3rd, 6th and 9th of 11 beams: each return nearer than both
    # its neighbours by more than the noise step (3 sqrt(2) x 1 cm = 4.2 cm). The spike rule
    # drops the largest step's one; the other two stay and the candidate fails the RMS test.
    # With step_twigs all three go and the stem's other 8 returns are one trunk.
    batch = _wide_with_twigs((2, 5, 8))
    for extra in ({}, {"step_split": True}):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **extra))
        assert len(det.detect_batch(batch)) == 0
        assert det.rejected(batch)["reason"] == ["rms"]
    on = DetectorConfig.preset("stemmap", step_split=True, step_twigs=True)
    obs = ScanTrunkDetector(on).detect_batch(batch)
    assert len(obs) == 1
    assert obs.n_points[0] == 8
    # noise-free returns on the circle: radius and centre within 5 mm
    assert obs.radii[0] == pytest.approx(WIDE[2], abs=0.005)
    assert np.hypot(*(obs.centers[0] - WIDE[:2])) < 0.005
    # off unless step_split (the dips are read at the step threshold of step_split)
    alone = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=False, step_twigs=True))
    assert len(alone.detect_batch(batch)) == 0


def test_a_stem_without_twigs_has_no_front_dip():
    # a solid circle seen from outside: the range rises from its nearest return outwards,
    # so no return lies in front of both neighbours (at the centre the dip is about 2 R / n^2
    # for n returns: < 1 cm here), nor an end in front of its neighbour
    for stem in (WIDE, (4.5, 0.0, 0.09), (2.0, 0.3, 0.4), (8.0, -0.5, 0.3)):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=True))
        every = _every(det, _circles_scan([stem]))[0]
        assert len(every) == 1 and every.counts[0] >= 4
        assert not front_dips(every, np.array([0.01])).any()


def test_front_dips_interior_and_unoccluded_ends():
    # dips of 6 cm at the 2nd and 4th returns, below both neighbours: both (the spike rule
    # takes one, at the largest step)
    segs = _segment([5.0, 4.94, 5.01, 4.95, 5.02, 5.03])
    assert np.flatnonzero(front_dips(segs, np.array([0.042]))).tolist() == [1, 3]
    assert np.flatnonzero(front_spikes(segs, largest_steps(segs), np.array([0.042]))).size == 1
    # a 5 cm dip under a 5.5 cm limit is none
    assert not front_dips(segs, np.array([0.065])).any()
    # an end nearer than its one neighbour: a dip when nothing nearer lies beyond the end
    end = _segment([5.0, 5.01, 5.02, 4.95])
    assert np.flatnonzero(front_dips(end, np.array([0.042]))).tolist() == [3]
    # ... and none when the end is occluded (a nearer return across it) or truncated
    z, t = np.zeros(1, dtype=bool), np.ones(1, dtype=bool)
    for flags in ((z, t, z, z), (z, z, z, t)):
        shut = Segments(end.points, end.start, end.stop, end.scan, *flags)
        assert not front_dips(shut, np.array([0.042])).any()
    # two twigs on consecutive beams are no one-return dip (runs are not dropped)
    run = _segment([5.0, 5.01, 4.95, 4.95, 5.02, 5.03])
    assert not front_dips(run, np.array([0.042])).any()


def test_step_noise_pool_batch_reads_the_step_against_every_scans_noise():
    # the stem with the branch behind (a 6.8 cm step) is the only scan without a noise
    # estimate of its own; the three wall scans (3 cm noise) have theirs. The sparse scans'
    # pool (True) holds the stem's 3 noise-free triples only (< 16): no estimate, the step is
    # read against the configured 1 cm and cut. "batch" reads the estimate over every scan's
    # interior triples (48 wall triples, 3 of the stem), near the walls' 3 cm: the
    # step is below 3 sqrt(2) sigma (> 7 cm for any sigma above 1.7 cm), may be noise: no cut.
    batch = _with_walls(_stem_and_neighbour(BEHIND), n_walls=3, seed=2, per_scan=2)
    cfg = DetectorConfig.preset("stemmap", step_split=True, step_noise_pool="batch")
    det = ScanTrunkDetector(cfg)
    pts = _every(det, batch)[0].points
    assert pts.noise is not None and pts.step_noise is not None
    # the stem's scan has no estimate of its own, the wall scans have theirs (kept)
    assert pts.noise[0] == 0.0 and np.all(pts.noise[1:] > 0.0)
    np.testing.assert_array_equal(pts.step_noise[1:], pts.noise[1:])
    # the stem's scan reads the batch's estimate (scan_noise's batch path, no floor)
    # (in the preset's statistic: the biweight since grid 80)
    want = scan_noise(
        batch.ranges,
        cfg.scan_noise_jump,
        cfg.scan_noise_surface,
        batch_min=0.0,
        batch_scale=cfg.batch_noise_scale,
    )
    assert pts.step_noise[0] == want[0]
    assert 0.017 < pts.step_noise[0] < 0.045
    assert int(np.sum(det.detect_batch(batch).index == 0)) == 0
    # the sparse scans' pool has no estimate for it: cut at the configured sigma and found
    pool = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", step_split=True, step_noise_pool=True)
    )
    assert _every(pool, batch)[0].points.step_noise[0] == 0.0
    assert int(np.sum(pool.detect_batch(batch).index == 0)) == 1


def test_step_noise_pool_takes_false_true_or_batch():
    with pytest.raises(ValueError, match="step_noise_pool"):
        DetectorConfig.preset("stemmap", step_noise_pool="sparse")
