"""The GNSS-frame track: the Gauss-Markov offset model from the run's own fixes, causal and
smoothed offsets, their standard deviations (stemmap.slam.gnss_track)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.trajectory import ate
from stemmap.slam.gnss import (
    GnssFixes,
    fit_gnss_offset_model,
    gnss_frame_trajectory,
    gnss_offset,
)
from stemmap.types import Trajectory


def _gm_run(seed: int, tau: float, dur: float, s_b: float = 0.8, s_w: float = 0.1):
    """A circle driven for ``dur`` s and a 5 Hz receiver whose error is a first-order
    Gauss-Markov bias (std ``s_b`` per axis, time constant ``tau``, simulated exactly at 5 Hz)
    + white noise ``s_w``. Returns (path, receiver times, readings, true bias)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, dur, 0.2)
    poses = np.column_stack((60 * np.cos(t / 60), 60 * np.sin(t / 60), t / 60 + math.pi / 2))
    traj = Trajectory(t, poses)
    tg = np.arange(0.0, dur - 1.0, 0.2)
    a = math.exp(-0.2 / tau)
    w = rng.normal(size=(tg.size, 2))
    b = np.empty((tg.size, 2))
    b[0] = s_b * w[0]
    for k in range(1, tg.size):
        b[k] = a * b[k - 1] + s_b * math.sqrt(1 - a * a) * w[k]
    g = traj.interpolate(tg)[:, :2] + b + s_w * rng.normal(size=b.shape)
    return traj, tg, g, b


def _every_tenth(tg, g):
    fused = np.arange(tg.size) % 10 == 0  # 2 s apart, as Victoria Park's every 10th fix
    return fused, GnssFixes(tg[fused], g[fused], np.ones(int(fused.sum())))


@pytest.mark.parametrize(("tau", "dur"), [(18.0, 1500.0), (60.0, 3000.0)])
def test_model_recovers_the_time_constant_and_the_track_beats_the_path(tau, dur):
    """The time constant comes back within 45 %: over seeds 0-19 of this simulation the
    estimate is 17.8 +- 2.7 s (range 14.5-25.2) for T = 18 s over 1500 s, and 57.0 +- 4.9 s
    (47.8-65.7, seeds 0-9) for T = 60 s over 3000 s -- about the spread of a correlation time
    seen for L / T = 50-80 correlation times, sqrt(2 T / L) ~ 0.15-0.2; 45 % is 3 sigmas of
    the 18-s case, and a model hard-coded to either T fails the other case. The bias std
    within 20 % (0.80 +- 0.04 / 0.79 +- 0.04 m for 0.8 m). The track (path + offset, the model
    fitted on the fixes before the middle only) beats the raw path on the held-out fixes of the
    second half by > 3x."""
    traj, tg, g, _ = _gm_run(0, tau, dur)
    fused, fx = _every_tenth(tg, g)
    m = fit_gnss_offset_model(traj, fx)
    assert abs(m.time_constant - tau) < 0.45 * tau
    assert abs(m.bias_sigma - 0.8) < 0.2 * 0.8
    assert m.resolved and m.n_fixes == int(fused.sum())
    first = fx.select(fx.times < 0.5 * dur)
    m1 = fit_gnss_offset_model(traj, first)
    track = gnss_frame_trajectory(traj, gnss_offset(traj, fx, model=m1))
    held = ~fused & (tg >= 0.5 * dur)
    raw = ate(traj, tg[held], g[held], align=False).rmse
    got = ate(track, tg[held], g[held], align=False).rmse
    assert raw > 0.8 and got < raw / 3.0


def test_offset_std_is_calibrated_between_the_fixes():
    """With the true model, the smoothed offset's error against the true bias at every 5 Hz
    reading (4 of 5 between the fused fixes) has a z-score RMS near 1 (0.8-1.25), and so does
    the causal (filter) estimate, whose error is larger."""
    traj, tg, g, b = _gm_run(1, 18.0, 1200.0)
    _, fx = _every_tenth(tg, g)
    kw = {"time_constant": 18.0, "prior_sigma": 0.8, "fix_sigma": 0.1}
    errs = {}
    for causal in (False, True):
        off = gnss_offset(traj, fx, causal=causal, **kw)
        inside = (tg >= fx.times[0]) & (tg <= fx.times[-1])
        e = off.at(tg[inside]) - b[inside]
        z = e / off.std_at(tg[inside])[:, None]
        assert 0.8 < math.sqrt(np.mean(z**2)) < 1.25
        errs[causal] = math.sqrt(np.mean(e**2))
    assert errs[True] > errs[False]


