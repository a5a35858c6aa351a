"""``mixed_end_min_points``: a 3-return trunk is kept when the beam beyond an end is a mixed
return lying behind it (stemmap.scan._mixed_end; issue 11, Dec 6)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.scan._mixed_end import mixed_end_on
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.sim.forest import add_clutter, random_stand
from stemmap.sim.scanner import scanner_preset, simulate_scans
from stemmap.types import LaserScan, ScanBatch

STEP = math.radians(0.5)
N = 121  # beams at -30 .. +30 deg
A0 = -math.radians(30.0)
#: the trunk: 27 cm at 9 m, bearing +0.1 deg, so its silhouette spans -0.76 .. +0.96 deg
D, R, BEARING = 9.0, 0.135, math.radians(0.1)
MIXED = 62  # the beam at +1.0 deg: its footprint (0.875 .. 1.125 deg) holds the trunk's edge
BACK = 12.0  # a surface behind the trunk, metres


def _circle_range(b: float) -> float:
    """Range of a beam centre at bearing ``b`` to the trunk (inf: misses it)."""
    u = b - BEARING
    p = D * math.sin(u)
    if abs(p) >= R:
        return math.inf
    return D * math.cos(u) - math.sqrt(R * R - p * p)


def _blend(share: float, near: float, far: float) -> float:
    """The footprint-averaging range of a beam ``share`` on ``near``, the rest on ``far`` (the
    power-weighted mean of stemmap.sim.footprint)."""
    w_n, w_f = share / near**2, (1.0 - share) / far**2
    return (w_n * near + w_f * far) / (w_n + w_f)


def _scan(beyond: str) -> tuple[np.ndarray, float]:
    """Ranges of a scan that sees the trunk with three clean returns (beams 59-61, at
    -0.5, 0, +0.5 deg; every footprint on the trunk) and, at beam 62, ``beyond``: ``"mixed"`` a
    mixed return of the trunk's edge and a surface 3 m behind that the next beam sees,
    ``"mixed_alone"`` the same return with nothing beyond it, ``"nothing"`` no return,
    ``"background"`` that surface seen cleanly by beam 62 and the beams after it. Also the
    true tangent's bearing past beam 62's footprint start, as the trunk's share of it."""
    r = np.full(N, np.inf)
    bearings = A0 + STEP * np.arange(N)
    for k in (59, 60, 61):
        r[k] = _circle_range(bearings[k])
    assert np.all(np.isfinite(r[59:62])) and not np.isfinite(_circle_range(bearings[MIXED]))
    half = math.asin(R / D)
    foot = math.radians(0.25)
    share = (BEARING + half - (bearings[MIXED] - foot / 2)) / foot
    tangent = math.sqrt(D * D - R * R)
    if beyond in ("mixed", "mixed_alone"):
        r[MIXED] = _blend(share, tangent, tangent + 3.0)
        if beyond == "mixed":
            r[MIXED + 1 : MIXED + 6] = tangent + 3.0
    elif beyond == "background":
        r[MIXED : MIXED + 6] = BACK
    return r, share


def _detect(ranges: np.ndarray, **overrides: object):
    cfg = DetectorConfig.preset("stemmap", **overrides)
    return ScanTrunkDetector(cfg).detect(LaserScan(ranges, A0, STEP))


def test_scene_is_a_mixed_return_of_the_trunk_edge():
    r, share = _scan("mixed")
    assert 0.3 < share < 0.9  # the mixed footprint holds a real part of the trunk
    assert r[MIXED] > r[61] + 0.2  # behind the edge by more than the occlusion margin
    assert r[MIXED + 1] > r[MIXED] + 0.2  # and nearer than what lies behind


@pytest.mark.parametrize("beyond", ["mixed", "mixed_alone"])
def test_three_returns_and_a_mixed_end_are_kept(beyond):
    r, _ = _scan(beyond)
    # the preset (min_points 4) makes no candidate of three returns
    assert len(_detect(r)) == 0
    obs = _detect(r, mixed_end_min_points=3)
    assert len(obs) == 1
    assert obs.n_points[0] == 3
    true = D * np.array([math.cos(BEARING), math.sin(BEARING)])
    if beyond == "mixed":
        # the surface behind is seen: the mixed return's range gives the trunk's share of its
        # footprint, which pins the tangent (features.edge_silhouette); noise-free returns, so
        # the diameter within the 3 cm of the benchmark's count (FORTLS: -0.1 .. +0.4 cm)
        assert abs(2.0 * (obs.radii[0] - R)) < 0.03
    else:
        # nothing beyond: the fit keeps its default tangent prior (half a beam past the edge
        # return, narrower than the truth; FORTLS's one such view read -3.1 cm), so only the
        # diameter's sign of error and a loose bound are asserted
        assert -0.06 < 2.0 * (obs.radii[0] - R) < 0.0
    assert np.hypot(*(obs.centers[0] - true)) < 0.03


