"""The annulus about a found stem (guided refits, thin re-measure) takes the stem's own
residual scale when the cloud's noise floor is not pooled over stems
(:func:`stemmap.cloud.slicestem._annulus_noise`; docs/algorithms/cloud.md "Single trees: the
annulus about a found stem").

treels spruce.laz randomly thinned to 20 / 10 % has a single candidate cluster whose slices
mostly fit its branch whorls, so its noise floor (their median RMS) is 71 / 124 mm; an annulus
of 3 floors about its 12 cm stem reaches 21-37 cm out, into the whorls, and its RANSAC
tolerance (half a floor) lets them win. Its DBH came out 2.1 cm off its ring."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stemmap.cloud.band import _Band
from stemmap.cloud.config import StemConfig
from stemmap.cloud.slicestem import _annulus_fit, _annulus_noise, _BandContext, _SliceFits


def _slice_in_a_whorl(seed: int) -> np.ndarray:
    """One 20 cm slice of a sparse spruce: 25 returns on the scanned 200 degrees of a 12 cm
    stem (3 mm noise) and 120 branch and needle returns 14-40 cm from its axis (the 20 %
    spruce's thin slices hold 20-40 stem inliers among 110-160 points)."""
    rng = np.random.default_rng(seed)
    a = np.radians(rng.uniform(-100, 100, 25))
    r = 0.12 + rng.normal(0, 0.003, a.shape[0])
    b = rng.uniform(0, 2 * np.pi, 120)
    d = rng.uniform(0.14, 0.40, b.shape[0])
    return np.vstack(
        (
            np.column_stack((r * np.cos(a), r * np.sin(a))),
            np.column_stack((d * np.cos(b), d * np.sin(b))),
        )
    )


def _context(xy: np.ndarray, noise_floor: float, own_floor: bool) -> _BandContext:
    n = xy.shape[0]
    band = _Band(xy=xy, h=np.full(n, 1.3), z=np.full(n, 1.3))
    return _BandContext(
        band=band,
        tree=cKDTree(xy),
        band_sl=np.zeros(n, dtype=np.int64),
        centers_h=np.array([1.3]),
        noise_floor=noise_floor,
        slice_cloud=False,
        rms_max=3 * noise_floor,
        own_floor=own_floor,
    )


@pytest.mark.parametrize("seed", range(5))
def test_the_stems_own_scale_refits_the_stem_among_whorls(seed: int) -> None:
    """Predicted circle: the stem. With a floor of 70 mm (the whorl fits') the annulus
    refit finds no circle that agrees with it (RANSAC at 35 mm in a 21 cm annulus locks onto
    the branches); with the stem's own 5 mm it finds the stem: radius within 5 mm (a
    25-return half arc at 3 mm noise: ~1 mm; 5 mm leaves room for the branch returns that
    touch the stem) and centre within 1 cm."""
    xy = _slice_in_a_whorl(seed)
    ctx = _context(xy, 0.07, True)
    cfg = StemConfig()
    centre = np.zeros(2)
    assert _annulus_fit(ctx, 0, centre, 0.12, 0.018, 0.0, cfg) is None
    fit = _annulus_fit(ctx, 0, centre, 0.12, 0.018, 0.0, cfg, 0.005)
    assert fit is not None
    assert abs(fit.radius - 0.12) < 0.005
    assert np.hypot(*fit.center) < 0.01


def _fits(rms: list[float]) -> _SliceFits:
    ns = len(rms)
    return _SliceFits(
        passed=np.ones((1, ns), dtype=bool),
        fitted=np.ones((1, ns), dtype=bool),
        centers=np.zeros((1, ns, 2)),
        radii=np.full((1, ns), 0.12),
        rms=np.array([rms]),
        arcs=np.full((1, ns), 300.0),
        n_in=np.full((1, ns), 30, dtype=np.int64),
        weights=np.ones((1, ns)),
        cov=np.zeros((1, ns, 3, 3)),
        present=np.array([ns]),
    )


def test_the_floor_is_kept_where_it_is_the_stems_noise() -> None:
    """The stem's own scale (mean RMS of its agreeing slices, 5 mm here) replaces the floor
    only in a single-candidate cloud, with at least two agreeing slices, and when the floor
    is more than ``residual_factor`` (3) times it: 70 mm (whorls) yes; 12 mm (rough bark, as
    archi Tree_1's 20 mm against 10 mm) no; a pooled plot floor or one slice, no."""
    fits = _fits([0.004, 0.006, 0.09])
    kept = np.array([True, True, False])
    xy = _slice_in_a_whorl(0)
    cfg = StemConfig()
    assert _annulus_noise(fits, 0, kept, _context(xy, 0.07, True), cfg) == pytest.approx(0.005)
    assert _annulus_noise(fits, 0, kept, _context(xy, 0.012, True), cfg) is None
    assert _annulus_noise(fits, 0, kept, _context(xy, 0.07, False), cfg) is None
    one = np.array([True, False, False])
    assert _annulus_noise(fits, 0, one, _context(xy, 0.07, True), cfg) is None
