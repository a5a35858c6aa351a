import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap import ConfigError, InputError
from stemmap.scan.segment import (
    build_segments,
    euclidean_breaks,
    extract_points,
    range_jump_breaks,
)

INC = math.radians(0.5)


def _pts(ranges):
    r = np.asarray(ranges, dtype=float)
    n = r.shape[-1]
    return extract_points(r, INC * np.arange(n), INC)


def test_extract_points_flattens_valid_returns_of_a_batch():
    r = np.array([[1.0, np.nan, 2.0], [np.inf, 3.0, 4.0]])
    p = _pts(r)
    assert p.scan.tolist() == [0, 0, 1, 1] and p.beam.tolist() == [0, 2, 1, 2]
    np.testing.assert_allclose(p.r, [1, 2, 3, 4])
    np.testing.assert_allclose(np.hypot(p.x, p.y), p.r)
    with pytest.raises(InputError, match="beam angles"):
        extract_points(r, np.zeros(2), INC)
    with pytest.raises(InputError, match="non-zero"):
        extract_points(r, np.zeros(3), 0.0)


def test_range_jump_zheng_eq2_threshold():
    # 0.19 m steps stay together, a 0.21 m step splits (Zheng: Delta l_max = 0.2 m)
    r = [5.0, 5.19, 5.38, 5.59, 5.6]
    brk = range_jump_breaks(_pts(r), 0.2)
    assert brk.tolist() == [True, False, False, True, False]
    with pytest.raises(ConfigError):
        range_jump_breaks(_pts(r), 0.0)


def test_missing_beams_split_unless_bridged_and_scans_never_merge():
    r = np.array([[5.0, 5.0, np.nan, 5.0, 5.0], [5.0, 5.0, 5.0, 5.0, 5.0]])
    p = _pts(r)
    b0 = range_jump_breaks(p, 0.2, max_skip=0)
    b1 = range_jump_breaks(p, 0.2, max_skip=1)
    assert int(b0.sum()) == 3  # two pieces in scan 0, one in scan 1
    assert int(b1.sum()) == 2  # the dropout is bridged; the scan boundary always breaks
    with pytest.raises(ConfigError):
        range_jump_breaks(p, 0.2, max_skip=-1)


def test_euclidean_fixed_and_adaptive():
    # a wall at 20 m: returns 0.5 deg apart are 0.175 m apart
    r = np.full(10, 20.0)
    p = _pts(r)
    assert int(euclidean_breaks(p, 0.1).sum()) == 10  # fixed 0.1 m splits every return
    # adaptive: 0.1 + 3 * r * dtheta = 0.62 m keeps the wall in one piece
    assert int(euclidean_breaks(p, 0.1, range_factor=3.0).sum()) == 1
    with pytest.raises(ConfigError):
        euclidean_breaks(p, 0.1, range_factor=-1.0)


def test_occlusion_and_truncation_flags():
    # beams: far background, near occluder, trunk, background, trunk touching the last beam
    r = np.array([[9.0, 2.0, 2.0, 5.0, 5.0, 5.0, 9.0, 9.0, 4.0, 4.0]])
    p = _pts(r)
    segs = build_segments(p, range_jump_breaks(p, 0.2), ranges=r)
    assert segs.counts.tolist() == [1, 2, 3, 2, 2]
    # the 5 m trunk's start is hidden behind the 2 m occluder; its end is free (background);
    # the 9 m background piece is occluded on both sides (by the 5 m and the 4 m trunks)
    assert segs.occluded_start.tolist() == [False, False, True, True, False]
    assert segs.occluded_end.tolist() == [True, False, False, True, False]
    assert segs.truncated_start.tolist() == [True, False, False, False, False]
    assert segs.truncated_end.tolist() == [False, False, False, False, True]
    # without the grid, the same flags from neighbouring returns
    segs2 = build_segments(p, range_jump_breaks(p, 0.2))
    np.testing.assert_array_equal(segs2.occluded_start, segs.occluded_start)
    np.testing.assert_array_equal(segs2.occluded_end, segs.occluded_end)
    with pytest.raises(InputError, match="breaks"):
        build_segments(p, np.zeros(len(p), dtype=bool))


