"""Short arcs in the radius consensus and guided refits on a root flare
(``StemConfig.consensus_radius_se``, ``StemConfig.guided_taper``; docs/algorithms/cloud.md
"Short arcs in the radius consensus").

The slice fits below are treels pine_plot's at 20 % (seed 1, the 23.8 cm edge stem 0, seen
from one side) and at 10 % (seed 3, stem 13 with the refit of its 0.8-1.2 m slice on the
root flare), as ``benchmarks/cloud_lost_stems.py`` prints them.
"""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.cloud.config import StemConfig
from stemmap.cloud.slicefit import _fit_segments, _segment_covariances
from stemmap.cloud.slicestem import (
    _AnnulusFit,
    _consistent_slices,
    _radius_se,
    _SliceFits,
    _taper_checked,
    _weighted_median,
)

HEIGHTS = np.array([1.0, 1.4, 1.8])


def _fits(
    radii: list[float], rms: list[float], n_in: list[int], arcs: list[float], se: list[float]
) -> _SliceFits:
    """One cluster's passing slice fits centred on (5, 5) m with radius standard errors
    ``se`` (the (r, r) covariance entries)."""
    ns = len(radii)
    q, n = np.array([rms]), np.array([n_in], dtype=np.int64)
    cov = np.zeros((1, ns, 3, 3))
    cov[0, :, 0, 0] = cov[0, :, 1, 1] = 1e-6
    cov[0, :, 2, 2] = np.square(se)
    return _SliceFits(
        passed=np.ones((1, ns), dtype=bool),
        fitted=np.ones((1, ns), dtype=bool),
        centers=np.tile([5.0, 5.0], (1, ns, 1)).astype(float),
        radii=np.array([radii]),
        rms=q,
        arcs=np.array([arcs], dtype=float),
        n_in=n,
        weights=n / np.maximum(q, 1e-4) ** 2,
        cov=cov,
        present=np.array([ns]),
    )


def _arc_se(arc_deg: float, n: int, noise: float, seed: int) -> float:
    """The fit's radius standard error (covariance) for ``n`` points on an ``arc_deg`` arc of
    an 11 cm circle with Gaussian radial noise ``noise``."""
    rng = np.random.default_rng(seed)
    t = np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, n))
    rr = 0.11 + rng.normal(0.0, noise, n)
    pts = np.column_stack((5 + rr * np.cos(t), 5 + rr * np.sin(t)))
    ids = np.zeros(n, dtype=np.int64)
    c, r, rms, ok, _ = _fit_segments(pts, ids, 1, "ours", ransac_tol=0.005)
    assert ok[0]
    return float(np.sqrt(_segment_covariances(pts, ids, 1, c, r, rms)[0, 2, 2]))


def test_a_one_sided_arc_fixes_its_radius_to_centimetres() -> None:
    """The covariance's radius standard error grows steeply as the arc shortens: 9-10 points
    with 5 mm noise give several mm on 145 deg and about a centimetre or more on 91 deg (the
    short-arc approximation's (180 / arc)^2 growth), medians over 20 draws."""
    se = {
        a: float(np.median([_arc_se(a, 10, 0.005, s) for s in range(20)]))
        for a in (91.0, 145.0, 300.0)
    }
    assert se[300.0] < 0.003
    assert se[145.0] < se[91.0] / 1.8
    assert se[91.0] > 0.008


def test_weighted_median() -> None:
    x = np.array([3.0, 1.0, 2.0])
    assert _weighted_median(x, np.ones(3)) == 2.0
    assert _weighted_median(np.array([1.0, 3.0]), np.ones(2)) == 2.0
    assert _weighted_median(x, np.array([1.0, 10.0, 1.0])) == 1.0


#: pine_plot 20 %, seed 1, stem 0 (partial ring 21.97 cm) at the tighter tolerance: a 91 deg
#: arc of 9 points (r 19.68 cm, se 18.8 mm) and a 145 deg arc of 10 (r 11.06 cm, se 5.2 mm)
ONE_SIDED = _fits(
    [0.1248, 0.1968, 0.1106],
    [0.0038, 0.0057, 0.0043],
    [7, 9, 10],
    [101, 91, 145],
    [0.0085, 0.0188, 0.0052],
)