def test_causal_offset_uses_only_past_fixes():
    """Moving a later fix changes the smoothed offset before it but not the causal one; the
    causal offset decays from the last fix as exp(-dt / T) and its std grows towards the
    stationary std; before the first fix it is the prior (0, prior_sigma)."""
    traj, tg, g, _ = _gm_run(2, 18.0, 300.0)
    _, fx = _every_tenth(tg, g)
    moved = np.array(fx.xy)
    moved[80] += 5.0
    fx2 = GnssFixes(fx.times, moved, fx.sigma)
    kw = {"time_constant": 18.0, "prior_sigma": 0.8, "fix_sigma": 0.1}
    tq = np.linspace(fx.times[0], fx.times[79] + 1.0, 50)
    c1 = gnss_offset(traj, fx, causal=True, **kw)
    c2 = gnss_offset(traj, fx2, causal=True, **kw)
    np.testing.assert_array_equal(c1.at(tq), c2.at(tq))
    s1, s2 = gnss_offset(traj, fx, **kw), gnss_offset(traj, fx2, **kw)
    assert np.abs(s1.at(tq[-5:]) - s2.at(tq[-5:])).max() > 0.1
    k, dt = 40, 1.0
    np.testing.assert_allclose(
        c1.at([fx.times[k] + dt])[0], c1.offset[k] * math.exp(-dt / 18.0), rtol=1e-12
    )
    far = c1.std_at([fx.times[-1] + 1000.0])[0]
    assert c1.std[-1] < c1.std_at([fx.times[-1] + 5.0])[0] < far
    assert far == pytest.approx(0.8, rel=1e-6)
    early = GnssFixes(fx.times + 5.0, fx.xy, fx.sigma)
    c3 = gnss_offset(traj, early, causal=True, **kw)
    np.testing.assert_array_equal(c3.at([1.0]), [[0.0, 0.0]])
    assert c3.std_at([1.0])[0] == pytest.approx(0.8)


def test_smoothed_std_at_fixes_and_across_an_outage():
    """At the fixes ``std_at`` is the smoother's std; in the middle of a 100-s outage with
    T = 10 s it is close to the stationary std (the bridge forgets both ends)."""
    t = np.arange(0.0, 300.0, 0.5)
    traj = Trajectory(t, np.column_stack((t, np.zeros_like(t), np.zeros_like(t))))
    tg = np.concatenate((np.arange(1.0, 100.0, 2.0), np.arange(200.0, 299.0, 2.0)))
    rng = np.random.default_rng(4)
    fx = GnssFixes(
        tg, np.column_stack((tg, np.zeros_like(tg))) + rng.normal(0, 0.5, (tg.size, 2)), 1.0
    )
    off = gnss_offset(traj, fx, time_constant=10.0, prior_sigma=0.5, fix_sigma=0.1)
    np.testing.assert_allclose(off.std_at(off.times), off.std, rtol=1e-9, atol=1e-12)
    mid = off.std_at([150.0])[0]
    assert 0.49 < mid <= 0.5 + 1e-9
    assert off.std_at([98.0])[0] < 0.2


def test_too_few_fixes_is_a_clear_error():
    traj, tg, g, _ = _gm_run(3, 18.0, 100.0)
    fx = GnssFixes(tg[::25], g[::25], np.ones(tg[::25].size))
    with pytest.raises(InputError, match=r"20 fixes inside the run, need at least 30"):
        fit_gnss_offset_model(traj, fx)
    with pytest.raises(InputError, match="no fix"):
        gnss_offset(traj, GnssFixes(np.array([500.0]), np.zeros((1, 2)), np.ones(1)))


def test_offset_filter_online_equals_the_causal_offset():
    """Fed one fix at a time, GnssOffsetFilter gives gnss_offset(causal=True)'s numbers at
    the fixes and between them; before any fix the prior; a fix back in time is an error."""
    from stemmap.slam.gnss_track import GnssOffsetFilter, GnssOffsetModel

    traj, tg, g, _ = _gm_run(5, 18.0, 200.0)
    _, fx = _every_tenth(tg, g)
    model = GnssOffsetModel(time_constant=18.0, bias_sigma=0.8, white_sigma=0.1, n_fixes=0)
    batch = gnss_offset(traj, fx, model=model, causal=True)
    filt = GnssOffsetFilter(model)
    assert filt.at(0.0)[1] == pytest.approx(0.8) and not filt.at(0.0)[0].any()
    resid = fx.xy - traj.interpolate(fx.times)[:, :2]
    for k, (t, r) in enumerate(zip(fx.times, resid, strict=True)):
        filt.update(float(t), r)
        for tq in (float(t), float(t) + 1.3):
            m, s = filt.at(tq)
            np.testing.assert_allclose(m, batch.at([tq])[0], rtol=1e-9, atol=1e-12)
            assert s == pytest.approx(float(batch.std_at([tq])[0]), rel=1e-9)
        assert filt.last_time == t and k < len(fx)
    with pytest.raises(InputError, match="before the last"):
        filt.update(float(fx.times[0]), resid[0])
