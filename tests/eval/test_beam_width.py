"""Beam-count widths and the scanner's return threshold (stemmap.eval.beam_width)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.beam_width import (
    beam_tree_detections,
    beams_spanned,
    link_passes,
    usable_detections,
    width_excess,
)
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import scanner_preset, simulate_scans

DELTA = math.radians(0.5)


def _one_trunk_scans(q: float, divergence_deg: float, ranges: np.ndarray, seed: int = 0):
    """Scans of one 40 cm trunk from the given ranges, the sensor looking at it from
    slightly different bearings (random beam phase)."""
    gen = np.random.default_rng(seed)
    stand = Stand(np.array([[0.0, 0.0]]), np.array([0.4]))
    th = gen.uniform(-0.6, 0.6, ranges.size)  # trunk bearing in the sensor frame
    poses = np.column_stack((-ranges, np.zeros(ranges.size), -th))
    model = scanner_preset(
        "sick_lms",
        beam_divergence=math.radians(divergence_deg),
        sub_beams=20,
        min_hit_fraction=q,
        range_noise=0.0,
    )
    scans, hit, _ = simulate_scans(stand, poses, model, rng=seed)
    return scans, hit, model


def test_detector_counts_the_beams_that_hit_and_reports_the_centre():
    r = np.linspace(4.0, 20.0, 60)
    scans, hit, model = _one_trunk_scans(0.5, 0.0, r)  # thin beams: a beam hits or not
    det = beam_tree_detections(scans.ranges, model.angle_min, model.angle_increment)
    assert det.scan.size == r.size  # one detection per scan, nothing else in the stand
    hits = (hit == 0).sum(axis=1)
    np.testing.assert_array_equal(det.beams, hits[det.scan])
    # centre-beam range + half the reported diameter: the trunk centre within a few cm
    # (the reported diameter is N delta r_edge, not the true 40 cm)
    assert np.max(np.abs(det.range - r[det.scan])) < 0.15
    # the diameter is beams x step x mean edge range
    rr = scans.ranges[det.scan]
    first = np.argmax(np.isfinite(rr), axis=1)
    last = rr.shape[1] - 1 - np.argmax(np.isfinite(rr[:, ::-1]), axis=1)
    rows = np.arange(det.scan.size)
    expect = det.beams * DELTA * 0.5 * (rr[rows, first] + rr[rows, last])
    np.testing.assert_allclose(det.diameter, expect, rtol=1e-12)


def test_beams_spanned_inverts_the_detector():
    r = np.linspace(2.5, 40.0, 200)
    scans, _, model = _one_trunk_scans(0.5, 0.25, r, seed=3)
    det = beam_tree_detections(scans.ranges, model.angle_min, model.angle_increment)
    assert det.scan.size > 150
    np.testing.assert_array_equal(beams_spanned(det.range, det.diameter, DELTA), det.beams)


def test_detector_gates():
    # a wall (chord >= 1 m) is no trunk; a return nearer than min_range neither
    rng = np.full((1, 361), np.inf)
    rng[0, 100:140] = 5.0
    rng[0, 200:203] = 0.8
    det = beam_tree_detections(rng, -math.pi / 2, DELTA)
    assert det.scan.size == 0
    with pytest.raises(InputError):
        beam_tree_detections(np.ones(5), 0.0, DELTA)


def _synthetic_passes(e: float, n_pass: int, seed: int):
    """Beam counts of trunks (D 0.15-0.8 m) at 3-20 m: N = floor((Phi + e + phase) / delta)
    with a uniform phase, so E[N delta] = Phi + e exactly."""
    gen = np.random.default_rng(seed)
    pid, rr, ww = [], [], []
    for p in range(n_pass):
        d = gen.uniform(0.15, 0.8)
        r = np.sort(gen.uniform(3.0, 20.0, 30))
        phi = 2 * np.arcsin(0.5 * d / r)
        n = np.floor((phi + e) / DELTA + gen.uniform(0, 1, r.size))
        pid.append(np.full(r.size, p))
        rr.append(r)
        ww.append(n * DELTA)
    return np.concatenate(pid), np.concatenate(rr), np.concatenate(ww)


@pytest.mark.parametrize("e_deg", [0.25, 0.0, -0.2])
def test_width_excess_recovers_a_known_excess(e_deg):
    pid, r, w = _synthetic_passes(math.radians(e_deg), 300, seed=int(10 * e_deg) + 7)
    res = width_excess(pid, r, w, n_boot=300)
    got = math.degrees(res.excess)
    se = math.degrees(res.se)
    # 9,000 counts: the estimate is unbiased up to the asin curvature (< 0.005 deg here);
    # the bootstrap SE is ~0.01 deg, so 4 SE + the curvature bound
    assert abs(got - e_deg) < 4 * se + 0.005, (got, se)
    assert math.degrees(res.ci[0]) < e_deg + 0.005 and e_deg - 0.005 < math.degrees(res.ci[1])
    assert res.passes == 300 and res.detections == pid.size


def test_width_excess_needs_leverage():
    pid = np.zeros(20, dtype=int)
    r = np.full(20, 10.0)  # one range: diameter and excess cannot be told apart
    with pytest.raises(InputError, match="range ratio"):
        width_excess(pid, r, np.full(20, 0.05))


@pytest.mark.parametrize(
    ("q", "expect_deg"),
    [(0.05, 0.25 * (1 - 2 * 0.025)), (0.3, 0.25 * (1 - 2 * 0.275)), (0.5, 0.0125)],
)
def test_simulated_threshold_is_recovered_from_one_trunk(q, expect_deg):
    """The simulated SICK (0.25 deg footprint, 20 sub-beams): a beam returns when
    k = ceil(q 20) sub-beams hit, the k-th from the edge (k - 1/2)/20 of the footprint in, so
    the excess is (1 - 2 (k - 1/2)/20) 0.25 deg: 0.2375 (any hit), 0.1125 (0.3, the
    ``sick_lms`` preset's threshold since Dec 6, the real LMS200's), 0.0125 (half)."""
    r = np.random.default_rng(5).permutation(np.linspace(3.0, 12.0, 600))  # >= 3.8 beams
    scans, _, model = _one_trunk_scans(q, 0.25, r, seed=11)
    det = beam_tree_detections(scans.ranges, model.angle_min, model.angle_increment)
    # ten passes of 60 scans each, as a drive would give
    pid = det.scan // 60
    res = width_excess(pid, det.range, det.beams * DELTA, n_boot=200)
    assert abs(math.degrees(res.excess) - expect_deg) < 0.04, res
    assert abs(math.degrees(res.excess) - expect_deg) < 4 * math.degrees(res.se) + 0.01


def test_link_passes_follows_trunks_and_breaks_at_gaps():
    # two trunks 5 m apart, seen in frames 0-9 with 5 cm jitter; trunk B missing in 3-8
    gen = np.random.default_rng(0)
    frames, xy, truth = [], [], []
    for f in range(10):
        for t, c in enumerate(([0.0, 0.0], [5.0, 0.0])):
            if t == 1 and 3 <= f <= 8:
                continue
            frames.append(f)
            xy.append(np.asarray(c) + gen.normal(0, 0.05, 2))
            truth.append(t)
    ids = link_passes(np.array(frames), np.array(xy), gate=1.0, max_gap=3)
    truth_a = np.array(truth)
    assert np.unique(ids[truth_a == 0]).size == 1  # one pass for A
    # B: frames 0-2 and 9 are 7 scans apart > max_gap: two passes
    assert np.unique(ids[truth_a == 1]).size == 2
    assert not set(ids[truth_a == 0]) & set(ids[truth_a == 1])
    with pytest.raises(InputError):
        link_passes(np.array([1, 0]), np.zeros((2, 2)))


def test_usable_detections_keeps_ranges_with_two_beams():
    r = np.array([5.0, 10.0, 17.0, 18.0, 30.0, 1.5])
    d = 0.3  # spans 0.3 / (r delta) beams: >= 2 up to 17.19 m
    w = d / r
    keep = usable_detections(np.zeros(6, dtype=int), r, w, DELTA, min_beams=2.0, min_range=2.0)
    np.testing.assert_array_equal(keep, [True, True, True, False, False, False])


def test_usable_detections_max_beams_uses_the_pass_not_the_count():
    r = np.array([3.0, 5.0, 8.0, 12.0])
    d = 0.3  # predicted span 11.5, 6.9, 4.3, 2.9 beams
    w = np.array([12, 5, 4, 3]) * DELTA  # the counts themselves do not decide
    w = w * (d / np.median(w * r))  # the pass diameter is 0.3 m
    keep = usable_detections(np.zeros(4, dtype=int), r, w, DELTA, min_beams=2.0, max_beams=8.0)
    np.testing.assert_array_equal(keep, [False, True, True, True])
