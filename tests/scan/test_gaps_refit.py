"""Largest-gap cuts of non-convex segments and re-fitted pieces of failed candidates (issue 11,
third round): a trunk merged with a thin stem beside it in one segment is found again."""

import math

import numpy as np
import pytest
from tests.scan.test_detect_fast import _both
from tests.scan.test_stub_runs import GRID_67

from stemmap.errors import ConfigError
from stemmap.scan._refit import corner_cut_pieces, validate_pieces
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.segment import ScanPoints, Segments, largest_gap_cuts, split_largest_gap
from stemmap.types import ScanBatch

INC = math.radians(0.5)


def _scan(circles, n=121):
    """Noise-free thin-beam ranges of circles (cx, cy, r), beams centred on the x axis."""
    a0 = -INC * (n - 1) / 2
    ang = a0 + INC * np.arange(n)
    d = np.column_stack((np.cos(ang), np.sin(ang)))
    r = np.full(n, np.inf)
    for cx, cy, rad in circles:
        b = d @ np.array([cx, cy])
        disc = b * b - (cx * cx + cy * cy - rad * rad)
        t = b - np.sqrt(np.maximum(disc, 0.0))
        r = np.where((disc > 0) & (t > 0), np.minimum(r, t), r)
    return ScanBatch(
        ranges=r[None, :], times=np.zeros(1), angle_min=a0, angle_increment=INC, range_max=30.0
    )


def _segment(r):
    """One segment of returns at ranges ``r`` on consecutive 0.5 degree beams."""
    r = np.asarray(r, dtype=np.float64)
    ang = INC * np.arange(r.shape[0])
    m = r.shape[0]
    pts = ScanPoints(
        np.zeros(m, dtype=np.int64),
        np.arange(m, dtype=np.int64),
        r,
        r * np.cos(ang),
        r * np.sin(ang),
        1,
        m,
        INC,
    )
    z = np.zeros(1, dtype=bool)
    return Segments(pts, np.array([0]), np.array([m]), np.array([0]), z, z, z, z)


def test_largest_gap_cut_and_the_median_gap_ratio():
    # four returns of a trunk at 6.6 m, then two of a nearer stem 0.25 m in front
    segs = _segment([6.57, 6.567, 6.574, 6.628, 6.386, 6.301])
    cuts = largest_gap_cuts(segs, [True])
    assert np.flatnonzero(cuts).tolist() == [4]
    # the junction gap is ~4x the median gap: a ratio of 5 keeps the segment whole
    assert not largest_gap_cuts(segs, [True], ratio=5.0).any()
    assert not largest_gap_cuts(segs, [False]).any()


def test_cut_ends_are_occluded_only_behind_a_nearer_return():
    segs = _segment([6.57, 6.567, 6.574, 6.628, 6.386, 6.301])
    near = split_largest_gap(segs, [True], occlusion_margin=0.2)
    assert near.counts.tolist() == [4, 2]
    # the trunk's cut end is next to a return 0.24 m nearer: occluded; the stem's is not
    assert near.occluded_end.tolist() == [True, False]
    assert near.occluded_start.tolist() == [False, False]
    loose = split_largest_gap(segs, [True], occlusion_margin=0.3)
    assert loose.occluded_end.tolist() == [False, False]


def test_gap_splits_find_a_trunk_merged_with_a_stem_in_front():
    batch = _scan([(5.0, 0.0, 0.1), (4.8, 0.2, 0.05)])
    # (the default's largest consistent arc is off here: the gap split is under test)
    base = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", beam_divergence_deg=0.0, arc_refit=False)
    )
    assert len(base.detect_batch(batch)) == 0
    assert base.rejected(batch)["reason"] == ["depth"]  # one non-convex segment
    det = ScanTrunkDetector(
        DetectorConfig.preset(
            "stemmap", beam_divergence_deg=0.0, gap_splits=1, gap_ratio=2.0, arc_refit=False
        )
    )
    obs = det.detect_batch(batch)
    assert len(obs) == 1
    np.testing.assert_allclose(obs.centers[0], [5.0, 0.0], atol=0.01)
    assert abs(2 * obs.radii[0] - 0.2) < 0.015  # 0.5 deg thin beams: ~+1 cm of edge bias


