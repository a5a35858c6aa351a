import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import InputError
from stemmap.eval import align_rigid_2d, map_metrics, pairwise_distance_errors
from stemmap.types import StemMap, Tree


def _rot(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def test_pairwise_distance_errors_hand_built():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 5.0]])
    est = np.array([[0.0, 0.0], [11.0, 0.0], [0.0, 5.0]])
    p = pairwise_distance_errors(est, truth)
    assert p.percent_error[0, 1] == pytest.approx(10.0)
    assert p.percent_error[0, 2] == pytest.approx(0.0)
    d12_true, d12_est = math.hypot(10, 5), math.hypot(11, 5)
    assert p.abs_error[1, 2] == pytest.approx(d12_est - d12_true)
    expect = (10.0 + 0.0 + 100 * (d12_est - d12_true) / d12_true) / 3
    assert p.mean_percent_error == pytest.approx(expect)
    assert math.isnan(p.percent_error[1, 1])
    json.dumps(p.to_dict())


@settings(max_examples=30, deadline=None)
@given(
    a=st.floats(-3.1, 3.1), tx=st.floats(-50, 50), ty=st.floats(-50, 50), seed=st.integers(0, 999)
)
def test_pairwise_errors_are_frame_free_and_alignment_is_exact(a, tx, ty, seed):
    truth = np.random.default_rng(seed).uniform(0, 30, (8, 2))
    moved = truth @ _rot(a).T + [tx, ty]
    p = pairwise_distance_errors(moved, truth)
    assert p.max_percent_error < 1e-6
    R, t = align_rigid_2d(moved, truth)
    np.testing.assert_allclose(moved @ R.T + t, truth, atol=1e-8)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_map_metrics_counts_duplicates_and_spurious():
    truth = np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0], [15.0, 0.0]])
    tdiam = np.array([0.3, 0.3, 0.3, 0.3])
    mp = np.array([[0.1, 0.0], [5.0, 0.1], [5.3, -0.2], [30.0, 0.0]])  # 1 dup near tree 1
    mdiam = np.array([0.32, 0.28, 0.3, 0.3])
    m = map_metrics(mp, mdiam, truth, tdiam, gate=0.5)
    assert (m.n_matched, m.n_duplicates, m.n_spurious, m.n_missed) == (2, 1, 1, 2)
    assert m.precision == 0.5 and m.recall == 0.5
    assert m.duplicate_rate == 0.25
    assert m.position_rmse == pytest.approx(0.1)
    assert m.diameter_bias == pytest.approx(0.0)
    assert m.diameter_rmse == pytest.approx(0.02)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["n_duplicates"] == 1


def test_map_metrics_alignment_recovers_a_rigidly_moved_map():
    rng = np.random.default_rng(5)
    truth = rng.uniform(0, 40, (40, 2))
    a = math.radians(4.0)
    noisy = truth + rng.normal(0, 0.05, truth.shape)  # 5 cm mapping noise
    # small offsets: what a SLAM map starting at a slightly wrong pose looks like
    mapped = (noisy - 20) @ _rot(a).T + 20 + [0.4, -0.3]
    raw = map_metrics(mapped, np.full(40, 0.3), truth, np.full(40, 0.3), gate=0.5)
    al = map_metrics(mapped, np.full(40, 0.3), truth, np.full(40, 0.3), gate=0.5, align=True)
    assert al.n_matched == 40 > raw.n_matched
    # after alignment only the 5 cm noise remains: RMSE of a 2D N(0, 0.05^2 I) error is
    # 0.05 * sqrt(2) = 7 cm; allow sampling spread
    assert al.position_rmse < 0.09
    assert math.atan2(al.rotation[1, 0], al.rotation[0, 0]) == pytest.approx(-a, abs=0.005)
    # inter-tree distances do not depend on the frame: same pairwise error either way
    assert al.pairwise.mean_percent_error < 1.0


def test_map_metrics_accepts_stemmap():
    sm = StemMap((Tree(0, 1.0, 2.0, 0.3), Tree(1, 5.0, 2.0, 0.4)))
    m = map_metrics(sm, None, [[1.0, 2.0], [5.0, 2.0]], [0.3, 0.5], gate=0.5)
    assert m.n_matched == 2 and m.diameter_bias == pytest.approx(-0.05)


