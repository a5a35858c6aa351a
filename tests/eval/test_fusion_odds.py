"""Odds that a re-weighted fusion of two independent errors beats both (eval/fusion_odds.py):
the derivation behind "fused better than both sources on every loop is not a reachable
target" (docs/algorithms/visual-odometry.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.eval.fusion_odds import p_fused_beats_both, p_fused_beats_both_1d

N = 200_000
SE = 0.5 / math.sqrt(N)  # Monte Carlo standard error bound of a probability


@pytest.mark.parametrize("r", [1.0, 1.7, 3.0, 10.0])
def test_one_dimensional_closed_form_matches_monte_carlo(r: float) -> None:
    mc = p_fused_beats_both(r, dim=1, n_samples=N, rng=int(10 * r))
    assert mc == pytest.approx(p_fused_beats_both_1d(r), abs=4 * SE)


def test_closed_form_values_and_limit() -> None:
    assert p_fused_beats_both_1d(1.0) == pytest.approx(0.2952, abs=1e-4)
    assert p_fused_beats_both_1d(3.0) == pytest.approx(0.3654, abs=1e-4)
    assert p_fused_beats_both_1d(1e4) == pytest.approx(0.5, abs=1e-4)
    # which source is the worse one does not matter
    assert p_fused_beats_both_1d(0.5) == pytest.approx(p_fused_beats_both_1d(2.0), abs=1e-12)
    with pytest.raises(ConfigError, match="sigma_ratio"):
        p_fused_beats_both_1d(0.0)


@pytest.mark.parametrize("w", [0.05, 0.2, 0.5, 0.8, 0.95])
def test_in_one_dimension_no_weight_beats_a_coin_toss(w: float) -> None:
    """Opposite signs are necessary in 1D, so P < 1/2 for every fixed weight."""
    for r in (0.5, 1.0, 3.0):
        assert p_fused_beats_both(r, dim=1, weight=w, n_samples=50_000, rng=1) < 0.5


@pytest.mark.parametrize("r", [1.0, 2.0, 2.5, 4.0])
def test_two_dimensional_loop_error_is_about_a_coin_toss(r: float) -> None:
    """A loop's start-end error is a 2-vector: 0.45-0.51 for r = 1-4 (docs table)."""
    p = p_fused_beats_both(r, dim=2, n_samples=N, rng=3)
    assert 0.44 < p < 0.52
    # every one of 12 independent loops: below 4e-4
    assert p**12 < 4e-4


def test_fused_mean_square_error_is_below_the_better_source() -> None:
    """The other half of the argument: on the mean the fusion wins, MSE ratio r^2 / (1 + r^2)
    of the better source's (the target "better than either source" is a statement about means)."""
    rng = np.random.default_rng(5)
    r = 2.5
    a = r * rng.standard_normal((N, 2))
    b = rng.standard_normal((N, 2))
    w = 1 / (1 + r * r)
    f = w * a + (1 - w) * b
    ratio = np.mean(np.sum(f**2, axis=1)) / np.mean(np.sum(b**2, axis=1))
    assert ratio == pytest.approx(r * r / (1 + r * r), abs=0.01)


def test_bad_arguments() -> None:
    with pytest.raises(ConfigError, match="sigma_ratio"):
        p_fused_beats_both(-1.0)
    with pytest.raises(ConfigError, match="dim"):
        p_fused_beats_both(1.0, dim=0)
    with pytest.raises(ConfigError, match="weight"):
        p_fused_beats_both(1.0, weight=1.5)


def test_weight_limits_are_one_source_and_never_beat_both() -> None:
    """``w = 0`` and ``w = 1`` (both allowed: ``weight`` in [0, 1]) make the fusion equal to one
    source, which is never *strictly* smaller than itself: P = 0 exactly."""
    for w in (0.0, 1.0):
        for dim in (1, 2):
            assert p_fused_beats_both(1.5, dim=dim, weight=w, n_samples=5_000, rng=2) == 0.0


def test_default_is_a_two_dimensional_error_and_a_seed_repeats() -> None:
    n = 20_000
    p = p_fused_beats_both(2.0, n_samples=n, rng=7)
    assert p == p_fused_beats_both(2.0, dim=2, n_samples=n, rng=7)  # dim defaults to 2
    assert p != p_fused_beats_both(2.0, dim=3, n_samples=n, rng=7)
    assert p_fused_beats_both(2.0, n_samples=n) == p_fused_beats_both(2.0, n_samples=n)
    g1, g2 = np.random.default_rng(4), np.random.default_rng(4)  # a Generator is used as given
    assert p_fused_beats_both(2.0, n_samples=n, rng=g1) == p_fused_beats_both(
        2.0, n_samples=n, rng=g2
    )


def test_argument_limits_and_messages() -> None:
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ConfigError, match=r"^sigma_ratio must be > 0, got "):
            p_fused_beats_both(bad)
        with pytest.raises(ConfigError, match=r"^sigma_ratio must be > 0, got "):
            p_fused_beats_both_1d(bad)
    with pytest.raises(ConfigError, match=r"^dim must be >= 1, got 0$"):
        p_fused_beats_both(1.0, dim=0)
    for w in (-0.01, 1.01, math.nan):
        with pytest.raises(ConfigError, match=r"^weight must be in \[0, 1\], got "):
            p_fused_beats_both(1.0, weight=w)
    assert 0.0 < p_fused_beats_both(1.0, dim=1, n_samples=2_000) < 0.5  # dim = 1 is allowed