def test_the_better_determined_arc_sets_the_consensus() -> None:
    fits = _SliceFits(*(np.array(getattr(ONE_SIDED, f)) for f in ONE_SIDED.__dataclass_fields__))
    fits.passed[0, 0] = False  # 7 inliers: failed the per-slice test
    off = _consistent_slices(fits, 0, HEIGHTS)
    on = _consistent_slices(fits, 0, HEIGHTS, 0.0, 0.0)
    # default: the two "agree" within 5 x the short-arc sigma and the median is between
    assert off.radius == pytest.approx((0.1968 + 0.1106) / 2)
    # by the radius's own inverse variance: the 145 deg arc (r 11.06 cm; ring 10.99)
    assert on.radius == pytest.approx(0.1106)
    assert not on.kept[1]


def test_the_se_floor_keeps_a_smooth_clutter_circle_from_winning() -> None:
    """pine_plot 20 %, seed 0, stem 4: a 10.1 cm clutter circle (8 inliers at 1.7 mm, below
    the 7.0 mm pooled floor) has the smallest covariance; floored, the stem's slices win."""
    fits = _fits(
        [0.0387, 0.0415, 0.1014],
        [0.0052, 0.0041, 0.0017],
        [12, 14, 8],
        [310, 282, 144],
        [0.0012, 0.0010, 0.0006],
    )
    assert _radius_se(fits, 0, 0.007)[2] == pytest.approx(0.0006 * 7.0 / 1.7)
    bare = _consistent_slices(fits, 0, HEIGHTS, 0.0, 0.0)
    floored = _consistent_slices(fits, 0, HEIGHTS, 0.0, 0.007)
    assert list(bare.kept) == [False, False, True]
    assert list(floored.kept) == [True, True, False]


def test_the_option_off_is_the_default_consensus() -> None:
    """Without ``se_floor`` the consensus is the one by fit weights, whatever the
    covariances say."""
    fits = _fits([0.10, 0.11, 0.30], [0.004, 0.004, 0.02], [20, 20, 30], [300, 300, 250], [1, 1, 1])
    a = _consistent_slices(fits, 0, HEIGHTS)
    assert list(a.kept) == [True, True, False]
    assert a.radius == pytest.approx(0.105)


def _refit(r: float) -> _AnnulusFit:
    return _AnnulusFit(np.array([5.0, 5.0]), r, 0.003, 200.0, 11, np.eye(3) * 1e-6)


def test_a_refit_on_the_flare_is_left_out_not_the_stem() -> None:
    """pine_plot 10 %, seed 3, stem 13: slices at 1.4 / 1.8 m agree on 8.02 / 9.32 cm; the
    refit of the 0.8-1.2 m slice fits 14.22 cm (root flare and clutter). With it the
    Theil-Sen radius line tapers 6.1 cm/m (> 5): it is left out. A refit at 8.5 cm stays."""
    cfg = StemConfig(guided_taper=True)
    radii = np.array([np.nan, 0.0802, 0.0932])
    m = np.array([False, True, True])
    assert _taper_checked({0: _refit(0.1422)}, HEIGHTS, m, radii, 1.6, cfg) == {}
    kept = _taper_checked({0: _refit(0.085)}, HEIGHTS, m, radii, 1.6, cfg)
    assert list(kept) == [0]


def test_the_kept_refits_keep_the_stem_within_its_taper() -> None:
    """Six thin slices, two agreeing at 1.3 / 1.5 m (8.0 cm); refits at 1.1 m (12 cm, flare),
    1.7 m (8.3 cm) and 0.9 m (13 cm). From the nearest outwards: the 1.1 m refit would give
    the three-radius line 10 cm/m and is left out, the 1.7 m one is kept; with four others the
    robust (Theil-Sen) line is no longer tilted by the 0.9 m one (2.9 cm/m), so it is kept,
    as :func:`_stem_at` would accept it. Whatever is kept passes the taper test."""
    from stemmap.cloud.slicefit import _theil_sen

    h = np.array([0.9, 1.1, 1.3, 1.5, 1.7, 1.9])
    radii = np.array([np.nan, np.nan, 0.080, 0.080, np.nan, np.nan])
    m = np.array([False, False, True, True, False, False])
    found = {0: _refit(0.13), 1: _refit(0.12), 4: _refit(0.083)}
    cfg = StemConfig(guided_taper=True)
    kept = _taper_checked(found, h, m, radii, 1.4, cfg)
    assert sorted(kept) == [0, 4]
    ks = sorted(kept)
    hh = np.concatenate((h[m], h[ks]))
    rr = np.concatenate((radii[m], [kept[k].radius for k in ks]))
    assert abs(_theil_sen(hh, rr)[1]) <= cfg.max_taper