def test_select_and_split_keep_tables_consistent():
    r = np.array([[5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 9.0, 9.0, 9.0]])
    p = _pts(r)
    segs = build_segments(p, range_jump_breaks(p, 0.2), ranges=r)
    sel = segs.select(segs.counts >= 4)
    assert len(sel) == 1 and sel.counts.tolist() == [6] and len(sel.points) == 6
    keep = np.ones(len(sel.points), dtype=bool)
    keep[2] = False
    parts = sel.split(keep)
    assert parts.counts.tolist() == [2, 3]
    # the cut ends are marked occluded (the piece continued into something else)
    assert parts.occluded_end.tolist() == [True, False]
    assert parts.occluded_start.tolist() == [False, True]
    assert sel.split(keep, min_points=3).counts.tolist() == [3]


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.one_of(st.floats(0.2, 30.0), st.just(float("nan"))), min_size=1, max_size=60),
    st.integers(1, 4),
)
def test_segments_partition_the_returns(values, n_scans):
    r = np.tile(np.array(values), (n_scans, 1))
    p = _pts(r)
    segs = build_segments(p, range_jump_breaks(p, 0.2, max_skip=1), ranges=r)
    # segments tile the returns exactly, never span two scans, and are identical per scan
    assert int(segs.counts.sum()) == len(p)
    if len(segs):
        assert segs.start[0] == 0 and np.all(segs.start[1:] == segs.stop[:-1])
        assert np.all(p.scan[segs.start] == p.scan[segs.stop - 1])
        per_scan = np.bincount(segs.scan, minlength=n_scans)
        assert np.all(per_scan == per_scan[0])


def _arc_scan(points_xy):
    """One scan whose returns are ``points_xy`` (sensor at the origin), in bearing order."""
    th = np.arctan2(points_xy[:, 1], points_xy[:, 0])
    order = np.argsort(th)
    inc = 0.001
    beams = np.round((th[order] - th[order][0]) / inc).astype(int)
    ranges = np.full((1, int(beams[-1]) + 1), np.inf)
    ranges[0, beams] = np.hypot(*points_xy[order].T)
    angles = th[order][0] + inc * np.arange(ranges.shape[1])
    pts = extract_points(ranges, angles, inc)
    return build_segments(pts, np.r_[True, np.zeros(len(pts) - 1, dtype=bool)])


def test_concave_corner_at_a_trunk_branch_junction_and_none_on_the_arc():
    from stemmap.scan.segment import concave_corners

    # a trunk (r 15 cm at 5 m) seen from the sensor, and a branch leaving its silhouette edge
    # sideways: the junction lies behind the chord of its neighbours
    phi = np.linspace(math.pi - 1.2, math.pi + 1.2, 40)
    arc = np.column_stack((5.0 + 0.15 * np.cos(phi), 0.15 * np.sin(phi)))
    tip = arc[0]
    branch = tip + np.outer(np.linspace(0.03, 0.5, 15), [0.0, 1.0])
    segs = _arc_scan(np.vstack((arc, branch)))
    corners = concave_corners(segs, span=2, depth=0.005)
    assert corners.sum() == 1
    junction = segs.points.x[corners], segs.points.y[corners]
    assert np.hypot(junction[0] - tip[0], junction[1] - tip[1]) < 0.05
    # the trunk alone: convex everywhere (the 1 mrad beam grid moves returns by <= 2.5 mm)
    assert not concave_corners(_arc_scan(arc), span=2, depth=0.005).any()
    with pytest.raises(ConfigError):
        concave_corners(segs, span=0)
    with pytest.raises(ConfigError):
        concave_corners(segs, depth=0.0)