@pytest.mark.parametrize("beyond", ["nothing", "background"])
def test_three_returns_without_a_mixed_end_are_not_kept(beyond):
    r, _ = _scan(beyond)
    assert len(_detect(r, mixed_end_min_points=3)) == 0


def test_a_nearer_neighbour_is_an_occluder_not_a_mixed_return():
    r, _ = _scan("mixed")
    r[MIXED] = r[61] - 1.0  # the beam beyond is in front: the end is occluded
    assert len(_detect(r, mixed_end_min_points=3)) == 0


def test_first_echo_scanners_have_no_mixed_returns():
    r, _ = _scan("mixed")
    cfg = DetectorConfig.preset("stemmap", mixed_end_min_points=3, beam_footprint_deg=0.5)
    assert not mixed_end_on(cfg)
    assert len(ScanTrunkDetector(cfg).detect(LaserScan(r, A0, STEP))) == 0
    assert not mixed_end_on(DetectorConfig.preset("stemmap", beam_divergence_deg=0.0))
    assert mixed_end_on(DetectorConfig.preset("stemmap", mixed_end_min_points=3))


def test_config_bounds():
    with pytest.raises(ConfigError, match="mixed_end_min_points"):
        DetectorConfig.preset("stemmap", mixed_end_min_points=2)
    with pytest.raises(ConfigError, match="mixed_end_min_points"):
        DetectorConfig.preset("stemmap", mixed_end_min_points=5)  # above min_points 4
    assert not mixed_end_on(DetectorConfig.preset("stemmap", mixed_end_min_points=4))


def test_option_only_adds_three_return_trunks_on_a_simulated_drive():
    """On the simulator's averaging scanner (clutter included) the option keeps every
    detection of the preset unchanged and adds only candidates of three returns; off, it is
    the compiled pipeline's result bit for bit."""
    rng = np.random.default_rng(11)
    st = random_stand(45, (30.0, 30.0), dbh_mean=0.3, dbh_std=0.1, dbh_min=0.08, rng=rng)
    st = add_clutter(st, n_bushes=4, n_branches=4, n_walls=1, n_fences=1, n_rocks=3, rng=rng)
    t = np.linspace(0.0, 1.0, 40)
    poses = np.column_stack((3.0 + 24.0 * t, 4.0 + 20.0 * t, 0.7 + 3.0 * t))
    model = dataclasses.replace(scanner_preset("sick_lms", range_max=30.0), range_noise=0.0)
    batch, _, _ = simulate_scans(st, poses, model, rng=3)
    assert isinstance(batch, ScanBatch)
    off = ScanTrunkDetector(DetectorConfig.preset("stemmap"))
    on = ScanTrunkDetector(DetectorConfig.preset("stemmap", mixed_end_min_points=3))
    assert off._compiled(None, None) and not on._compiled(None, None)
    a = off.detect_batch(batch)
    b = on.detect_batch(batch)
    old = b.n_points > 3
    assert np.count_nonzero(old) == len(a)
    np.testing.assert_array_equal(b.index[old], a.index)
    np.testing.assert_allclose(b.centers[old], a.centers, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b.radii[old], a.radii, rtol=1e-9, atol=1e-12)
    assert np.all(b.n_points[~old] == 3)


def test_residual_floor_reads_noise_free_few_return_trunks_closer():
    """``residual_floor``: on noise-free averaging scans the 1 cm floor leaves the radius of a
    4-6-return trunk to the tangent prior; weighted by its own residuals' median bound the fit
    reads the same views with a smaller DBH error (measured: RMSE 1.63 -> 1.22 cm on these
    views with grid 96's settings), and finds the same trunks."""
    from stemmap.sim.forest import Stand

    st = Stand(trees_xy=np.array([[0.0, 0.0]]), diameters=np.array([0.30]))
    rng = np.random.default_rng(0)
    d = rng.uniform(6.0, 14.0, 200)
    th = rng.uniform(-math.pi, math.pi, 200)
    head = th + math.pi + rng.uniform(-0.5, 0.5, 200)
    poses = np.column_stack((d * np.cos(th), d * np.sin(th), head))
    model = dataclasses.replace(scanner_preset("sick_lms", range_max=30.0), range_noise=0.0)
    batch, _, _ = simulate_scans(st, poses, model, rng=1)
    obs = {
        floor: ScanTrunkDetector(
            DetectorConfig.preset("stemmap", residual_floor=floor)
        ).detect_batch(batch)
        for floor in (0.0, 0.5)
    }
    np.testing.assert_array_equal(obs[0.5].index, obs[0.0].index)
    assert len(obs[0.0]) > 50 and obs[0.0].n_points.max() <= 8  # few returns each
    rmse = {f: float(np.sqrt(np.mean((2.0 * o.radii - 0.30) ** 2))) for f, o in obs.items()}
    assert rmse[0.5] < 0.9 * rmse[0.0]