def test_map_metrics_bad_inputs():
    with pytest.raises(InputError, match="map_diam"):
        map_metrics([[0, 0]], None, [[0, 0]], [0.3])
    with pytest.raises(InputError, match="diameters"):
        map_metrics([[0, 0]], [0.3, 0.2], [[0, 0]], [0.3])
    with pytest.raises(InputError, match="gate"):
        map_metrics([[0, 0]], [0.3], [[0, 0]], [0.3], gate=-1)
    with pytest.raises(InputError, match="row for row"):
        pairwise_distance_errors(np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(InputError):
        align_rigid_2d(np.zeros((1, 2)), np.zeros((1, 2)))


def test_empty_map():
    m = map_metrics(np.zeros((0, 2)), np.zeros(0), [[0.0, 0.0]], [0.3])
    assert m.n_matched == 0 and m.n_missed == 1 and math.isnan(m.precision)
    assert math.isnan(m.pairwise.mean_percent_error)
    # no matched tree: (0, 0) matrices (M = 0), not a 1 x 1 distance "matrix" of nothing
    assert m.pairwise.estimated.shape == (0, 0) and m.pairwise.true.shape == (0, 0)
    assert m.pairwise.percent_error.shape == (0, 0) and m.pairwise.truth_index.shape == (0,)


def test_pairwise_distance_errors_every_field():
    """Signed errors, both matrices, the summary values over pairs i < j, labels and JSON."""
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 5.0]])
    est = np.array([[0.0, 0.0], [9.0, 0.0], [0.0, 5.5]])  # one pair 1 m short, one 0.5 m long
    p = pairwise_distance_errors(est, truth, truth_index=[7, 3, 9])
    assert p.truth_index.tolist() == [7, 3, 9] and p.truth_index.dtype == np.int64
    np.testing.assert_allclose(p.true[0], [0.0, 10.0, 5.0])
    np.testing.assert_allclose(p.estimated[0], [0.0, 9.0, 5.5])
    np.testing.assert_allclose(p.abs_error, p.estimated - p.true)  # signed
    assert p.abs_error[0, 1] == pytest.approx(-1.0) and p.abs_error[0, 2] == pytest.approx(0.5)
    assert p.percent_error[0, 1] == pytest.approx(10.0)  # |error| / true
    assert p.percent_error[0, 2] == pytest.approx(10.0)
    np.testing.assert_allclose(p.percent_error, p.percent_error.T, equal_nan=True)
    assert np.all(np.isnan(np.diag(p.percent_error)))
    d12 = abs(math.hypot(9.0, 5.5) - math.hypot(10.0, 5.0))
    assert p.mean_abs_error == pytest.approx((1.0 + 0.5 + d12) / 3)
    assert p.max_percent_error == pytest.approx(10.0)
    d = json.loads(json.dumps(p.to_dict()))
    assert d["truth_index"] == [7, 3, 9]
    assert d["mean_abs_error_m"] == pytest.approx(p.mean_abs_error)
    assert d["max_percent_error"] == pytest.approx(10.0)
    assert d["mean_percent_error"] == pytest.approx(p.mean_percent_error)
    assert d["percent_error"][0][0] is None and d["percent_error"][0][1] == pytest.approx(10.0)


def test_pairwise_distance_errors_one_tree_and_bad_inputs():
    p = pairwise_distance_errors([[1.0, 2.0]], [[1.0, 2.0]])
    assert p.estimated.shape == (1, 1) and p.true.shape == (1, 1)
    assert math.isnan(p.mean_percent_error) and math.isnan(p.max_percent_error)
    assert math.isnan(p.mean_abs_error)
    d = p.to_dict()
    assert d["mean_percent_error"] is None and d["mean_abs_error_m"] is None
    assert d["max_percent_error"] is None and d["truth_index"] == [0]
    with pytest.raises(InputError, match=r"row for row; got \(2, 2\) and \(1, 2\)"):
        pairwise_distance_errors([[0, 0], [1, 1]], [[0, 0]])
    with pytest.raises(InputError, match=r"truth_index must have 2 entries, got \(3,\)"):
        pairwise_distance_errors([[0, 0], [1, 1]], [[0, 0], [1, 1]], truth_index=[1, 2, 3])


