import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import InputError
from stemmap.eval import detectable_trees, detection_metrics, scan_detection_metrics
from stemmap.sim import Stand, add_clutter, random_stand, simulate_run, straight_path
from stemmap.types import StemObservations


def test_hand_built_counts_and_errors():
    truth = np.array([[0.0, 0.0], [3.0, 0.0], [8.0, 0.0], [12.0, 0.0]])
    tdiam = np.array([0.30, 0.20, 0.40, 0.25])
    det = np.array([[0.1, 0.0], [3.0, 0.2], [20.0, 0.0]])  # two hits, one far-away false alarm
    ddiam = np.array([0.32, 0.17, 0.3])
    m = detection_metrics(det, ddiam, truth, tdiam, gate=0.5)
    assert (m.ta, m.fa, m.fr, m.tr) == (2, 1, 2, 0)
    assert m.precision == pytest.approx(2 / 3)
    assert m.recall == pytest.approx(0.5)
    assert m.f1 == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
    assert m.center_rmse == pytest.approx(math.sqrt((0.1**2 + 0.2**2) / 2))
    assert m.center_mean == pytest.approx(0.15)
    assert m.diameter_bias == pytest.approx((0.02 - 0.03) / 2)
    assert m.diameter_rmse == pytest.approx(math.sqrt((0.02**2 + 0.03**2) / 2))
    # range bins from the origin: trees at 0 and 3 m in [0, 5), 8 m in [5, 10), 12 m in [10, 15)
    b = {(r.range_lo, r.range_hi): r for r in m.by_range}
    assert (b[0.0, 5.0].ta, b[0.0, 5.0].fr) == (2, 0)
    assert (b[5.0, 10.0].ta, b[5.0, 10.0].fr) == (0, 1)
    assert (b[10.0, 15.0].ta, b[10.0, 15.0].fr) == (0, 1)
    assert math.isnan(b[5.0, 10.0].diameter_rmse)


def test_range_bins_follow_the_sensor_position():
    truth = np.array([[0.0, 0.0], [10.0, 0.0]])
    m = detection_metrics(truth, [0.3, 0.3], truth, [0.3, 0.3], gate=0.5, sensor_xy=[10.0, 1.0])
    b = {(r.range_lo, r.range_hi): r.ta for r in m.by_range}
    assert b[0.0, 5.0] == 1 and b[10.0, 15.0] == 1


def test_true_rejects_and_false_accepts_on_clutter():
    truth = np.array([[0.0, 0.0]])
    bushes = np.array([[5.0, 0.0], [0.0, 5.0], [-5.0, 0.0]])
    det = np.array([[0.0, 0.0], [5.2, 0.0]])  # the second detection sits on bush 0
    m = detection_metrics(
        det, [0.3, 0.1], truth, [0.3], gate=0.3, nontree_xy=bushes, nontree_extent=[0.3] * 3
    )
    assert (m.ta, m.fa, m.fr, m.tr) == (1, 1, 0, 2)
    assert m.n_nontree == 3


def test_ineligible_truth_is_dont_care():
    truth = np.array([[0.0, 0.0], [4.0, 0.0], [8.0, 0.0]])
    det = np.array([[0.0, 0.0], [4.0, 0.0]])
    elig = np.array([True, False, False])
    m = detection_metrics(det, [0.3, 0.3], truth, [0.3] * 3, gate=0.5, truth_eligible=elig)
    # the match to ineligible tree 1 is neither TA nor FA; missing tree 2 is not an FR
    assert (m.ta, m.fa, m.fr, m.n_ignored) == (1, 0, 0, 1)
    assert m.precision == 1.0 and m.recall == 1.0


def test_empty_inputs_give_nan_rates_not_zero():
    m = detection_metrics(np.zeros((0, 2)), [], np.zeros((0, 2)), [], gate=0.5)
    assert (m.ta, m.fa, m.fr) == (0, 0, 0)
    assert math.isnan(m.precision) and math.isnan(m.recall) and math.isnan(m.f1)
    d = m.to_dict()
    assert d["precision"] is None
    json.dumps(d)  # JSON-ready


def test_to_dict_round_trips_through_json():
    m = detection_metrics([[0, 0]], [0.3], [[0, 0.1]], [0.31], gate=0.5)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["ta"] == 1 and d["gate"] == 0.5 and len(d["by_range"]) == 4


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"det_xy": [[0, 0, 0]]}, "shape"),
        ({"det_diam": [0.3, 0.2]}, "det_diam"),
        ({"gate": 0.0}, "gate"),
        ({"truth_eligible": [True, False]}, "truth_eligible"),
        ({"det_xy": [[np.nan, 0]]}, "NaN"),
        ({"range_bins": (5.0, 1.0)}, "range_bins"),
    ],
)
def test_bad_inputs(kwargs, match):
    args = {
        "det_xy": [[0, 0]],
        "det_diam": [0.3],
        "truth_xy": [[0, 0]],
        "truth_diam": [0.3],
        "gate": 0.5,
    }
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        detection_metrics(
            args.pop("det_xy"),
            args.pop("det_diam"),
            args.pop("truth_xy"),
            args.pop("truth_diam"),
            **args,
        )


