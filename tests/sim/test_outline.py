"""Real-trunk features of the simulator (issue 11): each changes the outline and the scan as it
should. Used to test the detectors, never to tune them."""

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.scan.plausibility import range_roughness
from stemmap.scan.segment import build_segments, euclidean_breaks, extract_points
from stemmap.sim import (
    Stand,
    add_understory,
    make_trunks_noncircular,
    random_stand,
    scanner_preset,
    simulate_scans,
    trunk_outline,
)
from stemmap.sim.scanner import HIT_CLUTTER


def _radii(xy):
    return np.hypot(xy[:, 0], xy[:, 1])


def test_plain_outline_is_the_circle():
    xy = trunk_outline(0.2, np.random.default_rng(0), n_vertices=64)
    np.testing.assert_allclose(_radii(xy), 0.2, rtol=1e-12)


def test_bark_ridges_have_the_requested_rms_and_keep_the_mean_radius():
    gen = np.random.default_rng(1)
    res = [
        _radii(trunk_outline(0.15, gen, n_vertices=360, bark_rms=0.005)) - 0.15 for _ in range(20)
    ]
    rms = [float(np.sqrt(np.mean(r * r))) for r in res]
    # the ridge profile is normalised to its RMS: exact up to the mean of the harmonics (0)
    np.testing.assert_allclose(rms, 0.005, rtol=1e-9)
    assert abs(float(np.mean(res))) < 1e-4
    # cm-scale ridges: the profile crosses its mean more than 18 times (>= harmonic 9)
    crossings = np.count_nonzero(np.diff(np.sign(res[0])) != 0)
    assert crossings >= 18


def test_lean_stretches_the_section_along_its_azimuth_by_one_over_cos():
    xy = trunk_outline(0.2, np.random.default_rng(2), n_vertices=720, lean_deg=30.0)
    # the longest caliper is along the lean, the shortest across it: ratio 1 / cos(30 deg)
    d = xy[:, None, :] - xy[None, :, :]
    longest = float(np.max(np.hypot(d[..., 0], d[..., 1])))
    assert longest == pytest.approx(0.4 / math.cos(math.radians(30.0)), rel=1e-3)
    assert float(np.min(_radii(xy))) == pytest.approx(0.2, rel=1e-3)


def test_buttress_lobes_reach_one_plus_b_and_leave_the_troughs_at_r():
    xy = trunk_outline(0.3, np.random.default_rng(3), n_vertices=720, buttress=0.2, n_lobes=5)
    r = _radii(xy)
    assert float(r.max()) == pytest.approx(0.36, rel=1e-3)
    assert float(r.min()) == pytest.approx(0.3, rel=1e-9)
    # five lobes: the profile rises above the mid level five times
    above = r > 0.33
    assert np.count_nonzero(above & ~np.roll(above, 1)) == 5


def test_outline_rejects_bad_parameters():
    with pytest.raises(ConfigError, match="lean_deg"):
        trunk_outline(0.2, np.random.default_rng(0), lean_deg=80.0)
    with pytest.raises(ConfigError, match="bark_rms"):
        trunk_outline(0.2, np.random.default_rng(0), bark_rms=-0.01)


def test_default_noncircular_trunks_keep_their_random_stream():
    # the new features draw nothing when off: a stand made before them is unchanged
    s = random_stand(20, (20, 20), rng=4)
    a = make_trunks_noncircular(s, rng=5)
    b = make_trunks_noncircular(s, rng=5, bark_rms=0.0, lean_deg=0.0, buttress=0.0)
    np.testing.assert_array_equal(a.segments, b.segments)


def _trunk_roughness(stand, noise=0.0):
    """Median range roughness of the trunk segments of noise-free scans of ``stand``."""
    poses = np.array([[-4.0, 0.0, 0.0], [0.0, -4.0, math.pi / 2], [4.0, 0.0, math.pi]])
    model = scanner_preset("sick_lms", range_noise=noise, beam_divergence=0.0, sub_beams=1)
    batch, _, _ = simulate_scans(stand, poses, model, rng=0)
    pts = extract_points(batch.ranges, batch.angles, batch.angle_increment)
    segs = build_segments(pts, euclidean_breaks(pts, 0.1), ranges=batch.ranges)
    segs = segs.select(segs.counts >= 10)
    return float(np.median(range_roughness(segs)))


