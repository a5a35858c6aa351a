"""Inliers of a thin-slice annulus refit in a plot's thickened band
(``StemConfig.thin_refit_points``, :func:`stemmap.cloud.slicestem.thin_slice_points`;
docs/algorithms/cloud.md "Sparse plots: thin-slice counts from the density")."""

from __future__ import annotations

from stemmap.cloud.band import _adapt_slices
from stemmap.cloud.config import StemConfig
from stemmap.cloud.slicestem import MIN_ANNULUS_POINTS, thin_slice_points


def test_the_count_follows_the_thickness_ratio() -> None:
    # the default band, not thickened: the dense cloud's count
    assert thin_slice_points(8, 0.2, 0.2) == 8
    # 4 slices of 0.3 m: a thin slice holds 2/3 of a thick one's returns
    assert thin_slice_points(8, 0.2, 0.3) == 6
    # 3 slices of 0.4 m: half, but never below 5 (3 circle parameters + 2)
    assert thin_slice_points(8, 0.2, 0.4) == MIN_ANNULUS_POINTS == 5
    assert thin_slice_points(8, 0.2, 1.0) == 5


def test_the_thick_slices_of_the_measured_spacing_set_it() -> None:
    """The ratio is the band's own: _adapt_slices thickens to 4 spacings, so the count is
    what the measured density gives (60 mm: 5 slices of 0.24 m, 7 points; 93 mm: 3 of 0.4 m, 5)."""
    cfg = StemConfig()
    for spacing, want in ((0.04, 8), (0.06, 7), (0.075, 6), (0.093, 5), (0.128, 5)):
        thick = _adapt_slices(cfg, spacing).slice_thickness
        assert thin_slice_points(8, cfg.slice_thickness, thick) == want, spacing


def test_never_more_than_the_dense_count() -> None:
    assert thin_slice_points(4, 0.2, 0.4) == 4
