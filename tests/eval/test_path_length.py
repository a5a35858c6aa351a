"""``path_length``: distance travelled along a jittered path of poses (the ``distance_m`` of the
odometry and map commands), and ``rpe``'s stretches along a jittered reference.

The jitter is 1 cm per axis per pose, white: KISS-ICP's step errors on the simulated 2D log of
tests/cli/test_odometry_distance.py were 1.2-1.5 cm per axis (sqrt(2) sigma); the steps are
1.33 cm, a SICK-like scanner at 75 Hz on a 1 m/s drive.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.eval.trajectory import path_length, rpe
from stemmap.types import Trajectory

SIGMA = 0.01  # m per axis per pose
STEP = 1.0 / 75.0  # m


def _line(length: float) -> np.ndarray:
    n = round(length / STEP) + 1
    return np.column_stack((np.linspace(0.0, length, n), np.zeros(n)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jittered_straight_line(seed: int) -> None:
    """20 m: the step sum reads the jitter (+40 % and more); the chords of >= 0.5 m are within
    0.5 % -- the cross-track jitter adds sigma^2 / L^2 = 0.04 %, the along-track jitter cancels
    except at the two ends (3 sigma of their difference: 3 * sqrt(2) * 1 cm = 4.2 cm, 0.21 %
    of 20 m)."""
    xy = _line(20.0) + np.random.default_rng(seed).normal(0.0, SIGMA, (1501, 2))
    assert path_length(xy, min_step=0.0) > 1.4 * 20.0
    assert path_length(xy) == pytest.approx(20.0, rel=0.005)


def test_circle_chord_bias_is_the_documented_one() -> None:
    """A noise-free 5 m radius circle sampled every 1 cm: the chords (0.50-0.51 m) are short by
    c^2 / (24 R^2) = 0.042 % of the arc; the polyline (min_step 0) is exact to 1e-6."""
    r = 5.0
    true_len = 2.0 * math.pi * r
    a = np.linspace(0.0, 2.0 * math.pi, round(true_len / 0.01) + 1)
    xy = r * np.column_stack((np.cos(a), np.sin(a)))
    assert path_length(xy, min_step=0.0) == pytest.approx(true_len, rel=1e-6)
    deficit = 1.0 - path_length(xy) / true_len
    assert deficit == pytest.approx(0.5**2 / (24 * r**2), rel=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jittered_circle(seed: int) -> None:
    """The same circle at 1.33 cm steps with the jitter: step sum +40 % and more, chords within
    0.5 % (-0.042 % chord bias, +0.04 % jitter, the end points as on the line)."""
    r = 5.0
    true_len = 2.0 * math.pi * r
    a = np.linspace(0.0, 2.0 * math.pi, round(true_len / STEP) + 1)
    xy = r * np.column_stack((np.cos(a), np.sin(a)))
    xy += np.random.default_rng(seed).normal(0.0, SIGMA, xy.shape)
    assert path_length(xy, min_step=0.0) > 1.4 * true_len
    assert path_length(xy) == pytest.approx(true_len, rel=0.005)


def test_standing_still_reads_the_jitter_once() -> None:
    """1000 frames of a parked vehicle: the step sum is ~1000 jitter steps (~18 m), the chords
    at most one jitter difference (the first-to-last chord: < 0.1 m)."""
    xy = np.random.default_rng(0).normal(0.0, SIGMA, (1000, 2))
    assert path_length(xy, min_step=0.0) > 15.0
    assert path_length(xy) < 0.1


def test_inputs_and_the_last_pose_are_kept() -> None:
    xy = np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.0], [0.7, 0.0]])
    # kept: 0, 2 (0.6 >= 0.5) and the last (0.1 m past it)
    assert path_length(xy) == pytest.approx(0.7)
    poses = np.column_stack((xy, np.arange(4.0)))
    assert path_length(poses) == path_length(Trajectory(np.arange(4.0), poses)) == path_length(xy)
    assert path_length(xy, min_step=1.0) == pytest.approx(0.7)  # first to last
    assert path_length(xy[:1]) == 0.0
    assert path_length(np.zeros((0, 2))) == 0.0


def test_bad_inputs() -> None:
    with pytest.raises(ConfigError, match="min_step"):
        path_length(np.zeros((3, 2)), min_step=-0.1)
    with pytest.raises(ConfigError, match="min_step"):
        path_length(np.zeros((3, 2)), min_step=math.nan)
    with pytest.raises(InputError, match="shape"):
        path_length(np.zeros((3, 4)))
    with pytest.raises(InputError, match="position 1 is not finite"):
        path_length(np.array([[0.0, 0.0], [math.nan, 1.0], [2.0, 2.0]]))


def test_rpe_stretches_along_a_jittered_reference() -> None:
    """45 m of jittered line as its own reference: 10 m stretches along it fit 4 times when
    measured by the chords, 6 or more times by the jitter-lengthened step sum."""
    xy = _line(45.0)
    xy += np.random.default_rng(0).normal(0.0, SIGMA, xy.shape)
    ref = Trajectory(np.arange(len(xy)) / 75.0, np.column_stack((xy, np.zeros(len(xy)))))
    assert rpe(ref, ref, delta=10.0, min_step=0.5).n == 4
    assert rpe(ref, ref, delta=10.0).n >= 6
    with pytest.raises(ConfigError, match="min_step"):
        rpe(ref, ref, min_step=-1.0)