def test_refit_pieces_recover_a_trunk_whose_segment_fails_the_rms_test():
    batch = _scan([(5.0, 0.0, 0.12), (5.12, 0.19, 0.05)])
    # (the default's corner split leaves this convex candidate alone: no concave corner; the
    # default's step split, since Dec 5, would cut it at its largest step: off here)
    cfg = {
        "beam_divergence_deg": 0.0,
        "refit_split": "gap",
        "refit_validate": False,
        "step_split": False,
    }
    base = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg, refit_pieces=False))
    assert len(base.detect_batch(batch)) == 0
    assert base.rejected(batch)["reason"] == ["rms"]
    assert len(ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg)).detect_batch(batch)) == 1
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", refit_pieces=True, **cfg))
    assert not det._compiled(None, None)  # the gap split: numpy path only
    obs = det.detect_batch(batch)
    assert len(obs) == 1 and obs.index.tolist() == [0]
    np.testing.assert_allclose(obs.centers[0], [5.0, 0.0], atol=0.015)
    # the same diameter (within 5 mm) as the trunk alone gives (whose own thin-beam edge
    # bias is ~-1.6 cm at 0.5 deg without the footprint model)
    alone = base.detect_batch(_scan([(5.0, 0.0, 0.12)]))
    assert len(alone) == 1 and abs(obs.radii[0] - alone.radii[0]) < 0.0025
    # validated: the stem's piece is too short to be judged, so the trunk's piece stands
    det = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", refit_pieces=True, **{**cfg, "refit_validate": True})
    )
    got = det.detect_batch(batch)
    assert len(got) == 1 and np.allclose(got.centers, obs.centers)
    # outlier trimming instead of the gap cut keeps the same trunk here
    det = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", refit_pieces=True, **{**cfg, "refit_split": "outliers"})
    )
    assert len(det.detect_batch(batch)) <= 1


def test_new_options_are_validated():
    with pytest.raises(ConfigError, match="gap_splits"):
        DetectorConfig.preset("stemmap", gap_splits=-1)
    with pytest.raises(ConfigError, match="gap_ratio"):
        DetectorConfig.preset("stemmap", gap_ratio=math.inf)
    with pytest.raises(ConfigError, match="refit_sigmas"):
        DetectorConfig.preset("stemmap", refit_sigmas=0.0)


def test_a_near_arc_bulging_many_sigmas_is_not_straight():
    from stemmap.scan.features import segment_features
    from stemmap.scan.plausibility import REASONS, segment_reasons

    # a 12.9 cm stem at 1.5 m of the TreeLS plot (0.5 deg nearest): 10 returns whose line RMS
    # is within the chi-square bound of 1 cm noise, but whose sagitta is 3.8 cm
    segs = _segment([1.482, 1.456, 1.448, 1.445, 1.448, 1.458, 1.462, 1.465, 1.476, 1.487])
    f = segment_features(segs)
    assert 0.035 < f.depth[0] < 0.04
    off = DetectorConfig.preset("stemmap", straight_depth_sigmas=math.inf)
    assert REASONS[segment_reasons(segs, f, off)[0]] == "straight"
    assert DetectorConfig.preset("stemmap").straight_depth_sigmas == 3.0  # the default keeps it
    for k, want in ((3.0, "kept"), (4.0, "straight")):
        got = segment_reasons(segs, f, DetectorConfig.preset("stemmap", straight_depth_sigmas=k))
        assert REASONS[got[0]] == want
    # a wall (sagitta 0 within the noise) stays straight whatever the setting
    ang = INC * np.arange(20)
    wall = _segment(3.0 / np.cos(ang - ang.mean()))
    fw = segment_features(wall)
    loose = DetectorConfig.preset("stemmap", straight_depth_sigmas=3.0)
    assert REASONS[segment_reasons(wall, fw, loose)[0]] in ("straight", "depth")


def _scan_with_branch(circle, p, q, n=121):
    """:func:`_scan` of one circle plus a straight branch from ``p`` to ``q`` (thin beams)."""
    b = _scan([circle], n)
    r = b.ranges[0].copy()
    ang = b.angle_min + INC * np.arange(n)
    p, q = np.asarray(p, dtype=float), np.asarray(q, dtype=float)
    e = q - p
    for i, a in enumerate(ang):
        d = np.array([math.cos(a), math.sin(a)])
        m = np.column_stack((d, -e))
        t, s = np.linalg.solve(m, p)
        if t > 0 and 0 <= s <= 1:
            r[i] = min(r[i], t)
    return ScanBatch(
        ranges=r[None, :],
        times=np.zeros(1),
        angle_min=b.angle_min,
        angle_increment=INC,
        range_max=30.0,
    )


_CORNERS = {"refit_pieces": True, "refit_split": "corners", "refit_validate": True}