def test_align_rigid_2d_is_a_proper_rotation_even_for_a_mirrored_set():
    src = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    # the best orthogonal map is a reflection; a rotation (det +1) must be returned
    R, t = align_rigid_2d(src, src * [1.0, -1.0])
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(2), atol=1e-12)
    # a pure translation is recovered exactly, with R = I
    R, t = align_rigid_2d(src, src + np.array([3.0, -2.0]))
    np.testing.assert_allclose(R, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(t, [3.0, -2.0], atol=1e-12)
    with pytest.raises(InputError, match=r"got \(1, 2\), \(1, 2\)"):
        align_rigid_2d([[0.0, 0.0]], [[0.0, 0.0]])
    with pytest.raises(InputError, match="equal shape"):
        align_rigid_2d(src, src[:3])


def test_align_rigid_2d_recovers_a_rotation_about_an_offset_centre_from_two_points():
    a = math.radians(30.0)
    src = np.array([[10.0, 20.0], [14.0, 23.0]])  # two points (the minimum), mean far from 0
    dst = src @ _rot(a).T + [5.0, -7.0]
    R, t = align_rigid_2d(src, dst)
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(a, abs=1e-12)
    np.testing.assert_allclose(t, [5.0, -7.0], atol=1e-9)
    np.testing.assert_allclose(src @ R.T + t, dst, atol=1e-9)


def test_pairwise_distance_errors_of_two_trees():
    p = pairwise_distance_errors([[0.0, 0.0], [0.0, 3.3]], [[0.0, 0.0], [0.0, 3.0]])
    assert p.true[0, 1] == pytest.approx(3.0) and p.estimated[1, 0] == pytest.approx(3.3)
    assert p.mean_percent_error == pytest.approx(10.0)
    assert p.mean_abs_error == pytest.approx(0.3)


def test_map_metrics_to_dict_reports_the_alignment_and_the_pairwise_summary():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 5.0], [8.0, 9.0]])
    a = math.radians(-3.0)
    mapped = truth @ _rot(a).T + [0.2, 0.1]
    m = map_metrics(mapped, np.full(4, 0.3), truth, np.full(4, 0.3), gate=0.5, align=True)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["rotation_rad"] == pytest.approx(-a, abs=1e-9)  # map frame -> truth frame
    np.testing.assert_allclose(d["translation"], m.translation)
    assert d["pairwise_mean_percent_error"] == pytest.approx(0.0, abs=1e-9)
    assert d["pairwise_mean_abs_error"] == pytest.approx(0.0, abs=1e-9)
    for k in ("rotation", "pairwise", "matching"):
        assert k not in d
    assert d["n_matched"] == 4 and d["aligned"] is True
    # one mapped tree: no pair, so the pairwise summary is null
    one = map_metrics([[0.0, 0.0]], [0.3], [[0.0, 0.0]], [0.3]).to_dict()
    assert one["pairwise_mean_percent_error"] is None and one["pairwise_mean_abs_error"] is None
    assert one["rotation_rad"] == 0.0 and one["translation"] == [0.0, 0.0]


def test_map_metrics_every_count_and_error_with_shuffled_rows():
    """Map rows in another order than the truth: each statistic from the matched pairs."""
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [20.0, 20.0]])
    tdiam = np.array([0.20, 0.30, 0.40, 0.50])
    # map: truth 2 (+0.3 m), truth 0 (+0.4 m), a duplicate of truth 0, truth 1 (exact), and a
    # spurious tree far from all; truth 3 is missed
    mxy = np.array([[0.0, 10.3], [0.4, 0.0], [0.0, 0.7], [10.0, 0.0], [50.0, 50.0]])
    mdiam = np.array([0.43, 0.18, 0.25, 0.30, 0.30])
    m = map_metrics(mxy, mdiam, truth, tdiam)  # default gate 1 m
    assert (m.gate, m.n_map, m.n_truth) == (1.0, 5, 4)
    assert (m.n_matched, m.n_duplicates, m.n_spurious, m.n_missed) == (3, 1, 1, 1)
    assert m.precision == pytest.approx(3 / 5) and m.recall == pytest.approx(3 / 4)
    assert m.duplicate_rate == pytest.approx(1 / 5)
    errs = np.array([0.3, 0.4, 0.0])
    assert m.position_rmse == pytest.approx(math.sqrt(np.mean(errs**2)))
    assert m.position_mean == pytest.approx(errs.mean())
    assert m.position_max == pytest.approx(0.4)
    d_err = np.array([0.43 - 0.40, 0.18 - 0.20, 0.0])
    assert m.diameter_rmse == pytest.approx(math.sqrt(np.mean(d_err**2)))
    assert m.diameter_bias == pytest.approx(d_err.mean())
    assert m.aligned is False
    np.testing.assert_array_equal(m.rotation, np.eye(2))
    # the pairwise comparison uses the matched pairs, labelled by their truth ids
    assert sorted(m.pairwise.truth_index.tolist()) == [0, 1, 2]
    assert m.matching.n_matched == 3
    # a smaller gate drops the 0.4 m match
    m3 = map_metrics(mxy, mdiam, truth, tdiam, gate=0.35)
    assert m3.gate == 0.35 and m3.n_matched == 2 and m3.position_max == pytest.approx(0.3)


