import numpy as np

from stemmap.eval.matching import match_points


def test_hungarian_prefers_global_optimum_and_gates():
    truth = np.array([[0.0, 0.0], [1.0, 0.0], [10.0, 0.0]])
    det = np.array([[0.6, 0.0], [1.05, 0.0], [20.0, 0.0]])
    m = match_points(det, truth, gate=0.7)
    assert sorted(map(tuple, m.pairs.tolist())) == [(0, 0), (1, 1)]
    assert m.unmatched_detections.tolist() == [2]
    assert m.unmatched_truth.tolist() == [2]


def test_empty_inputs():
    m = match_points(np.zeros((0, 2)), np.ones((3, 2)), gate=1.0)
    assert m.n_matched == 0 and m.unmatched_truth.tolist() == [0, 1, 2]