@settings(max_examples=50, deadline=None)
@given(
    n=st.integers(0, 12),
    k=st.integers(0, 12),
    seed=st.integers(0, 10_000),
)
def test_count_identities(n, k, seed):
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0, 20, (n, 2))
    det = rng.uniform(0, 20, (k, 2))
    m = detection_metrics(det, np.full(k, 0.3), truth, np.full(n, 0.3), gate=1.0)
    assert m.ta + m.fa == k
    assert m.ta + m.fr == n
    assert sum(b.ta for b in m.by_range) == m.ta
    assert sum(b.fr for b in m.by_range) == m.fr


@settings(max_examples=50, deadline=None)
@given(n=st.integers(0, 10), k=st.integers(0, 10), c=st.integers(0, 5), seed=st.integers(0, 999))
def test_count_identities_with_dont_care_and_clutter(n, k, c, seed):
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0, 15, (n, 2))
    det = rng.uniform(0, 15, (k, 2))
    elig = rng.random(n) < 0.6
    clutter = rng.uniform(0, 15, (c, 2))
    m = detection_metrics(
        det,
        np.full(k, 0.3),
        truth,
        np.full(n, 0.3),
        gate=1.0,
        truth_eligible=elig,
        nontree_xy=clutter,
        nontree_extent=np.full(c, 0.2),
    )
    assert m.ta + m.fa + m.n_ignored == k
    assert m.ta + m.fr == int(elig.sum()) == m.n_truth_eligible
    assert 0 <= m.tr <= c == m.n_nontree
    if m.fa == 0:
        assert m.tr == c  # no unmatched detection can claim a non-tree object


def test_detectable_trees_counts_returns():
    hit = np.array([[0, 0, 0, 0, 0, 1, 1, -1, -2], [1] * 5 + [-1] * 4])
    ok = detectable_trees(hit, 3, min_returns=5)
    np.testing.assert_array_equal(ok, [[True, False, False], [False, True, False]])
    ok1 = detectable_trees(hit[0], 3, min_returns=2)
    np.testing.assert_array_equal(ok1, [True, True, False])
    far = detectable_trees(hit, 3, min_returns=1, truth_range=[[3.0, 20.0, 1.0]] * 2, max_range=15)
    np.testing.assert_array_equal(far, [[True, False, False], [False, False, False]])
    thin = detectable_trees(hit, 3, min_returns=1, diameters=[0.05, 0.3, 0.3], min_diameter=0.1)
    np.testing.assert_array_equal(thin, [[False, True, False], [False, True, False]])
    with pytest.raises(InputError, match="names tree"):
        detectable_trees(hit, 1)
    with pytest.raises(InputError, match="integers"):
        detectable_trees(hit.astype(float), 3)


def test_scan_detection_metrics_perfect_detector_scores_one():
    stand = add_clutter(random_stand(30, (20.0, 20.0), rng=2), n_bushes=3, rng=3)
    run = simulate_run(stand, straight_path((1.0, 1.0), (19.0, 15.0)), max_scans=40, rng=4)
    # an oracle: report every detectable tree at its true sensor-frame position
    poses = run.true_poses.poses
    rows = []
    for k in range(len(run)):
        ok = detectable_trees(run.hit_ids[k], stand.n_trees, min_returns=5)
        c, s = math.cos(poses[k, 2]), math.sin(poses[k, 2])
        for i in np.flatnonzero(ok):
            dx, dy = stand.trees_xy[i] - poses[k, :2]
            rows.append((k, c * dx + s * dy, -s * dx + c * dy, stand.radii[i]))
    a = np.array(rows)
    n = a.shape[0]
    obs = StemObservations(
        centers=a[:, 1:3],
        radii=a[:, 3],
        covs=np.zeros((n, 3, 3)),
        n_points=np.zeros(n),
        arc_deg=np.zeros(n),
        widths=np.zeros(n),
        quality=np.ones(n),
        index=a[:, 0],
        times=run.scans.times[a[:, 0].astype(int)],
    )
    m = scan_detection_metrics(obs, run, gate=0.5, min_diameter=0.0, max_range=100.0)
    assert m.fa == 0 and m.fr == 0 and m.ta == n
    assert m.center_rmse < 1e-9 and abs(m.diameter_bias) < 1e-12
    assert m.n_frames == 40
    assert m.tr == m.n_nontree > 0  # the oracle never reports a bush
    fc = m.frame_counts
    assert fc is not None and fc.shape == (40, 3)
    assert fc[:, 0].sum() == m.ta and fc[:, 1].sum() == 0 and fc[:, 2].sum() == 0
    # dropping every second detection halves the recall
    half = scan_detection_metrics(
        obs.select(np.arange(n) % 2 == 0), run, gate=0.5, min_diameter=0.0, max_range=100.0
    )
    assert half.recall == pytest.approx(0.5, abs=1 / n)
    bad = StemObservations(**{**obs.__dict__, "index": np.full(n, 10_000)})
    with pytest.raises(InputError, match="scan indices"):
        scan_detection_metrics(bad, run)


def test_stand_truth_is_unaffected_by_metrics():
    st_ = Stand([[0.0, 0.0]], [0.3])
    truth = st_.trees_xy
    detection_metrics(truth, [0.3], truth, st_.diameters, gate=0.5)
    assert not truth.flags.writeable
