"""The ground and understory of the virtual scans (stemmap.eval.scan_background, issue 11,
fifteenth round)."""

import math

import numpy as np
import pytest

from stemmap.datasets import find_datasets_dir
from stemmap.errors import InputError
from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch, virtual_scans
from stemmap.eval.scan_background import (
    GroundSurface,
    Mount,
    Relief,
    band_points,
    ground_ranges,
)
from stemmap.scan.plausibility import scan_noise

FLAT = GroundSurface.flat("test")


def _beam(res_deg, bearing_deg):
    return round((bearing_deg + 180.0) / res_deg)


def test_a_pitched_beam_meets_flat_ground_at_height_over_tan_pitch_ahead_and_never_behind():
    m = Mount(height=1.3, pitch_deg=3.0)
    b = np.radians([0.0, 30.0, 89.0, 120.0, 180.0])
    s = ground_ranges(FLAT, b, 0.0, m, max_range=100.0)
    ahead = 1.3 / math.tan(math.radians(3.0))  # 24.8 m
    assert s[0] == pytest.approx(ahead, rel=1e-9)
    # the plane's cut with flat ground is a straight line across the heading: x = 24.8 m
    assert s[1] * math.cos(math.radians(30.0)) == pytest.approx(ahead, rel=1e-9)
    assert np.isinf(s[2]) and np.isinf(s[3]) and np.isinf(s[4])  # beyond 100 m, or rising
    assert np.isinf(ground_ranges(FLAT, b[:1], 0.0, m, max_range=20.0)[0])
    # uphill (the ground rising 7 % along the beam) it comes nearer: 1.3 / (0.07 + tan 3 deg)
    up = GroundSurface((0.07, 0.0), np.zeros((0, 3)), "test")
    assert ground_ranges(up, b[:1], 0.0, m, 100.0)[0] == pytest.approx(
        1.3 / (0.07 + math.tan(math.radians(3.0)))
    )
    # a beam pitched towards 90 deg: its 0-deg beam stays level, never meets flat ground
    assert np.isinf(ground_ranges(FLAT, b[:1], math.pi / 2, m, 100.0)[0])


def test_the_band_keeps_the_understory_points_the_pitched_plane_passes_through():
    m = Mount(height=1.3, pitch_deg=3.0, band=0.1)
    drop = 5.0 * math.tan(math.radians(3.0))  # 26 cm lower at 5 m ahead
    pts = np.array(
        [
            [5.0, 0.0, 1.3 - drop],  # on the beam
            [5.0, 0.0, 1.3 - drop + 0.04],  # within 5 cm
            [5.0, 0.0, 1.3 - drop + 0.2],  # above it
            [-5.0, 0.0, 1.3 + drop],  # behind: the plane rises
            [-5.0, 0.0, 1.3 - drop],  # behind, below it
        ]
    )
    surf = GroundSurface((0.0, 0.0), pts, "test")
    got = band_points(surf, np.zeros(2), 0.0, m)
    assert got.tolist() == [[5.0, 0.0], [5.0, 0.0], [-5.0, 0.0]]
    assert band_points(FLAT, np.zeros(2), 0.0, m).shape == (0, 2)


def test_relief_has_its_std_and_the_first_bump_a_beam_grazes_answers():
    rel = Relief.random(40.0, seed=3, std=0.04, corr=0.3)
    assert float(rel.z.std()) == pytest.approx(0.04, rel=1e-6)
    # neighbouring cells correlate (0.1 m apart, 0.3 m correlation), distant ones do not
    z = rel.z
    near = np.corrcoef(z[:, :-1].ravel(), z[:, 1:].ravel())[0, 1]
    far = np.corrcoef(z[:, :-20].ravel(), z[:, 20:].ravel())[0, 1]
    assert near > 0.9 and abs(far) < 0.1
    m = Mount(height=1.3, pitch_deg=3.0)
    b = np.radians(np.arange(-20.0, 20.0, 0.5))
    plane = ground_ranges(FLAT, b, 0.0, m, 30.0)
    rough = ground_ranges(FLAT, b, 0.0, m, 30.0, np.zeros(2), rel)
    assert np.all(np.isfinite(rough))
    # the relief moves the first echo by up to its largest height / tan(pitch), both ways
    lim = float(np.abs(z).max()) / math.tan(math.radians(3.0)) / np.cos(b) + 0.05
    assert np.all(np.abs(rough - plane) <= lim)
    assert np.std(rough - plane) > 0.2  # grazing incidence: cm of relief are dm of range
    flat = Relief(np.zeros((5, 5)), (-1.0, -1.0), 0.5)
    assert np.allclose(ground_ranges(FLAT, b, 0.0, m, 30.0, np.zeros(2), flat), plane, atol=0.01)


