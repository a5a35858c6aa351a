import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap import ConfigError
from stemmap.scan.features import (
    chord_width,
    cluster_curvature,
    footprint_correct,
    is_straight,
    line_bulge_gain,
    line_fit_rms,
    point_curvature,
    radius_median_filter,
    sagitta_depth,
    segment_features,
)
from stemmap.scan.segment import build_segments, extract_points, range_jump_breaks

INC = math.radians(0.5)


def trunk_ranges(distance, radius, angles):
    """Exact ranges to a circle centred on the x axis (inf where missed)."""
    b = distance * np.cos(angles)
    disc = b * b - (distance * distance - radius * radius)
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)


def segments_of(r, jump=0.2):
    r = np.atleast_2d(np.asarray(r, dtype=float))
    n = r.shape[1]
    a = INC * (np.arange(n) - n // 2)
    p = extract_points(np.where(np.isfinite(r), r, np.nan), a, INC)
    return build_segments(p, range_jump_breaks(p, jump), ranges=r)


def test_law_of_cosines_xue_eq12():
    assert chord_width(1.0, 1.0, math.pi / 3) == pytest.approx(1.0)
    assert chord_width(3.0, 4.0, math.pi / 2) == pytest.approx(5.0)
    # a 30 cm trunk at 3 m seen at 0.5 deg: the chord is shorter than the diameter
    # (Xue et al. report 6-16.7 % under-estimation) but within one beam spacing of it
    a = INC * (np.arange(-40, 41))
    segs = segments_of(trunk_ranges(3.0, 0.15, a))
    f = segment_features(segs)
    assert 0.30 - 2 * 3.0 * INC < f.width[0] < 0.30


@settings(max_examples=50, deadline=None)
@given(st.floats(0.1, 20), st.floats(0.1, 20), st.floats(0.0, math.pi))
def test_chord_width_is_the_euclidean_distance(r0, r1, theta):
    p0 = np.array([r0, 0.0])
    p1 = r1 * np.array([math.cos(theta), math.sin(theta)])
    assert float(chord_width(r0, r1, theta)) == pytest.approx(np.linalg.norm(p1 - p0), abs=1e-9)


def test_point_curvature_zheng_eq3_corrected():
    # second difference l_{i+1} - 2 l_i + l_{i-1}; the printed l_{i+1} - 2 l_{i-1} + l_i
    # would give -1 for the middle of [1, 2, 3] instead of 0 (a straight ramp)
    np.testing.assert_array_equal(point_curvature([1.0, 2.0, 3.0]), [np.nan, 0.0, np.nan])
    segs = segments_of([5.0, 4.9, 5.0, 9.0, 9.0, 9.0])
    cur = point_curvature(segs.points.r, segs)
    assert cur[1] == pytest.approx(0.2) and np.isnan(cur[0]) and np.isnan(cur[2])
    assert np.isnan(cur[3]) and cur[4] == 0.0


def test_depth_curvature_recover_a_half_circle():
    # dense scan of a 0.2 m radius trunk at 1.5 m: sagitta ~ r, curvature ~ 1/r
    a = np.radians(np.arange(-20, 20.01, 0.05))
    r = trunk_ranges(1.5, 0.2, a)
    p = extract_points(np.where(np.isfinite(r), r, np.nan), a, math.radians(0.05))
    segs = build_segments(p, range_jump_breaks(p, 0.2), ranges=r)
    f = segment_features(segs)
    assert len(segs) == 1
    # visible arc from 1.5 m spans at most 2*acos(r/d) = 164.7 deg, so sagitta < r and
    # chord < 2r; exact values from the two edge returns (symmetric about the x axis)
    x_end, y_end = segs.points.x[0], abs(segs.points.y[0])
    assert f.depth[0] == pytest.approx(x_end - (1.5 - 0.2), abs=1e-4)
    assert f.width[0] == pytest.approx(2 * y_end, abs=1e-4)
    assert f.depth[0] < 0.2 * (1 - 0.2 / 1.5) + 1e-9
    # the circle through both edges and the apex is the trunk itself
    assert f.curvature[0] == pytest.approx(1 / 0.2, rel=1e-3)
    assert cluster_curvature(0.4, 0.0) == 0.0


def test_wall_is_straight_trunk_is_not():
    rng = np.random.default_rng(3)
    # wall x = 4 seen over 40 deg, 1 cm noise; a 25 cm trunk at 3 m with the same noise
    a = np.radians(np.arange(-20, 20.01, 0.5))
    wall = 4.0 / np.cos(a) + rng.normal(0, 0.01, a.size)
    trunk = trunk_ranges(3.0, 0.125, a) + rng.normal(0, 0.01, a.size)
    r = np.stack([wall, trunk])
    p = extract_points(np.where(np.isfinite(r), r, np.nan), a, INC)
    segs = build_segments(p, range_jump_breaks(p, 0.2), ranges=r)
    f = segment_features(segs)
    wall_k = int(np.argmax(f.n_points * (segs.scan == 0)))
    trunk_k = int(np.argmax(f.n_points * (segs.scan == 1)))
    # line residual of a wall is the noise (1 cm), of a trunk ~0.31 r (decisively larger)
    assert line_fit_rms(segs)[wall_k] == pytest.approx(0.01, rel=0.35)
    assert f.line_rms[trunk_k] > 0.02
    for kw in ({"n_points": f.n_points}, {}):
        st_ = is_straight(f.line_rms, f.width, 0.01, **kw)
        assert st_[wall_k] and not st_[trunk_k]
    assert abs(sagitta_depth(segs)[wall_k]) < 0.05
    with pytest.raises(ConfigError):
        is_straight(f.line_rms, f.width, 0.01, alpha=2.0)


def test_line_bulge_gain_reads_the_bend_towards_the_sensor():
    # noise-free: a 15 cm stem at 3 m (0.5 deg) bulges towards the sensor, and a parabola
    # takes most of its line residual (exactly the circle's arc is not a parabola: >= 90 %);
    # a hollow (the middle receding by 5 cm) bends away: the same kind of gain, negative
    a = np.radians(np.arange(-20, 20.01, 0.5))
    trunk = trunk_ranges(3.0, 0.075, a)
    hollow = 4.0 + 0.05 * (1.0 - (a / a.max()) ** 2)
    segs = segments_of(np.stack([np.where(np.isfinite(trunk), trunk, np.inf), hollow]))
    g = line_bulge_gain(segs)
    line_rss = segs.counts * line_fit_rms(segs) ** 2
    t, h = int(np.argmax(segs.scan == 0)), int(np.argmax(segs.scan == 1))
    assert 0.9 * line_rss[t] < g[t] <= line_rss[t] * (1 + 1e-9)
    assert -line_rss[h] * (1 + 1e-9) <= g[h] < -0.9 * line_rss[h]


def test_line_bulge_gain_of_a_noisy_wall_is_one_chi_square_degree():
    # a wall at 4 m over 40 deg (0.5 deg) with 3 cm range noise: the gain / sigma^2 is chi^2 with
    # one degree of freedom, signed at random, so P(gain > z_0.99^2 sigma^2) = 1 %; 4 000
    # walls: binomial std 0.16 %, the bounds are > 3 std; E|gain| / sigma^2 = 1 (std of the
    # mean 0.022, +-0.1 is > 4 std)
    rng = np.random.default_rng(11)
    a = np.radians(np.arange(-20, 20.01, 0.5))
    walls = 4.0 / np.cos(a) + rng.normal(0.0, 0.03, (4000, a.size))
    segs = segments_of(walls)
    assert len(segs) == 4000
    g = line_bulge_gain(segs) / 0.03**2
    assert np.mean(np.abs(g)) == pytest.approx(1.0, abs=0.1)
    assert 0.005 < np.mean(g > 2.3263478740408408**2) < 0.015


def test_radius_median_filter_separates_merged_trunks():
    # two trunks side by side at the same range merge under the range-jump rule
    a = np.radians(np.arange(-15, 15.01, 0.25))
    r = np.minimum(
        trunk_ranges(4.0, 0.15, a - math.radians(-4.5)),
        trunk_ranges(4.0, 0.15, a - math.radians(1.5)),
    )
    gap = np.flatnonzero(np.isinf(r))
    # close the gap between them so that they form one cluster
    inner = gap[(gap > np.argmin(np.abs(a + math.radians(4.5)))) & (gap < np.argmin(np.abs(a)))]
    r[inner] = 4.0
    p = extract_points(np.where(np.isfinite(r), r, np.nan), a, math.radians(0.25))
    segs = build_segments(p, range_jump_breaks(p, 0.3), ranges=r)
    assert len(segs) == 1
    keep = radius_median_filter(segs, 0.2)
    assert 0 < keep.sum() < len(keep)
    # paper: the far returns are discarded, one cluster remains
    dropped = segs.drop(keep)
    assert len(dropped) == 1 and dropped.counts[0] == keep.sum()
    # ours: the far returns form their own segments
    parts = segs.cut(keep)
    assert len(parts) >= 2 and int(parts.counts.sum()) == len(keep)
    with pytest.raises(ConfigError):
        radius_median_filter(segs, 0.0)


def test_footprint_correction_restores_nearest_return_geometry():
    # a first-echo scanner with a 0.5 deg footprint at 0.5 deg spacing reports, at the nominal
    # bearing, the nearest point of the trunk within the footprint; after the correction every
    # return lies exactly on the trunk circle (up to the sampling of the footprint)
    d, rad, inc = 4.0, 0.2, math.radians(0.5)
    nominal = inc * np.arange(-20, 21)
    fine = np.linspace(-0.5, 0.5, 401) * inc
    rr = trunk_ranges(d, rad, nominal[:, None] + fine[None, :])
    r = rr.min(axis=1)
    p = extract_points(np.where(np.isfinite(r), r, np.nan), nominal, inc)
    segs = build_segments(p, range_jump_breaks(p, 0.3), ranges=r[None, :])
    assert len(segs) == 1
    resid_raw = np.abs(np.hypot(segs.points.x - d, segs.points.y) - rad)
    fixed = footprint_correct(segs, inc)
    resid = np.abs(np.hypot(fixed.points.x - d, fixed.points.y) - rad)
    assert resid_raw.max() > 5e-3  # the edge returns sit centimetres off the circle
    assert resid.max() < 1e-4  # 1/400 of the footprint: the fine sampling step
    np.testing.assert_array_equal(fixed.points.r, segs.points.r)
    assert footprint_correct(segs, 0.0) is segs
    with pytest.raises(ConfigError):
        footprint_correct(segs, -1.0)
