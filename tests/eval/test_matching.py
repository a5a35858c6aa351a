import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.matching import match_points


def test_hungarian_prefers_global_optimum_and_gates() -> None:
    truth = np.array([[0.0, 0.0], [1.0, 0.0], [10.0, 0.0]])
    det = np.array([[0.6, 0.0], [1.05, 0.0], [20.0, 0.0]])
    m = match_points(det, truth, gate=0.7)
    assert sorted(map(tuple, m.pairs.tolist())) == [(0, 0), (1, 1)]
    assert m.unmatched_detections.tolist() == [2]
    assert m.unmatched_truth.tolist() == [2]
    order = np.argsort(m.pairs[:, 0])
    np.testing.assert_allclose(m.distances[order], [0.6, 0.05], atol=1e-12)


def test_empty_inputs() -> None:
    m = match_points(np.zeros((0, 2)), np.ones((3, 2)), gate=1.0)
    assert m.n_matched == 0 and m.unmatched_truth.tolist() == [0, 1, 2]
    assert m.pairs.shape == (0, 2) and m.pairs.dtype == np.int64 and m.distances.shape == (0,)
    assert m.unmatched_detections.shape == (0,)


def test_gate_is_inclusive_and_positive() -> None:
    # A pair exactly at the gate distance is matched ("farther than gate" is excluded).
    m = match_points([[0.0, 0.0]], [[0.0, 1.0]], gate=1.0)
    assert m.pairs.tolist() == [[0, 0]] and m.distances.tolist() == [1.0]
    with pytest.raises(InputError, match="gate must be > 0 m, got 0"):
        match_points([[0.0, 0.0]], [[0.0, 1.0]], gate=0.0)