def test_virtual_scans_with_ground_fill_missed_beams_and_keep_the_trunks():
    phi = np.arange(-math.pi, math.pi, 0.002 / 0.2)
    trunk = np.column_stack((5.0 + 0.2 * np.cos(phi), 0.2 * np.sin(phi)))
    far = np.column_stack((-28.0 + 0.2 * np.cos(phi), 0.2 * np.sin(phi)))
    xy = np.vstack((trunk, far))
    lab = np.r_[np.zeros(len(phi), dtype=np.int64), np.ones(len(phi), dtype=np.int64)]
    cen = [[5.0, 0.0], [-28.0, 0.0]]
    o = np.zeros((1, 2))
    r0, h0 = virtual_scans(xy, lab, o, resolution_deg=0.5, centers=cen)
    same = virtual_scans(
        xy, lab, o, resolution_deg=0.5, centers=cen, background="none", ground=FLAT
    )
    assert np.array_equal(r0, same[0]) and np.array_equal(h0, same[1])
    m = Mount(height=1.3, pitch_deg=3.0)
    for heading, hidden in ((0.0, False), (math.pi, True)):
        r, h = virtual_scans(
            xy, lab, o, resolution_deg=0.5, centers=cen, background="ground", mount=m,
            headings=[heading],
        )  # fmt: skip
        # the near trunk is hit as before; the beams that missed it now hit the ground ahead
        assert np.array_equal(r[0, h0[0] == 0], r0[0, h0[0] == 0])
        k = _beam(0.5, math.degrees(heading) - 10.0 if heading else 10.0)
        assert h[0, k] == -1 and r[0, k] == pytest.approx(24.8 / math.cos(math.radians(10)), 0.01)
        # the trunk 28 m away lies beyond the ground's line when the mount faces it
        assert bool(np.any(h[0] == 1)) is not hidden
    with pytest.raises(InputError, match="background must be"):
        virtual_scans(xy, lab, o, resolution_deg=0.5, background="walls")  # type: ignore[arg-type]


def test_slices_know_their_ground():
    ddir = find_datasets_dir()
    if ddir is None:
        pytest.skip("shared datasets not found")
    for name, spec in SLICES.items():
        g = load_slice(ddir, name).ground
        assert g is not None
        if spec.ground_points:  # a plane from the cloud's ground and the points below the slice
            assert g.source.startswith("cloud") and g.points.shape[0] > 500, name
            assert np.all(g.points[:, 2] < 1.3) and abs(np.median(g.points[:, 2])) < 0.5
            assert 0.0 < math.hypot(*g.gradient) < 0.15
        else:
            assert g.source.startswith("flat") and g.points.shape[0] == 0, name


@pytest.mark.parametrize("name", ["fortls_slice", "treels_pine_plot"])
def test_the_ground_gives_the_scan_noise_estimate_what_the_trunks_alone_do_not(name):
    """The scan's own noise estimate (sigma_from_scan) on the plots' virtual scans, 0.5 deg
    first echo, 10 vantages 2-6 m from a trunk: with the ground (the TreeLS plot's
    micro-relief, pitch 3 deg) every scan has an estimate (without it half of the FORTLS
    scans have none: its trunks are perfect circles, few continuous triples), within 20 % of
    3 cm of added noise; at 0 and 1 cm it reads up to ~1 cm more (the plot's understory and
    the relief at grazing incidence: FORTLS 0.3 / 1.4 / 2.9 cm, TreeLS plot 1.2 / 1.6 /
    3.4 cm when this test was written)."""
    ddir = find_datasets_dir()
    if ddir is None:
        pytest.skip("shared datasets not found")
    sl = load_slice(ddir, name)
    rng = np.random.default_rng(5)
    vp = sl.centers[rng.integers(len(sl.refs), size=10)] + rng.uniform(2.0, 6.0, (10, 1)) * [
        [math.cos(a), math.sin(a)] for a in rng.uniform(-math.pi, math.pi, 10)
    ]
    heads = rng.uniform(-math.pi, math.pi, 10)
    none, _ = virtual_scans(sl.xy, sl.labels, vp, resolution_deg=0.5, centers=sl.centers)
    grd, _ = virtual_scans(
        sl.xy, sl.labels, vp, resolution_deg=0.5, centers=sl.centers, background="ground",
        ground=sl.ground, headings=heads, relief=Relief.random(60.0, 5),
    )  # fmt: skip
    est = {}
    for label, r0 in (("none", none), ("ground", grd)):
        for noise in (0.0, 0.01, 0.03):
            r = noisy_batch(r0, 0.5, noise, np.random.default_rng(1)).ranges
            est[label, noise] = scan_noise(np.where(r < 30.0, r, np.nan), 0.2)
    for noise in (0.0, 0.01, 0.03):
        share = np.mean(est["ground", noise] > 0)
        assert share >= 0.9 and share >= np.mean(est["none", noise] > 0)
    if name == "fortls_slice":
        assert np.mean(est["none", 0.03] > 0) <= 0.6
    med = {n: float(np.median(est["ground", n])) for n in (0.0, 0.01, 0.03)}
    assert med[0.0] < 0.016
    assert 0.01 <= med[0.01] <= 0.02
    assert 0.024 <= med[0.03] <= 0.036
