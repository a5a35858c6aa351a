"""``StemConfig.ladder_found_rms``: the single-tree ladder's fair-support test uses the RMS
of the slice fits the kept stem was found with, not its thin re-measure's
(docs/algorithms/cloud.md "aRchi Tree_1 at 20 %: where its DBH moves")."""

from __future__ import annotations

import math

import pytest

from stemmap.cloud._ladder import _single_tree_stem, _stem_weight
from stemmap.cloud.config import StemConfig

TOL0 = 0.0585  # aRchi Tree_1 at 20 %, seed 0: the ladder's first tolerance (m)


def _row(dbh: float, n: int, rms: float) -> tuple[float, ...]:
    # (x, y, dbh, n_points, quality, arc, rms, n_slices, taper, dbh_std, cxx, cxy, cyy, h)
    return (0.0, 0.0, dbh, n, 1.0, 230.0, rms, 5, 0.0, 0.01, 0.0, 0.0, 0.0, 1.3)


# the first-round stem as measured again on thin slices: 52 cm, annulus fits at RMS 7.1 mm;
# the band's slice fits that found it had RMS 18.3 mm
KEPT = (_row(0.52, 100, 0.0071), "breast height")
FOUND_RMS = 0.0183


def _ladder(at_tol: float, stem: tuple[tuple[float, ...], str]):  # type: ignore[no-untyped-def]
    """A ladder whose only stem is ``stem``, on the thin slices at tolerance ``at_tol``."""

    def refit(thin: bool, first: float, tol: float):  # type: ignore[no-untyped-def]
        return stem if thin and math.isclose(tol, at_tol) else None

    return refit


def test_the_option_is_on_by_default() -> None:
    # a fix of what the fair-support test means (docs/algorithms/cloud.md "ladder_found_rms
    # is the default"), not a tuned threshold
    assert StemConfig().ladder_found_rms is True


def test_a_carved_stem_below_the_found_rms_does_not_win() -> None:
    # a 40 cm stem carved out of the rough bark at a 14.6 mm tolerance (RMS 6.3 mm), with
    # more support than the kept stem's re-measure: it is not half the diameter, and it was
    # fitted at a tolerance below the RMS the kept stem was found with -- no fair comparison
    carved = (_row(0.40, 125, 0.0063), "breast height")
    assert _stem_weight(carved[0]) > _stem_weight(KEPT[0])
    refit = _ladder(TOL0 / 4, carved)
    # as shipped: the re-measure's 7.1 mm RMS is below 14.6 mm, so the carved stem wins
    assert _single_tree_stem(KEPT, refit, TOL0, True) is carved
    assert _single_tree_stem(KEPT, refit, TOL0, True, found_rms=FOUND_RMS) is KEPT


@pytest.mark.parametrize("factor", [1.0, 0.5])
def test_a_fair_comparison_is_still_made(factor: float) -> None:
    # a smaller stem fitted at a tolerance not below the found RMS (58.5 / 29.2 mm) with
    # more support still replaces the kept one
    smaller = (_row(0.48, 400, 0.009), "breast height")
    got = _single_tree_stem(KEPT, _ladder(factor * TOL0, smaller), TOL0, True, FOUND_RMS)
    assert got is smaller


def test_half_the_diameter_wins_on_support_alone() -> None:
    # the spruce rule is untouched: a stem under half the kept diameter wins on support
    # whatever tolerance gave it (clutter circles against the bark)
    small = (_row(0.24, 60, 0.004), "breast height")
    got = _single_tree_stem(KEPT, _ladder(TOL0 / 8, small), TOL0, True, FOUND_RMS)
    assert got is small


def test_without_a_first_round_stem_the_ladder_stem_is_its_own_reference() -> None:
    # found_rms only concerns a first-round stem; a ladder-found incumbent keeps its RMS
    stem = (_row(0.50, 100, 0.012), "breast height")
    got = _single_tree_stem(None, _ladder(TOL0 / 2, stem), TOL0, True, FOUND_RMS)
    assert got is stem
