"""The compiled Theil-Sen line of the slice centres and radii equals the numpy definition bit
for bit (the stems' positions and diameters must not move when it is rewritten)."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.cloud.slicefit import _theil_sen


def _numpy_theil_sen(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The definition in numpy: every pair i < j, slopes where |dx| > 1e-9, np.median."""
    i, j = np.triu_indices(x.size, 1)
    dx = x[j] - x[i]
    ok = np.abs(dx) > 1e-9
    b = float(np.median((y[j] - y[i])[ok] / dx[ok])) if ok.any() else 0.0
    return float(np.median(y - b * x)), b


def _same(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return all(
        (np.isnan(u) and np.isnan(v)) or np.float64(u).tobytes() == np.float64(v).tobytes()
        for u, v in zip(a, b, strict=True)
    )


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7, 12, 25])
def test_theil_sen_equals_the_numpy_definition(n: int) -> None:
    rng = np.random.default_rng(n)
    for trial in range(200):
        x = np.sort(rng.uniform(-1.0, 1.5, n))
        if trial % 4 == 1:  # repeated heights: pairs without a slope
            x = np.round(x, 1)
        y = 0.2 + 0.03 * x + rng.normal(0, 0.01, n)
        if trial % 4 == 2:  # outliers and exact ties
            y[rng.integers(0, n)] += 0.5
            y[: n // 2] = y[0]
        if trial % 4 == 3:
            x = x[rng.permutation(n)]  # any order
        got, ref = _theil_sen(x, y), _numpy_theil_sen(x, y)
        assert _same(got, ref), (trial, got, ref)


def test_theil_sen_degenerate_inputs() -> None:
    x = np.array([0.5, 0.5, 0.5])
    y = np.array([0.1, 0.3, 0.2])
    assert _theil_sen(x, y) == (0.2, 0.0)  # no pair with a slope: b = 0, a = median of y
    assert _same(_theil_sen(x, y), _numpy_theil_sen(x, y))
    y_nan = np.array([0.1, np.nan, 0.2])
    xs = np.array([0.0, 1.0, 2.0])
    a, b = _theil_sen(xs, y_nan)
    assert np.isnan(a) and np.isnan(b)  # NaN propagates, as np.median
    assert _same((a, b), _numpy_theil_sen(xs, y_nan))
    # an exact line
    a, b = _theil_sen(xs, 1.0 + 2.0 * xs)
    assert (a, b) == (1.0, 2.0)
    # integer or strided input is taken as float64
    assert _theil_sen(np.arange(5), np.arange(5) * 3)[1] == 3.0
    big = np.column_stack((xs, 2.0 * xs))
    assert _theil_sen(big[:, 0], big[:, 1]) == (0.0, 2.0)
