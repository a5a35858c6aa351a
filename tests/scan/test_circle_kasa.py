import numpy as np
import pytest

from stemmap import ConfigError, InputError
from stemmap.scan.circle import fit_circle, fit_circle_kasa


def test_kasa_exact_on_full_circle_far_from_origin():
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    p = np.column_stack((1e5 + 0.3 * np.cos(t), -2e5 + 0.3 * np.sin(t)))
    fit = fit_circle_kasa(p)
    assert fit
    np.testing.assert_allclose(fit.center, [1e5, -2e5], atol=1e-6)
    assert fit.radius == pytest.approx(0.3, abs=1e-6)


def test_kasa_failures_are_falsy_with_reason():
    assert "at least 3" in fit_circle_kasa(np.zeros((2, 2))).reason
    line = np.column_stack((np.arange(5.0), np.arange(5.0)))
    fit = fit_circle_kasa(line)
    assert not fit and "collinear" in fit.reason


def test_bad_input_and_unknown_method():
    with pytest.raises(InputError, match=r"\(N, 2\)"):
        fit_circle_kasa(np.zeros(6))
    with pytest.raises(ConfigError, match="unknown circle fit"):
        fit_circle(np.zeros((3, 2)), method="nope")