def test_bark_ridges_roughen_the_scanned_arc_like_range_noise_does():
    one = Stand([[0.0, 0.0]], [0.6])

    def trunk(bark):
        return make_trunks_noncircular(
            one, ellipticity=0.0, roughness=0.0, n_vertices=720, bark_rms=bark, rng=1
        )

    # the robust roughness of a smooth arc is its curvature term (~3 mm at 4 m for r = 30 cm);
    # 8 mm ridges at least double it, and 3 mm ridges read like 3 mm of range noise (the
    # scale range_roughness estimates from real segments, issue 11)
    smooth = _trunk_roughness(trunk(0.0))
    assert _trunk_roughness(trunk(0.008)) > 2.0 * smooth
    ratio = _trunk_roughness(trunk(0.003)) / _trunk_roughness(trunk(0.0), noise=0.003)
    assert 0.7 < ratio < 1.4


def test_understory_stems_stand_beside_the_trunks_and_branches_leave_them():
    s = Stand([[0.0, 0.0], [5.0, 0.0]], [0.4, 0.3], bounds=(-3, -3, 8, 3))
    u = add_understory(s, stems_per_tree=3.0, branches_per_tree=2.0, rng=6)
    kinds = np.array(u.clutter_kinds)
    stems = u.clutter_xy[-int(np.count_nonzero(kinds == "understory")) :]
    gap = np.min(np.hypot(*(stems[:, None, :] - s.trees_xy[None]).transpose(2, 0, 1)), axis=1)
    surf = gap - 0.2  # (the nearer tree is within 0.5 m + 2.5 cm of a stem of the other)
    assert np.all(surf > 0.02 - 1e-9) and np.all(gap < 0.2 + 0.5 + 0.05 + 1e-9)
    branches = u.segments[u.segment_owner < 0]
    start = branches[:, :2]
    on = np.min(
        np.abs(np.hypot(*(start[:, None, :] - s.trees_xy[None]).transpose(2, 0, 1)) - s.radii),
        axis=1,
    )
    np.testing.assert_allclose(on, 0.0, atol=1e-12)
    assert np.count_nonzero(kinds == "branch") == branches.shape[0]
    with pytest.raises(ConfigError):
        add_understory(s, stems_per_tree=-1.0)


def test_understory_puts_clutter_returns_and_mixed_pixels_next_to_trunk_returns():
    s = random_stand(15, (12, 12), dbh_mean=0.35, min_spacing=2.0, rng=7)
    u = add_understory(s, stems_per_tree=2.0, branches_per_tree=1.0, rng=8)
    poses = np.array([[6.0, 6.0, a] for a in np.linspace(-math.pi, math.pi, 8, endpoint=False)])
    model = scanner_preset("sick_lms", range_noise=0.0)
    _, hit0, _ = simulate_scans(s, poses, model, rng=0)
    _, hit, mixed = simulate_scans(u, poses, model, rng=0)
    trunk = hit >= 0
    beside = trunk[:, :-1] & (hit[:, 1:] == HIT_CLUTTER) | trunk[:, 1:] & (
        hit[:, :-1] == HIT_CLUTTER
    )
    beside0 = trunk[:, :-1] & (hit0[:, 1:] == HIT_CLUTTER) | trunk[:, 1:] & (
        hit0[:, :-1] == HIT_CLUTTER
    )
    assert np.count_nonzero(beside) > np.count_nonzero(beside0) + 10
    # an averaging (SICK-class) beam straddling a trunk and a stem reports a mixed pixel
    assert np.count_nonzero(mixed) > np.count_nonzero(simulate_scans(s, poses, model, rng=0)[2])
