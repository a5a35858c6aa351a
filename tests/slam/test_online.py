"""OnlineMapper: one scan at a time, bounded smoother window, GNSS fed online."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from _synthetic import loop_problem

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import dead_reckoning
from stemmap.slam.graph import Isam2Config
from stemmap.slam.online import OnlineConfig, OnlineMapper, replay


@pytest.fixture(scope="module")
def loop():
    return loop_problem(2, laps=1.2)


def _rmse(traj, truth):
    return math.sqrt(np.mean(np.sum((traj.xy - truth[:, :2]) ** 2, axis=1)))


def test_online_tracks_the_loop_and_re_anchors(loop):
    problem, truth, trees, _ = loop
    # window of 12 keyframes (~12 s): the smoother is re-anchored ~5 times in the run
    cfg = OnlineConfig(window_keyframes=12)
    st = replay(problem, config=cfg)
    dr = _rmse(dead_reckoning(problem), truth)
    online = _rmse(st["trajectory"], truth)
    # the causal (filter) path: measured ~0.15 m vs ~5 m of dead reckoning
    assert dr > 2.0
    assert online < 0.5
    assert len(st["latency_s"]) == len(problem.frames)
    m = st["stem_map"]
    d = np.array([np.hypot(*(trees - p).T).min() for p in m.xy])
    assert np.median(d) < 0.25
    # trees that left the smoother carry a covariance
    covs = np.array([t.cov for t in m])
    assert np.isfinite(covs).all(axis=(1, 2)).mean() > 0.5
    # the same run without re-anchoring gives a path of the same quality
    full = replay(problem, config=OnlineConfig(window_keyframes=10_000))
    assert abs(_rmse(full["trajectory"], truth) - online) < 0.2


def test_online_gnss_gives_the_frame(loop):
    problem, truth, _, _ = loop
    rng = np.random.default_rng(4)
    shift = np.array([1000.0, -500.0])
    m = OnlineMapper(
        problem.motion, problem.sensor_offset, (shift[0], shift[1], 0.0),
        gnss_lever_arm=(0.0, 0.0),
    )  # fmt: skip
    ctl, fr = problem.controls, problem.frames
    ci = 0
    poses = []
    next_fix = 1.0
    for f in range(len(fr)):
        t = float(fr.times[f])
        while ci < len(ctl) and ctl.times[ci] <= t:
            m.add_odometry(float(ctl.times[ci]), float(ctl.speed[ci]), float(ctl.steer[ci]))
            ci += 1
        if t >= next_fix:  # 1 Hz fixes of the vehicle origin, 0.3 m noise, one 10 m jump
            g = truth[f, :2] + shift + rng.normal(0, 0.3, 2)
            if 30.0 < t < 32.5:
                g = g + np.array([10.0, 0.0])
            m.add_gnss(t, float(g[0]), float(g[1]), 0.3)
            next_fix += 1.0
        poses.append(m.add_scan(t, *fr.frame(f)))
    p = np.array(poses)
    err = np.hypot(*(p[:, :2] - truth[:, :2] - shift).T)
    assert m.stats["gnss_fused"] >= 0.9 * fr.times[-1] - 2
    assert math.sqrt(np.mean(err**2)) < 0.5
    assert err[(fr.times > 30.0) & (fr.times < 36.0)].max() < 1.0  # the jump is ignored


def test_online_input_checks(loop):
    problem = loop[0]
    m = OnlineMapper(problem.motion, problem.sensor_offset)
    m.add_odometry(1.0, 1.0, 0.0)
    with pytest.raises(InputError, match="older"):
        m.add_odometry(0.5, 1.0, 0.0)
    with pytest.raises(ConfigError, match="unicycle"):
        m.add_imu(1.0, 0.1)
    with pytest.raises(InputError, match="one length"):
        m.add_scan(1.0, np.ones(2), np.ones(3), np.ones(2))
    with pytest.raises(ConfigError):
        OnlineConfig(window_keyframes=2, isam2=Isam2Config(update_every=3))
    assert dataclasses.is_dataclass(OnlineConfig())


def test_rerun_recording_of_an_online_run(tmp_path):
    pytest.importorskip("rerun")
    import subprocess
    import sys

    from stemmap.viz.live import RerunRecorder, sigma_ellipses

    problem, _, _, _ = loop_problem(5, laps=0.4)
    path = tmp_path / "run.rrd"
    rec = RerunRecorder(path, map_every=10)
    st = replay(problem, on_scan=rec)
    rec.close()
    assert rec.n_logged == len(st["latency_s"])
    assert path.stat().st_size > 10_000
    out = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "print", str(path)],
        capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    for entity in ("world/vehicle", "world/detections", "world/path", "world/trees"):
        assert entity in out.stdout
    # the 2-sigma ellipse of a diagonal covariance reaches 2 sigma along each axis
    e = sigma_ellipses(np.array([[1.0, 2.0]]), np.array([[[0.25, 0.0], [0.0, 0.04]]]))[0]
    np.testing.assert_allclose(e[:, 0].max() - 1.0, 1.0, atol=1e-9)
    np.testing.assert_allclose(e[:, 1].max() - 2.0, 0.4, atol=0.03)


def _pos_z2(e, P):
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(P), e)


def test_online_pose_covariance_on_every_scan(loop, tmp_path):
    """Every reported pose has a map-frame covariance (issue 14), through re-anchors, written
    to trajectory.csv by ``--realtime``."""
    from stemmap.cli._map import _realtime
    from stemmap.io.trajectory import read_trajectory_csv_with_covariance, write_trajectory_csv

    problem = loop[0]
    res = _realtime(problem, "isam2", lambda *a: None, None)
    P = res.pose_covs
    assert P.shape == (len(problem.frames), 3, 3)
    assert np.isfinite(P).all()
    assert (np.linalg.eigvalsh(P[1:])[:, 0] > 0).all()
    write_trajectory_csv(tmp_path / "trajectory.csv", res.trajectory, covs=P)
    back = read_trajectory_csv_with_covariance(tmp_path / "trajectory.csv")[1]
    assert back is not None and np.isfinite(back).all()
    # re-anchoring (~every 2.4 s here) does not reset the covariance: per scan within the
    # run without re-anchors (measured: median ratio of the sigmas 0.94, 5 % below 0.73)
    win = replay(problem, config=OnlineConfig(window_keyframes=12))["pose_covs"]
    r = np.sqrt(
        np.trace(win[1:, :2, :2], axis1=1, axis2=2) / np.trace(P[1:, :2, :2], axis1=1, axis2=2)
    )
    assert np.median(r) > 0.8 and np.percentile(r, 5) > 0.6


@pytest.mark.parametrize("biased", [False, True])
def test_online_pose_covariance_against_truth(biased):
    """Position z² against the simulator's truth (calibrated 2-D median 1.39). The smoother's
    own covariance (factor 1) with the odometry the motion model assumes: covers the error
    (measured median 0.06, seed 2: the keyframe marginal's dead-reckoned part is
    conservative), so below 1.39 and not absurdly wide (> 0.01). With the fixture's biased
    odometry (2 % speed scale, 0.004 rad steering bias; no self-calibration online) and the
    VP-chosen factor 8.6: measured 0.24, so below 1.39 (not overconfident) and > 0.05."""
    kw = {} if biased else {"speed_scale": 1.0, "steer_bias": 0.0}
    problem, truth, _, _ = loop_problem(2, laps=1.2, **kw)
    cfg = OnlineConfig(window_keyframes=12, pose_cov_factor=8.6 if biased else 1.0)
    st = replay(problem, config=cfg)
    P, xy = st["pose_covs"], st["trajectory"].xy
    z2 = _pos_z2(xy[1:] - truth[1:, :2], P[1:, :2, :2])
    lo = 0.05 if biased else 0.01
    assert lo < np.median(z2) < 1.39


def test_online_pose_gnss_follows_the_receivers_slow_error(loop):
    """Fixes with a slowly varying receiver error (1.5 m x sin(2 pi t / 60 s) in x, 0.05 m
    noise) and the error's model given: pose_gnss (pose + the causal offset) is nearer to what
    the receiver reads than the tree-consistent pose, by > 2x after the first 20 s."""
    from stemmap.slam.gnss_track import GnssOffsetModel

    problem, truth, _, _ = loop
    rng = np.random.default_rng(6)
    model = GnssOffsetModel(time_constant=20.0, bias_sigma=1.0, white_sigma=0.05, n_fixes=0)
    m = OnlineMapper(problem.motion, problem.sensor_offset, gnss_offset_model=model)
    with pytest.raises(ConfigError, match="gnss_offset_model"):
        _ = OnlineMapper(problem.motion, problem.sensor_offset).pose_gnss
    ctl, fr = problem.controls, problem.frames
    ci, next_fix = 0, 1.0
    bias = lambda t: np.array([1.5 * math.sin(2 * math.pi * t / 60.0), 0.0])  # noqa: E731
    path_err, track_err = [], []
    for f in range(len(fr)):
        t = float(fr.times[f])
        while ci < len(ctl) and ctl.times[ci] <= t:
            m.add_odometry(float(ctl.times[ci]), float(ctl.speed[ci]), float(ctl.steer[ci]))
            ci += 1
        if t >= next_fix:
            g = truth[f, :2] + bias(t) + rng.normal(0, 0.05, 2)
            m.add_gnss(t, float(g[0]), float(g[1]), 0.5)
            next_fix += 1.0
        m.add_scan(t, *fr.frame(f))
        if t > 20.0:
            reads = truth[f, :2] + bias(t)
            path_err.append(np.hypot(*(np.array(m.pose[:2]) - reads)))
            track_err.append(np.hypot(*(np.array(m.pose_gnss[:2]) - reads)))
    assert math.sqrt(np.mean(np.square(track_err))) < 0.5 * math.sqrt(np.mean(np.square(path_err)))