def test_map_metrics_nothing_matched_and_input_errors():
    m = map_metrics([[50.0, 50.0]], [0.3], [[0.0, 0.0]], [0.3])
    assert (m.n_matched, m.n_spurious, m.n_duplicates, m.n_missed) == (0, 1, 0, 1)
    for k in ("position_rmse", "position_mean", "position_max", "diameter_rmse"):
        assert math.isnan(getattr(m, k))
    with pytest.raises(InputError, match=r"^map and truth positions must be finite\.$"):
        map_metrics([[math.nan, 0.0]], [0.3], [[0.0, 0.0]], [0.3])
    with pytest.raises(InputError, match=r"^map and truth positions must be finite\.$"):
        map_metrics([[0.0, 0.0]], [0.3], [[math.inf, 0.0]], [0.3])
    with pytest.raises(InputError, match=r"^map_diam is required unless map_xy is a StemMap\.$"):
        map_metrics([[0.0, 0.0]], None, [[0.0, 0.0]], [0.3])
    with pytest.raises(InputError, match="map has 2 positions and 1 diameters; truth has 1"):
        map_metrics([[0.0, 0.0], [1.0, 1.0]], [0.3], [[0.0, 0.0]], [0.3])
    for gate in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(InputError, match="gate must be a finite distance"):
            map_metrics([[0.0, 0.0]], [0.3], [[0.0, 0.0]], [0.3], gate=gate)


def test_map_metrics_alignment_with_shuffled_rows_and_extra_trees():
    """The ICP-style alignment pairs map rows with truth rows by the matching, not by order."""
    rng = np.random.default_rng(11)
    truth = rng.uniform(0, 40, (30, 2))
    a = math.radians(5.0)
    order = rng.permutation(30)
    mapped = (truth[order] - 20) @ _rot(a).T + 20 + [0.5, -0.4]
    mapped = np.vstack((mapped, [[100.0, 100.0]]))  # one spurious tree far away
    m = map_metrics(mapped, np.full(31, 0.3), truth, np.full(30, 0.3), gate=0.3, align=True)
    assert m.aligned and (m.n_matched, m.n_spurious) == (30, 1)
    assert m.position_max < 1e-6
    assert math.atan2(m.rotation[1, 0], m.rotation[0, 0]) == pytest.approx(-a, abs=1e-9)
    np.testing.assert_allclose(mapped[:30] @ m.rotation.T + m.translation, truth[order], atol=1e-6)
    # two trees are enough to align (0.64 m off: inside the first rounds' 3x gate)
    shifted = truth[:2] + np.array([0.5, -0.4])
    two = map_metrics(shifted[::-1], [0.3, 0.3], truth[:2], [0.3, 0.3], gate=0.3, align=True)
    assert two.n_matched == 2 and two.position_max < 1e-6


def test_map_metrics_stemmap_with_map_diam_uses_the_given_diameters():
    """A ``map_diam`` given with a StemMap overrides the map's own diameters (any shape of
    M values, as for arrays)."""
    sm = StemMap((Tree(0, 1.0, 2.0, 0.3), Tree(1, 5.0, 2.0, 0.4)))
    truth, tdiam = [[1.0, 2.0], [5.0, 2.0]], [0.3, 0.5]
    m = map_metrics(sm, [0.2, 0.6], truth, tdiam, gate=0.5)
    assert m.diameter_bias == pytest.approx(0.0)  # (-0.1 + 0.1) / 2, not the StemMap's -0.05
    assert m.diameter_rmse == pytest.approx(0.1)
    col = map_metrics(sm, [[0.2], [0.6]], truth, tdiam, gate=0.5)  # a column of M values
    assert col.diameter_rmse == pytest.approx(0.1) and col.diameter_bias == pytest.approx(0.0)
    ints = map_metrics(sm, [1, 0], truth, tdiam, gate=0.5)  # integers promoted to float
    assert ints.diameter_bias == pytest.approx(((1 - 0.3) + (0 - 0.5)) / 2)
    with pytest.raises(InputError, match="map has 2 positions and 3 diameters; truth has 2"):
        map_metrics(sm, [0.2, 0.6, 0.4], truth, tdiam, gate=0.5)