def test_validated_corner_split_finds_a_trunk_merged_with_a_branch():
    # a 30 cm trunk at 3 m and a branch leaving its side towards the sensor: one segment,
    # concave at the junction, rejected as not convex
    batch = _scan_with_branch((3.0, 0.0, 0.15), (3.0, 0.149), (2.7, 0.4))
    # thin beams, on the preset before grid 80 (grid 67): grid 80's first-echo trims
    # (stub_runs, cut_ends) act on thin-beam fits and run on the numpy path
    cfg = {"beam_divergence_deg": 0.0, **GRID_67}
    base = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", **cfg, refit_pieces=False, arc_refit=False)
    )
    assert len(base.detect_batch(batch)) == 0
    assert base.rejected(batch)["reason"] == ["depth"]
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg, **_CORNERS))
    assert det._compiled(None, None)  # the stemmap default since the eleventh round
    assert ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg)).config == det.config
    obs, ref = _both(det, batch)  # the compiled path and the numpy reference agree
    np.testing.assert_array_equal(obs.radii, ref.radii)
    assert len(obs) == 1
    # the trunk's own circle: centre and radius within 5 mm (thin-beam edge bias ~-3 mm)
    np.testing.assert_allclose(obs.centers[0], [3.0, 0.0], atol=0.005)
    assert abs(obs.radii[0] - 0.15) < 0.005


def test_validated_corner_split_keeps_the_verdict_of_two_lobes():
    # two overlapping lobes (a forked stem, a rock's two faces): cut at the notch, both
    # pieces pass as circles on their own; validated, the candidate stays rejected
    batch = _scan([(3.0, 0.0, 0.15), (3.0, 0.22, 0.13)])
    cfg = {
        "beam_divergence_deg": 0.0,
        "sigma": 0.002,
        "corner_depth": 0.01,
        "corner_depth_convex": 0.01,
        "step_split": False,  # the default's since Dec 5: its pieces would count in "pieces"
    }
    loose = {**_CORNERS, "refit_validate": False}
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg, **loose))
    assert len(det.detect_batch(batch)) == 2
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg, **_CORNERS))
    assert len(det.detect_batch(batch)) == 0
    # the rejected list says it was cut and that no piece was kept (it stays dropped)
    rej = det.rejected(batch)
    assert rej["reason"] == rej["failed_test"] and rej["reason"][0] in {"depth", "rms"}
    assert rej["pieces"].tolist() == [2] and rej["pieces_accepted"].tolist() == [0]


def test_rejected_list_names_a_split_parent_whose_pieces_were_kept():
    # the trunk merged with a branch: the whole candidate fails (depth), its corner split's
    # trunk piece is detected, so the parent is listed as split, not as dropped
    batch = _scan_with_branch((3.0, 0.0, 0.15), (3.0, 0.149), (2.7, 0.4))
    cfg = {"beam_divergence_deg": 0.0}
    for kw, reason in (
        ({}, "split"),  # the default: validated corner split
        ({"refit_pieces": False}, "arc"),  # no split: its largest consistent arc
        ({"refit_pieces": False, "arc_refit": False}, "depth"),  # nothing: dropped
    ):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg, **kw))
        n_det = len(det.detect_batch(batch))
        rej = det.rejected(batch)
        assert rej["failed_test"] == ["depth"]
        kept = int(rej["pieces_accepted"][0])
        assert (kept > 0) == (n_det == 1) and int(rej["pieces"][0]) >= kept
        assert rej["reason"] == [reason]


def test_validate_pieces_rules():
    # parent 0: one passing piece and a 2-return piece (min_points) -> accepted;
    # parent 1: a passing piece and a circle-like piece that fails its fit -> vetoed;
    # parent 2: two passing pieces -> vetoed; parent 3: a passing piece and a straight one
    parent = np.array([0, 0, 1, 1, 2, 2, 3, 3])
    codes = np.array([0, 1, 0, 0, 0, 0, 0, 7], dtype=np.int8)
    fit_ok = np.array([True, False, True, False, True, True, True, False])
    ok = validate_pieces(parent, codes, fit_ok)
    assert ok.tolist() == [True, False, False, False, False, False, True, False]


def test_corner_cut_pieces_name_their_parent():
    cfg = DetectorConfig.preset("stemmap", sigma=0.002, corner_depth=0.01)
    flat = _segment([5.0, 5.0, 5.0, 5.0, 5.0, 5.0])
    pieces, parent = corner_cut_pieces(flat, cfg)
    assert pieces.counts.tolist() == [6] and parent.tolist() == [0]
    # a V opening towards the sensor: the deepest return goes, two pieces of the same parent
    notch = _segment([5.0, 5.03, 5.06, 5.09, 5.12, 5.09, 5.06, 5.03, 5.0])
    pieces, parent = corner_cut_pieces(notch, cfg)
    assert pieces.counts.tolist() == [4, 4] and parent.tolist() == [0, 0]
