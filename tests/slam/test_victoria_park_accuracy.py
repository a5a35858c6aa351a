"""Victoria Park slices: path accuracy against GPS, not just "finite" (issue 13).

The slice tests in test_forestrix/test_fastslam/test_treedb check shapes and finiteness; these
bound the absolute trajectory error (ATE RMSE after the rigid GPS alignment and GPS screening
of ``stemmap map``) on the same slices. Measured on ../shared/datasets/victoria_park
(2026-12-02, `slam_metrics` of stemmap.cli._map):

| back-end | slice | ATE RMSE | ATE max | dead reckoning RMSE |
|---|---|---|---|---|
| Forestrix | 0-60 s | 0.87 m | 1.53 m | 2.68 m |
| treedb | 0-60 s | 0.84 m | 1.64 m | 2.68 m |
| FastSLAM (30 particles) | 0-40 s | 0.90 m | 1.68 m | 0.80 m |

Bounds: 1.5x the measured RMSE (GPS noise and the alignment leave ~0.5 m), and on the
60-s slices at most half of dead reckoning's error (the map must correct the drift). A run on
a truncated or misaligned input (166-445 m off, issue 13) fails all of them.
"""

from __future__ import annotations

import pytest

from stemmap.cli._map import slam_metrics


def _ate(datasets_dir, backend, t1):
    from stemmap.datasets.victoria_park import load_victoria_park

    vp = load_victoria_park(datasets_dir / "victoria_park").slice(0.0, t1)
    problem = vp.problem()
    res = backend.run(problem)
    m, _, _ = slam_metrics(problem, res, {"kind": "victoria-park", "vp": vp})
    assert m["gps_fixes_kept"] >= 100
    return m


@pytest.mark.slow
def test_forestrix_slice_accuracy(datasets_dir):
    from stemmap.slam.forestrix import ForestrixSlam

    m = _ate(datasets_dir, ForestrixSlam(), 60.0)
    assert m["ate_rmse_m"] < 1.3
    assert m["ate_max_m"] < 2.3
    assert m["ate_rmse_m"] < 0.5 * m["dead_reckoning_ate_rmse_m"]


@pytest.mark.slow
def test_treedb_slice_accuracy(datasets_dir):
    from stemmap.slam.treedb import TreeDbSlam

    m = _ate(datasets_dir, TreeDbSlam(), 60.0)
    assert m["ate_rmse_m"] < 1.3
    assert m["ate_max_m"] < 2.5
    assert m["ate_rmse_m"] < 0.5 * m["dead_reckoning_ate_rmse_m"]


@pytest.mark.slow
def test_fastslam_slice_accuracy(datasets_dir):
    from stemmap.slam.fastslam import FastSlam

    m = _ate(datasets_dir, FastSlam(n_particles=30), 40.0)
    assert m["ate_rmse_m"] < 1.35
    assert m["ate_max_m"] < 2.5
