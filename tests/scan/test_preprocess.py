import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap import ConfigError, InputError
from stemmap.scan.preprocess import (
    fov_window,
    gate_ranges,
    median_filter3,
    project_tilted,
    rotation_rpy,
    tilt_compensate,
)


def test_gate_marks_out_of_window_as_nan_and_keeps_input():
    r = np.array([0.01, 0.05, 1.0, 7.99, 8.0, np.inf, np.nan, -1.0])
    out = gate_ranges(r, 0.05, 8.0)
    expect = [np.nan, np.nan, 1.0, 7.99, np.nan, np.nan, np.nan, np.nan]
    np.testing.assert_array_equal(out, expect)
    assert r[0] == 0.01  # input untouched


def test_gate_batch_and_bad_window():
    r = np.full((3, 5), 2.0)
    r[1, 2] = 9.0
    out = gate_ranges(r, 0.0, 8.0)
    assert out.shape == (3, 5) and np.isnan(out[1, 2]) and np.isfinite(out).sum() == 14
    with pytest.raises(ConfigError, match="range_min < range_max"):
        gate_ranges(r, 5.0, 1.0)


def test_bad_range_arrays():
    with pytest.raises(InputError, match="zero beams"):
        gate_ranges(np.zeros(0))
    with pytest.raises(InputError, match=r"\(N,\) or \(S, N\)"):
        gate_ranges(np.zeros((2, 2, 2)))
    with pytest.raises(InputError, match="numeric"):
        gate_ranges(["a", "b"])


def test_fov_window_zheng_100_degrees():
    # Zheng 2012: 0.25 deg from 40 to 140 deg (90 = forward) -> 401 beams inside +-50 deg
    a = np.radians(np.arange(-90.0, 90.0 + 1e-9, 0.25))
    r = np.ones((2, a.size))
    out = fov_window(r, a, math.radians(-50.0), math.radians(50.0))
    assert np.isfinite(out[0]).sum() == 401
    with pytest.raises(InputError, match="beams"):
        fov_window(r, a[:-1], -1.0, 1.0)
    with pytest.raises(ConfigError):
        fov_window(r, a, 1.0, -1.0)


def test_median_filter_removes_spike_keeps_edges_and_dropout_neighbours():
    r = np.array([5.0, 5.0, 9.0, 5.0, 5.0, 20.0, 20.0, np.nan, 3.0, 4.0])
    out = median_filter3(r)
    np.testing.assert_array_equal(out[:7], [5.0, 5.0, 5.0, 5.0, 5.0, 20.0, 20.0])
    # next to a "no return" the value is kept (decision: never invent or erase a return)
    assert np.isnan(out[7]) and out[8] == 3.0 and out[9] == 4.0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.1, 50.0), min_size=3, max_size=40))
def test_median_filter_properties(values):
    r = np.array(values)
    out = median_filter3(r)
    # each output is one of its three inputs, ends unchanged, constant runs preserved
    assert out[0] == r[0] and out[-1] == r[-1]
    for i in range(1, len(r) - 1):
        assert out[i] in r[i - 1 : i + 2]
    np.testing.assert_array_equal(median_filter3(np.full(7, 2.5)), np.full(7, 2.5))
    # batch == row by row
    np.testing.assert_array_equal(
        median_filter3(np.stack([r, r[::-1]]))[1], median_filter3(r[::-1])
    )


def test_tilt_eq1_and_batch_attitudes():
    r = np.full((2, 4), 2.0)
    out = tilt_compensate(r, np.radians([0.0, 60.0]), 0.0)
    np.testing.assert_allclose(out[0], 2.0)
    np.testing.assert_allclose(out[1], 1.0)
    with pytest.raises(InputError, match="one value per scan"):
        tilt_compensate(r, np.zeros(3), 0.0)
    with pytest.raises(InputError, match="90"):
        tilt_compensate(r, 2.0, 0.0)


def test_rotation_is_orthonormal():
    R = rotation_rpy([0.1, -0.3], [0.2, 0.05], [0.0, 1.0])
    for m in R:
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(m) == pytest.approx(1.0)


def test_projection_matches_eq1_where_eq1_is_exact_and_differs_elsewhere():
    a = np.radians([0.0, 90.0])
    pitch = math.radians(10.0)
    h, b, z = project_tilted(np.array([4.0, 4.0]), a, 0.0, pitch)
    # beam along x under pitch: horizontal length r cos(pitch) = eq. 1
    assert h[0] == pytest.approx(float(tilt_compensate([4.0], 0.0, pitch)[0]), rel=1e-12)
    # beam along y (the pitch axis) is not shortened at all; eq. 1 would shorten it
    assert h[1] == pytest.approx(4.0, rel=1e-12)
    assert z[0] == pytest.approx(-4.0 * math.sin(pitch))
    assert b[1] == pytest.approx(math.pi / 2)


def test_projection_batch_and_small_tilt_agreement():
    a = np.radians(np.arange(-50.0, 50.5, 0.5))
    r = np.full((3, a.size), 6.0)
    h, _, _ = project_tilted(r, a, np.radians([1.0, 2.0, 3.0]), np.radians([2.0, 1.0, 0.0]))
    eq1 = tilt_compensate(r, np.radians([1.0, 2.0, 3.0]), np.radians([2.0, 1.0, 0.0]))
    # eq. 1 errs by at most 1 - cos(roll) cos(pitch) of the range (beam along a tilt axis)
    bound = 6.0 * (1 - np.cos(np.radians([1.0, 2.0, 3.0])) * np.cos(np.radians([2.0, 1.0, 0.0])))
    assert np.all(np.max(np.abs(h - eq1), axis=1) <= bound + 1e-12)
    assert np.max(np.abs(h - eq1)) > 0.5 * bound.max()  # and the bound is attained
    with pytest.raises(InputError, match="per-scan attitude"):
        project_tilted(r, a, np.zeros(2), 0.0)


def test_seam_shift_and_roll():
    from stemmap.scan.preprocess import roll_beams, seam_shift

    r = np.array([[1.0, 1.0, np.nan, 5.0], [1.0, 1.0, 5.0, 2.0], [2.0, 2.0, 2.0, 9.0]])
    sh = seam_shift(r)
    # first missing beam; else the largest jump, wrapping (9 -> 2 between beams 3 and 0)
    assert sh.tolist() == [2, 2, 0]
    rolled = roll_beams(r, sh)
    assert np.isnan(rolled[0, 0]) and rolled[1].tolist() == [5.0, 2.0, 1.0, 1.0]
    np.testing.assert_array_equal(np.sort(rolled, axis=1), np.sort(r, axis=1))
    assert roll_beams(np.arange(4.0), [1, 3]).tolist() == [[1, 2, 3, 0], [3, 0, 1, 2]]
    with pytest.raises(InputError):
        roll_beams(r, [0, 1])
