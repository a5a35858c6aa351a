"""Properties of the detection metrics that the first tests left open (found by mutation
testing, docs/reliability.md "Mutation testing"): per-bin statistics, half-open bins, the
single-frame matching, counts pooled over frames, the non-tree rules (extent, field of view,
range), the defaults of the per-scan scorer, and the input checks' messages."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval import detectable_trees, detection_metrics, scan_detection_metrics
from stemmap.eval.detection import score_scan_detections
from stemmap.types import StemObservations


def _obs(index, xy, diam):
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    n = xy.shape[0]
    return StemObservations(
        centers=xy,
        radii=np.asarray(diam, dtype=float) / 2,
        covs=np.zeros((n, 3, 3)),
        n_points=np.zeros(n, dtype=np.int64),
        arc_deg=np.zeros(n),
        widths=np.zeros(n),
        quality=np.ones(n),
        index=np.asarray(index, dtype=np.int64),
        times=np.zeros(n),
    )


def test_every_field_of_a_range_bin_and_the_json_form():
    # truth ranges given directly: 1 and 2 m (both found), 7 m (missed), 12 m (found)
    truth = np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [6.0, 0.0]])
    tdiam = np.array([0.30, 0.20, 0.40, 0.25])
    det = truth[[0, 1, 3]] + [[0.0, 0.3], [0.0, 0.4], [0.0, 0.1]]
    ddiam = np.array([0.34, 0.18, 0.25])
    m = detection_metrics(det, ddiam, truth, tdiam, gate=0.5, truth_range=[1.0, 2.0, 7.0, 12.0])
    b = {(r.range_lo, r.range_hi): r for r in m.by_range}
    near = b[0.0, 5.0]
    assert (near.n_truth, near.ta, near.fr) == (2, 2, 0)
    assert near.recall == 1.0
    assert near.center_rmse == pytest.approx(math.sqrt((0.3**2 + 0.4**2) / 2))
    assert near.diameter_rmse == pytest.approx(math.sqrt((0.04**2 + 0.02**2) / 2))
    assert near.diameter_bias == pytest.approx((0.04 - 0.02) / 2)
    mid = b[5.0, 10.0]
    assert (mid.n_truth, mid.ta, mid.fr, mid.recall) == (1, 0, 1, 0.0)
    far = b[10.0, 15.0]
    assert (far.n_truth, far.ta, far.fr, far.recall) == (1, 1, 0, 1.0)
    assert far.center_rmse == pytest.approx(0.1) and far.diameter_bias == pytest.approx(0.0)
    assert m.n_detections == 3
    assert m.diameter_mae == pytest.approx((0.04 + 0.02 + 0.0) / 3)
    d = near.to_dict()
    assert d["n_truth"] == 2 and d["recall"] == 1.0
    assert d["center_rmse"] == pytest.approx(near.center_rmse)
    empty = b[15.0, math.inf].to_dict()
    assert empty["recall"] is None and empty["range_hi"] is None  # inf -> null too
    # accuracy = (TA + TR) / (TA + TR + FA + FR) = 3 / 4 (no clutter: TR = 0)
    assert m.accuracy == pytest.approx(0.75)
    assert m.to_dict()["accuracy"] == pytest.approx(0.75)
    assert isinstance(m.to_dict()["by_range"], list)


def test_bins_are_half_open_at_both_ends_for_found_and_missed_trees():
    truth = np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [6.0, 0.0]])
    det = truth[[0, 1]]
    # found trees at exactly 0 and 5 m, missed trees at exactly 0 and 5 m
    m = detection_metrics(
        det, [0.3] * 2, truth, [0.3] * 4, gate=0.5, truth_range=[0.0, 5.0, 0.0, 5.0]
    )
    b = {(r.range_lo, r.range_hi): r for r in m.by_range}
    assert (b[0.0, 5.0].ta, b[0.0, 5.0].fr) == (1, 1)
    assert (b[5.0, 10.0].ta, b[5.0, 10.0].fr) == (1, 1)
    # two edges make one bin
    one = detection_metrics(det, [0.3] * 2, truth, [0.3] * 4, gate=0.5, range_bins=(0.0, 100.0))
    assert len(one.by_range) == 1 and one.by_range[0].n_truth == 4
    with pytest.raises(InputError, match="strictly increasing"):
        detection_metrics(det, [0.3] * 2, truth, [0.3] * 4, gate=0.5, range_bins=(0, 5, 5, 10))


def test_sensor_position_sets_the_ranges_and_truth_range_overrides_it():
    truth = np.array([[0.0, 0.0], [10.0, 0.0]])
    m = detection_metrics(truth, [0.3, 0.3], truth, [0.3, 0.3], gate=0.5, sensor_xy=[20.0, 0.0])
    b = {(r.range_lo, r.range_hi): r.ta for r in m.by_range}
    assert b[10.0, 15.0] == 1 and b[15.0, math.inf] == 1 and b[0.0, 5.0] == 0
    m2 = detection_metrics(
        truth, [0.3, 0.3], truth, [0.3, 0.3], gate=0.5, sensor_xy=[20.0, 0.0], truth_range=[1, 6]
    )
    b2 = {(r.range_lo, r.range_hi): r.ta for r in m2.by_range}
    assert b2[0.0, 5.0] == 1 and b2[5.0, 10.0] == 1
    with pytest.raises(InputError, match=r"^truth_range has 1 values"):
        detection_metrics(truth, [0.3, 0.3], truth, [0.3, 0.3], gate=0.5, truth_range=[1.0])


def test_f1_is_the_harmonic_mean_whatever_the_order_of_precision_and_recall():
    truth = np.array([[0.0, 0.0], [5.0, 0.0], [9.0, 0.0]])
    # precision 1/2 < recall 1/3? no: 1 TA, 1 FA, 2 FR -> precision 0.5, recall 1/3
    m = detection_metrics([[0, 0], [20, 20]], [0.3] * 2, truth, [0.3] * 3, gate=0.5)
    assert m.f1 == pytest.approx(2 * 0.5 * (1 / 3) / (0.5 + 1 / 3))
    # precision 0.5 < recall 1
    m = detection_metrics([[0, 0], [20, 20]], [0.3] * 2, truth[:1], [0.3], gate=0.5)
    assert m.f1 == pytest.approx(2 / 3)
    # precision = recall = 0.5: their sum is exactly 1
    m = detection_metrics([[0, 0], [20, 20]], [0.3] * 2, truth[:2], [0.3] * 2, gate=0.5)
    assert m.f1 == pytest.approx(0.5)


def test_single_frame_result_keeps_its_matching():
    truth = np.array([[0.0, 0.0], [3.0, 0.0]])
    m = detection_metrics([[3.1, 0.0], [0.0, 0.1]], [0.3] * 2, truth, [0.3] * 2, gate=0.5)
    assert m.matching is not None
    assert sorted(map(tuple, m.matching.pairs.tolist())) == [(0, 1), (1, 0)]


def test_inputs_in_other_shapes_and_types_give_the_same_result():
    truth = np.array([[0.0, 0.0], [3.0, 0.0], [6.0, 0.0]])
    det = np.array([[0.1, 0.0], [3.0, 0.1]])
    ref = detection_metrics(
        det, [0.32, 0.18], truth, [0.3, 0.2, 0.4], gate=0.5, truth_eligible=[True, False, True]
    )
    col = detection_metrics(
        det,
        [[0.32], [0.18]],
        truth,
        [[0.3], [0.2], [0.4]],
        gate=0.5,
        truth_eligible=[[1], [0], [1]],
    )
    for k in ("ta", "fa", "fr", "n_ignored", "diameter_bias", "diameter_rmse", "center_rmse"):
        assert getattr(col, k) == pytest.approx(getattr(ref, k)), k
    assert (ref.ta, ref.fr, ref.n_ignored) == (1, 1, 1)
    # an empty detection list in any spelling
    for empty in ([], np.zeros((0, 2)), np.zeros(0)):
        e = detection_metrics(empty, [], truth, [0.3] * 3, gate=0.5)
        assert (e.ta, e.fa, e.fr, e.n_detections) == (0, 0, 3, 0)


def test_empty_range_bins_give_nan_without_numpy_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = detection_metrics([[0, 0]], [0.3], [[0, 0]], [0.3], gate=0.5)
        z = detection_metrics(np.zeros((0, 2)), [], np.zeros((0, 2)), [], gate=0.5)
    assert math.isnan(m.by_range[1].center_rmse) and math.isnan(m.by_range[1].diameter_bias)
    assert math.isnan(z.center_rmse) and math.isnan(z.diameter_mae) and math.isnan(z.center_mean)


@pytest.mark.parametrize("gate", [-1.0, math.inf, math.nan, 0.0])
def test_gate_must_be_finite_and_positive(gate):
    with pytest.raises(InputError, match="finite distance > 0 m"):
        detection_metrics([[0, 0]], [0.3], [[0, 0]], [0.3], gate=gate)
    with pytest.raises(InputError, match="finite distance > 0 m"):
        score_scan_detections(
            _obs([0], [[0, 0]], [0.3]),
            trees_xy=[[0, 0]],
            diameters=[0.3],
            sensor_poses=[[0, 0, 0]],
            hit_ids=[[0] * 5],
            gate=gate,
        )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"det_xy": [[0, 0, 0]]}, r"^det_xy must have shape"),
        ({"det_xy": [[1.0]]}, r"^det_xy must have shape"),
        ({"truth_xy": [[0, 0, 0]]}, r"^truth_xy must have shape"),
        ({"det_diam": [0.3, 0.2]}, r"^det_diam has 2 values but 1 positions"),
        ({"truth_diam": [0.3, 0.2]}, r"^truth_diam has 2 values"),
        ({"nontree_xy": [[0, 0, 0]]}, r"^nontree_xy must have shape"),
        ({"nontree_xy": [[5, 0]], "nontree_extent": [0.1, 0.2]}, r"^nontree_extent has 2"),
    ],
)
def test_messages_name_the_argument(kwargs, match):
    args = {"det_xy": [[0, 0]], "det_diam": [0.3], "truth_xy": [[0, 0]], "truth_diam": [0.3]}
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        detection_metrics(
            args.pop("det_xy"),
            args.pop("det_diam"),
            args.pop("truth_xy"),
            args.pop("truth_diam"),
            gate=0.5,
            **args,
        )


def test_non_tree_claimed_within_gate_plus_extent_inclusive():
    truth = np.array([[0.0, 0.0]])
    # a false alarm 1.0 m from a bush of extent 0.5 with gate 0.5: exactly at the limit
    at = detection_metrics(
        [[0, 0], [6.0, 0]],
        [0.3] * 2,
        truth,
        [0.3],
        gate=0.5,
        nontree_xy=[[5.0, 0]],
        nontree_extent=[0.5],
    )
    assert (at.fa, at.tr, at.n_nontree) == (1, 0, 1)
    # 0.75 m away: only the extent makes it a claim
    near = detection_metrics(
        [[0, 0], [0.0, 5.75]],
        [0.3] * 2,
        truth,
        [0.3],
        gate=0.5,
        nontree_xy=[[0.0, 5.0]],
        nontree_extent=[0.5],
    )
    assert near.tr == 0
    bare = detection_metrics(
        [[0, 0], [0.0, 5.75]], [0.3] * 2, truth, [0.3], gate=0.5, nontree_xy=[[0.0, 5.0]]
    )
    assert bare.tr == 1
    # three objects without extents; the false alarm sits on the one at (-5, 2)
    three = detection_metrics(
        [[0, 0], [-5.0, 2.2]],
        [0.3] * 2,
        truth,
        [0.3],
        gate=0.5,
        nontree_xy=[[5.0, 2.0], [0.0, 7.0], [-5.0, 2.0]],
    )
    assert (three.tr, three.n_nontree) == (2, 3)


def test_detectable_trees_boundaries_and_defaults():
    hit = np.array([0] * 5 + [1] * 4)
    assert detectable_trees(hit, 2).tolist() == [True, False]  # default min_returns = 5
    r = [15.0, 1.0]
    assert detectable_trees(hit, 2, min_returns=1, truth_range=r, max_range=15.0).tolist() == [
        True,
        True,
    ]
    assert detectable_trees(hit, 2, min_returns=1, max_range=1.0).tolist() == [True, True]
    d = [0.1, 0.3]
    assert detectable_trees(hit, 2, min_returns=1, diameters=d, min_diameter=0.1).all()
    assert detectable_trees(hit, 2, min_returns=1, min_diameter=5.0).all()
    with pytest.raises(InputError, match=r"shape \(N,\) or \(S, N\)"):
        detectable_trees(np.zeros((1, 1, 3), dtype=int), 2)


# --- per-scan scoring on a hand-built single scan ------------------------------------------
#
# Sensor at the origin looking along +x, 180-degree field of view (bearings -90..+90 deg).
# T0 (3, 0) 5 returns, found 0.4 m off -> TA.     T1 (0, 6) DBH exactly 0.10, 5 returns,
# reported 0.6 m off -> FA + FR at gate 0.5.        T2 (15.5, 0) 5 returns: beyond 15 m.
# T3 (-4, 0) 4 returns: too few.                    A false alarm at (0, -3.7) lies 0.7 m from
# bush B0 (0, -3; extent 0.3; bearing exactly -90 deg): claimed (0.7 <= 0.5 + 0.3).
# B1 (-3, 0) is behind the scanner; B2 (20, 0) is beyond 15 m; B3 (0, 2) at exactly +90 deg
# and B4 (15, 0) at exactly 15 m count and are not claimed.

TREES = np.array([[3.0, 0.0], [0.0, 6.0], [15.5, 0.0], [-4.0, 0.0]])
DIAMS = np.array([0.3, 0.10, 0.3, 0.3])
HITS = np.array([[0] * 5 + [1] * 5 + [2] * 5 + [3] * 4 + [-1] * 3])
BUSHES = np.array([[0.0, -3.0], [-3.0, 0.0], [20.0, 0.0], [0.0, 2.0], [15.0, 0.0]])
EXTENT = np.full(5, 0.3)
FOV = (-math.pi / 2, math.pi / 2, 0.01)
DETS = _obs([0, 0, 0], [[3.4, 0.0], [0.0, 6.6], [0.0, -3.7]], [0.3, 0.1, 0.2])


def _score(**kw):
    return _score_dets(DETS, **kw)


def test_score_scan_detections_defaults_and_non_tree_rules():
    m = _score()
    assert (m.ta, m.fa, m.fr, m.n_truth_eligible) == (1, 2, 1, 2)
    assert (m.tr, m.n_nontree) == (2, 3)
    assert m.gate == 0.5 and m.n_frames == 1 and m.n_detections == 3
    assert m.center_rmse == pytest.approx(0.4)
    # each default matters: a wider gate, more returns, a longer range, a thicker minimum
    assert _score(gate=1.5).ta == 2
    assert _score(min_returns=6).n_truth_eligible == 0
    assert _score(max_range=16.0).fr == 2
    assert _score(min_diameter=0.11).n_truth_eligible == 1
    # without the extents the false alarm claims nothing; without a field of view B1 counts
    assert _score(nontree_extent=None).tr == 3
    assert (_score(fov=None).n_nontree, _score(fov=None).tr) == (4, 3)
    assert _score(nontree_xy=None, nontree_extent=None).n_nontree == 0
    # extents omitted for five objects: zero extent each
    assert _score(nontree_extent=None).n_nontree == 3


def test_score_scan_detections_full_circle_field_of_view():
    inc = 0.25
    # a 360-degree scanner spans 2 pi - inc (no duplicate beam): every bearing counts, also
    # the one in the last gap (B1, straight behind at +pi)
    full = _score(fov=(-math.pi, math.pi - inc, inc))
    assert full.n_nontree == 4
    # a scanner short of the full circle by 2.5 beams does not see straight behind
    part = _score(fov=(-math.pi, math.pi - 2.5 * inc, inc))
    assert part.n_nontree == 3


def test_score_scan_detections_rotated_pose_and_pooled_frames():
    # the same scene seen from a sensor at (10, 5) heading 90 deg, as a second scan
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    R = np.array([[c, -s], [s, c]])
    world = TREES @ R.T + [10.0, 5.0]
    bushes = BUSHES[:3] @ R.T + [10.0, 5.0]  # not those exactly on the limits
    dets = _obs([1, 1, 1], DETS.centers, [0.3, 0.1, 0.2])
    one = score_scan_detections(
        dets,
        trees_xy=world,
        diameters=DIAMS,
        sensor_poses=[[1e3, 1e3, 0.0], [10.0, 5.0, math.pi / 2]],
        hit_ids=np.vstack((np.full(HITS.shape[1], -1), HITS)),
        nontree_xy=bushes,
        nontree_extent=EXTENT[:3],
        fov=FOV,
    )
    assert (one.ta, one.fa, one.fr, one.tr, one.n_nontree) == (1, 2, 1, 0, 1)
    # two scans pooled: counts add up, no single matching, per-frame counts kept
    both = score_scan_detections(
        _obs([0, 0, 0, 1, 1, 1], np.vstack((DETS.centers, DETS.centers)), [0.3, 0.1, 0.2] * 2),
        trees_xy=TREES,
        diameters=DIAMS,
        sensor_poses=[[0.0, 0.0, 0.0]] * 2,
        hit_ids=np.vstack((HITS, HITS)),
        nontree_xy=BUSHES,
        nontree_extent=EXTENT,
        fov=FOV,
    )
    assert (both.ta, both.fa, both.fr, both.tr, both.n_nontree) == (2, 4, 2, 4, 6)
    assert both.n_detections == 6 and both.n_frames == 2 and both.matching is None
    assert both.frame_counts.tolist() == [[1, 2, 1], [1, 2, 1]]
    # ineligible matches are counted over both frames too
    both_ign = score_scan_detections(
        _obs([0, 1], [[-4.0, 0.0], [-4.0, 0.0]], [0.3, 0.3]),
        trees_xy=TREES,
        diameters=DIAMS,
        sensor_poses=[[0.0, 0.0, 0.0]] * 2,
        hit_ids=np.vstack((HITS, HITS)),
    )
    assert both_ign.n_ignored == 2 and both_ign.fa == 0


def test_score_scan_detections_without_scans():
    m = score_scan_detections(
        _obs([], np.zeros((0, 2)), []),
        trees_xy=TREES,
        diameters=DIAMS,
        sensor_poses=np.zeros((0, 3)),
        hit_ids=np.zeros((0, 5), dtype=int),
    )
    assert (m.ta, m.fa, m.fr, m.n_frames) == (0, 0, 0, 0)
    assert m.frame_counts is not None and m.frame_counts.shape == (0, 3)
    assert m.matching is None and math.isnan(m.recall)
    for v in (m.center_rmse, m.diameter_rmse, m.diameter_bias, m.diameter_mae):
        assert math.isnan(v)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"sensor_poses": [[0.0, 0.0]]}, r"^sensor_poses must have shape \(S, 3\)"),
        ({"hit_ids": np.vstack((HITS, HITS))}, r"^hit_ids must have shape \(S, N\)"),
        ({"trees_xy": [[0, 0, 0]]}, r"^trees_xy must have shape"),
        ({"diameters": [0.3]}, r"^diameters has 1 values"),
        ({"nontree_xy": [[0, 0, 0]]}, r"^nontree_xy must have shape"),
        ({"nontree_extent": [0.3]}, r"^nontree_extent has 1 values"),
    ],
)
def test_score_scan_detections_messages(kwargs, match):
    with pytest.raises(InputError, match=match):
        _score(**kwargs)


def test_detection_scan_index_must_name_a_scan():
    with pytest.raises(InputError, match=r"scan indices must lie in \[0, 1\)"):
        score_scan_detections(
            _obs([1], [[3.0, 0.0]], [0.3]),
            trees_xy=TREES,
            diameters=DIAMS,
            sensor_poses=[[0.0, 0.0, 0.0]],
            hit_ids=HITS,
        )


def test_scan_detection_metrics_passes_the_run_and_defaults_through():
    run = SimpleNamespace(
        scanner=SimpleNamespace(angle_min=FOV[0], angle_max=FOV[1], angle_increment=FOV[2]),
        stand=SimpleNamespace(
            trees_xy=TREES,
            diameters=DIAMS,
            clutter_objects_xy=BUSHES,
            clutter_objects_extent=EXTENT,
        ),
        true_poses=SimpleNamespace(poses=np.array([[0.0, 0.0, 0.0]])),
        hit_ids=HITS,
    )
    m = scan_detection_metrics(DETS, run)  # type: ignore[arg-type]
    ref = _score()
    assert m.to_dict() == ref.to_dict()
    kw = {"gate": 1.5, "min_returns": 4, "max_range": 16.0, "min_diameter": 0.2}
    bins = (0.0, 3.5, math.inf)
    m2 = scan_detection_metrics(DETS, run, range_bins=bins, **kw)  # type: ignore[arg-type]
    assert m2.to_dict() == _score(range_bins=bins, **kw).to_dict()
    assert m2.to_dict() != ref.to_dict()


def test_a_detection_beyond_the_scored_domain_is_neither_true_nor_false():
    # the scored domain is max_range + gate (15.5 m here) on both sides of precision: a
    # detection on the 15.5 m tree T2 (not eligible) was always ignored; one on the 20 m bush
    # B2 is now ignored too (it counted as a false alarm before Dec 5)
    xy = np.vstack((DETS.centers, [[20.0, 0.2], [15.4, 0.0]]))
    dets = _obs([0] * 5, xy, np.concatenate((DETS.diameters, [0.4, 0.3])))
    m = _score_dets(dets)
    assert (m.ta, m.fa, m.n_ignored, m.n_detections) == (1, 2, 2, 5)
    # a wider domain (max_range 20 m: T2 eligible, the bush detection within 20.5 m) counts both
    m20 = _score_dets(dets, max_range=20.0)
    assert (m20.ta, m20.fa, m20.n_ignored) == (2, 3, 0)


def _score_dets(dets, **kw):
    args = {
        "trees_xy": TREES,
        "diameters": DIAMS,
        "sensor_poses": [[0.0, 0.0, 0.0]],
        "hit_ids": HITS,
        "nontree_xy": BUSHES,
        "nontree_extent": EXTENT,
        "fov": FOV,
    }
    args.update(kw)
    return score_scan_detections(dets, **args)
