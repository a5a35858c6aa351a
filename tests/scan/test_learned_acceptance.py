"""The learned candidate acceptance study (benchmarks/learned_acceptance.py; issue 11, Dec 4):
the candidate rows come from the detector's own pass, the rescue only adds soft-rejected,
non-overlapping candidates, and the label is the benchmark's matching gate."""

import math

import numpy as np
import pytest

import _scan_sim as sim  # benchmarks/ is on sys.path (tests/conftest.py)
import learned_acceptance as la
from stemmap.eval.real_slices import RealSlice
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import REASONS


@pytest.fixture(scope="module")
def drive_rows():
    scans = sim.make_run(60, 3).scans
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap"))
    return det.detect_batch(scans), la.candidate_rows(det, scans)


def test_candidate_rows_hold_the_detectors_own_detections_and_its_rejections(drive_rows):
    obs, rows = drive_rows
    # the numpy pass with the rejection record gives the compiled default's detections
    assert len(rows["obs"]) == len(obs)
    np.testing.assert_allclose(rows["obs"].centers, obs.centers, atol=1e-9)
    k = rows["X"].shape[0]
    assert rows["X"].shape == (k, len(la.FEATURES)) and rows["code"].shape == (k,)
    soft = np.isin(rows["code"], [REASONS.index(t) for t in la.SOFT_TESTS])
    np.testing.assert_array_equal(rows["soft"], soft)
    assert soft.any()  # the drive has candidates the RMS / ratio tests drop
    rms_limit_col = la.FEATURES.index("rms_over_limit")
    # the RMS test fails exactly where its ratio exceeds 1
    fails_rms = rows["code"] == REASONS.index("rms")
    assert np.all(rows["X"][fails_rms, rms_limit_col] > 1.0)
    assert np.all(rows["X"][rows["code"] == 0, rms_limit_col] <= 1.0 + 1e-12)


def test_rescue_adds_only_confident_soft_rejections_that_overlap_nothing(drive_rows):
    obs, rows = drive_rows
    prob = np.ones(rows["X"].shape[0])
    assert la.rescued(rows, prob, math.inf) is rows["obs"]  # the model off: the default
    assert len(la.rescued(rows, np.zeros_like(prob), 0.5)) == len(obs)  # nobody confident
    out = la.rescued(rows, prob, 0.5)
    added = len(out) - len(obs)
    assert 0 < added <= int(rows["soft"].sum())
    # the default's detections are all kept, first and unchanged
    np.testing.assert_array_equal(out.centers[: len(obs)], obs.centers)
    # no two detections of a scan overlap once rescued ones are in
    for s in np.unique(out.index[len(obs) :]):
        m = np.flatnonzero(out.index == s)
        c, r = out.centers[m], out.radii[m]
        d = np.hypot(*(c[:, None, :] - c[None, :, :]).transpose(2, 0, 1))
        np.fill_diagonal(d, np.inf)
        assert np.all(d >= r[:, None] + r[None, :] - 1e-12)


def test_label_is_the_matching_gate_and_optionally_the_diameter_error():
    ref = {"x": 5.0, "y": 0.0, "diameter": 0.30}
    sl = RealSlice("lidr_dbh", np.zeros((1, 2)), np.zeros(1, dtype=np.int64), [ref], [])
    vp = np.array([[1.0, 0.0]])
    rows = {
        "X": np.zeros((3, len(la.FEATURES))),
        "scan": np.zeros(3, dtype=np.int64),
        # sensor frame: 4.0 m ahead is the trunk centre; the gate is r + 5 cm = 0.20 m
        "centers": np.array([[4.0, 0.0], [4.0, 0.19], [4.0, 0.21]]),
        "radii": np.array([0.20, 0.15, 0.15]),
    }
    np.testing.assert_array_equal(la.labels(sl, vp, rows), [1, 1, 0])
    # 40 cm against 30 cm: off by 10 cm
    np.testing.assert_array_equal(la.labels(sl, vp, rows, max_err_cm=3.0), [0, 1, 0])
