import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.eval import scan_detection_metrics
from stemmap.sim import (
    GnssNoise,
    add_clutter,
    loop_path,
    oracle_observations,
    random_stand,
    returns_per_tree,
    simulate_run,
    straight_path,
    trees_in_sensor_frame,
)


@pytest.fixture(scope="module")
def run():
    stand = add_clutter(random_stand(40, (30.0, 30.0), rng=1), n_bushes=4, n_rocks=2, rng=2)
    return simulate_run(
        stand,
        loop_path((15.0, 15.0), (9.0, 7.0)),
        rate_hz=10.0,
        corridor_half_width=1.0,
        max_scans=200,
        rng=3,
    )


def test_trees_in_sensor_frame_round_trip(run):
    local = trees_in_sensor_frame(run)
    p = run.true_poses.poses[17]
    c, s = math.cos(p[2]), math.sin(p[2])
    world = local[17] @ np.array([[c, s], [-s, c]]) + p[:2]
    np.testing.assert_allclose(world, run.stand.trees_xy, atol=1e-9)


def test_returns_per_tree_matches_hit_ids(run):
    n = returns_per_tree(run)
    assert n.shape == (len(run), run.stand.n_trees)
    k = 50
    for t in range(run.stand.n_trees):
        assert n[k, t] == np.sum(run.hit_ids[k] == t)


def test_oracle_noise_free_scores_perfectly(run):
    obs, truth = oracle_observations(run, sigma_xy=0.0, sigma_radius=0.0, rng=0)
    assert np.all(truth >= 0)
    m = scan_detection_metrics(obs, run, gate=0.3, min_returns=5, max_range=1e9, min_diameter=0.0)
    assert m.fa == 0 and m.fr == 0 and m.ta == len(obs)
    assert m.center_rmse < 1e-9 and m.diameter_rmse < 1e-12


def test_oracle_noise_level_and_false_alarms(run):
    obs, truth = oracle_observations(
        run, sigma_xy=0.05, sigma_radius=0.01, false_alarm_rate=0.5, rng=4
    )
    local = trees_in_sensor_frame(run)
    ok = truth >= 0
    err = obs.centers[ok] - local[obs.index[ok], truth[ok]]
    n = err.size
    # N(0, 0.05^2) per coordinate: sample std within 5 sigma of its sampling error
    assert abs(err.std() / 0.05 - 1) < 5 / math.sqrt(2 * n)
    n_fa = int(np.sum(~ok))
    # Poisson(0.5 per scan) capped by scans with clutter in view: at most 0.5 * 200 + 5 sigma
    assert 0 < n_fa < 100 + 5 * math.sqrt(100)
    assert np.all(np.diff(obs.index) >= 0)
    m = scan_detection_metrics(obs, run, gate=0.3, min_diameter=0.0, max_range=1e9)
    assert m.fa >= n_fa * 0.9  # false alarms sit on clutter, away from trunks


def test_oracle_bad_config(run):
    with pytest.raises(ConfigError):
        oracle_observations(run, min_returns=0)
    with pytest.raises(ConfigError):
        oracle_observations(run, sigma_xy=-1.0)


def test_gnss_noise_and_outages():
    stand = random_stand(10, (100.0, 100.0), rng=5)
    noise = GnssNoise(
        rate_hz=5.0, sigma=0.3, sigma_slow=0.0, outage_rate=0.01, outage_duration=10.0
    )
    r = simulate_run(
        stand, straight_path((5.0, 5.0), (95.0, 95.0)), speed=1.0, gnss_noise=noise, rng=6
    )
    g = r.gnss
    assert g is not None and len(g) > 100
    truth = r.true_path.interpolate(g.times)[:, :2]
    e = g.xy - truth
    n = e.size
    # white N(0, 0.3^2): std within 5 sigma of its sampling error; straight-line interpolation
    # of the truth between 50 Hz samples is exact here
    assert abs(e.std() / 0.3 - 1) < 5 / math.sqrt(2 * n)
    expected = 5.0 * (r.true_path.times[-1] - r.true_path.times[0])
    assert len(g) < expected + 2  # outages remove fixes (or none occurred)
    np.testing.assert_allclose(g.sigma, 0.3)


def test_gnss_slow_error_is_correlated():
    stand = random_stand(10, (100.0, 100.0), rng=5)
    noise = GnssNoise(rate_hz=1.0, sigma=0.0, sigma_slow=1.0, tau=30.0)
    r = simulate_run(stand, straight_path((5.0, 5.0), (95.0, 95.0)), gnss_noise=noise, rng=7)
    g = r.gnss
    e = g.xy[:, 0] - r.true_path.interpolate(g.times)[:, 0]
    lag1 = np.corrcoef(e[:-1], e[1:])[0, 1]
    # AR(1) with a = exp(-1/30) = 0.967; ~127 samples -> a loose bound
    assert lag1 > 0.8