def test_map_metrics_count_mismatch_message_names_every_count():
    with pytest.raises(
        InputError,
        match=r"^map has 3 positions and 3 diameters; truth has 1 positions and 4 diameters\.$",
    ):
        map_metrics(np.zeros((3, 2)), np.zeros(3), [[0.0, 0.0]], np.zeros(4))
    with pytest.raises(
        InputError,
        match=r"^map has 1 positions and 2 diameters; truth has 3 positions and 3 diameters\.$",
    ):
        map_metrics([[0.0, 0.0]], [0.3, 0.3], np.zeros((3, 2)), np.zeros(3))


def test_map_metrics_empty_truth():
    """No truth tree: every mapped tree is spurious, precision 0, recall undefined (NaN)."""
    m = map_metrics([[0.0, 0.0], [3.0, 0.0]], [0.3, 0.3], np.zeros((0, 2)), np.zeros(0))
    assert (m.n_map, m.n_truth, m.n_matched) == (2, 0, 0)
    assert (m.n_duplicates, m.n_spurious, m.n_missed) == (0, 2, 0)
    assert m.precision == 0.0 and math.isnan(m.recall) and m.duplicate_rate == 0.0
    assert math.isnan(m.position_rmse) and math.isnan(m.diameter_bias)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["recall"] is None and d["precision"] == 0.0
    al = map_metrics(
        [[0.0, 0.0], [3.0, 0.0]], [0.3, 0.3], np.zeros((0, 2)), np.zeros(0), align=True
    )
    assert al.n_spurious == 2 and math.isnan(al.recall)
    np.testing.assert_array_equal(al.rotation, np.eye(2))


def test_map_metrics_pairwise_is_labelled_by_the_matched_truth_ids():
    """Truth trees 0 and 2 missed: the pairwise matrix rows are truth 3 and truth 1, in the
    map's row order, and their distance is compared with the true one."""
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [30.0, 30.0], [10.0, 8.0]])
    mxy = np.array([[10.0, 8.4], [10.0, 0.0]])  # truth 3 (0.4 m north), truth 1
    m = map_metrics(mxy, [0.3, 0.3], truth, np.full(4, 0.3))
    assert m.pairwise.truth_index.tolist() == [3, 1]
    assert m.pairwise.true[0, 1] == pytest.approx(8.0)
    assert m.pairwise.abs_error[0, 1] == pytest.approx(0.4)
    assert m.pairwise.to_dict()["truth_index"] == [3, 1]


def test_pairwise_truth_index_is_integer_whatever_its_input():
    p = pairwise_distance_errors([[0.0, 0.0], [3.0, 4.0]], [[0.0, 0.0], [3.0, 4.0]], [7.0, 3.0])
    assert p.truth_index.dtype == np.int64
    assert json.dumps(p.to_dict()["truth_index"]) == "[7, 3]"


def test_map_metrics_alignment_that_finds_no_two_pairs_keeps_the_identity():
    """Map and truth too far apart for any match, even in the widened first rounds: the
    alignment gives up, the result is the unaligned one (identity transform, nothing matched)."""
    truth = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])
    m = map_metrics(truth + 100.0, np.full(3, 0.3), truth, np.full(3, 0.3), align=True)
    assert m.aligned and (m.n_matched, m.n_spurious, m.n_missed) == (0, 3, 3)
    np.testing.assert_array_equal(m.rotation, np.eye(2))
    np.testing.assert_array_equal(m.translation, [0.0, 0.0])
    # one pair within the widened gate is not enough to align either
    one = map_metrics(
        truth + np.array([[0.5, 0.0], [100.0, 0.0], [0.0, 100.0]]),
        np.full(3, 0.3),
        truth,
        np.full(3, 0.3),
        gate=0.3,
        align=True,
    )
    np.testing.assert_array_equal(one.rotation, np.eye(2))
    assert one.n_matched == 0


def test_map_trees_without_a_diameter_are_left_out_of_the_diameter_rmse():
    """A map tree with NaN diameter (DAIM's width check dropped every fit) still counts as a
    match; the diameter RMSE / bias are over the trees that have one, NaN when none has."""
    txy = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])
    td = np.array([0.3, 0.2, 0.4])
    m = map_metrics(txy + 0.1, np.array([0.32, np.nan, 0.37]), txy, td)
    assert m.n_matched == 3
    assert m.diameter_rmse == pytest.approx(math.sqrt((0.02**2 + 0.03**2) / 2))
    assert m.diameter_bias == pytest.approx((0.02 - 0.03) / 2)
    assert math.isnan(map_metrics(txy, np.full(3, np.nan), txy, td).diameter_rmse)
