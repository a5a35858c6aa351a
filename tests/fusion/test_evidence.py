"""Dempster-Shafer evidence and the Xue et al. (2018) BPAs: reproduce Tables 1-3 exactly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.fusion.bpa import (
    PRESETS,
    BpaParams,
    laser_bpa,
    no_support_mass,
    vision_bpa,
)
from stemmap.fusion.evidence import Mass, combine_dempster, decide_xue2018

# Paper inputs (Xue 2018 §3.2.2-§3.2.4): matching levels of regions 1, 4, 5, 8, 9 (Fig. 10f),
# laser widths of A, B, C, D (Fig. 11); A, B, C, D correspond to regions 9, 8, 4, 1, and region 5
# has no laser data.
ALPHA = np.array([0.64, 0.36, 0.66, 1.0, 0.52])
WIDTHS = {"A": 0.1836, "B": 0.1696, "C": 0.1735, "D": 0.1806}
LASER_FOR_REGION = ["D", "C", None, "B", "A"]

TABLE1 = np.array(
    [
        [0.576, 0.324, 0.594, 0.9, 0.468],
        [0.324, 0.576, 0.306, 0.1, 0.432],
        [0.1, 0.1, 0.1, 0.0, 0.1],
    ]
)
TABLE3 = np.array(
    [
        [0.935, 0.850, 0.0, 0.988, 0.906],
        [0.065, 0.150, 1.0, 0.012, 0.094],
        [0.0, 0.0, 0.0, 0.0, 0.0],
    ]
)


def _mass_strategy() -> st.SearchStrategy[tuple[float, float, float]]:
    return st.tuples(st.floats(0, 1, allow_nan=False), st.floats(0, 1, allow_nan=False)).map(
        lambda ab: (ab[0] * (1 - ab[1]), (1 - ab[0]) * (1 - ab[1]), ab[1])
    )


def test_table1_vision_bpa_exact() -> None:
    m = vision_bpa(ALPHA, "xue2018")
    # The paper prints 3 decimals; our values must round to exactly those.
    np.testing.assert_array_equal(np.round(m.as_array().T, 3), TABLE1)


def test_table2_laser_bpa_exact() -> None:
    m = laser_bpa(np.array(list(WIDTHS.values())), "xue2018")
    np.testing.assert_allclose(m.t, 0.9, atol=0)
    np.testing.assert_allclose(m.nt, 0.1, atol=1e-15)
    np.testing.assert_array_equal(m.theta, 0.0)


def test_table3_combination_and_decision_exact() -> None:
    mv = vision_bpa(ALPHA, "xue2018")
    widths = np.array([WIDTHS[k] if k else np.nan for k in LASER_FOR_REGION])
    ml = laser_bpa(widths, "xue2018")
    unsupported = np.array([k is None for k in LASER_FOR_REGION])
    ns = no_support_mass(len(ALPHA))
    ml = Mass(
        np.where(unsupported, ns.t, ml.t),
        np.where(unsupported, ns.nt, ml.nt),
        np.where(unsupported, ns.theta, ml.theta),
    )
    comb = combine_dempster(ml, mv)
    assert comb
    np.testing.assert_array_equal(np.round(comb.mass.as_array().T, 3), TABLE3)
    # Decision (eq. 17, eps1 = eps2 = 0.1): 1, 4, 8, 9 are trunks, 5 is not.
    np.testing.assert_array_equal(decide_xue2018(comb.mass), [True, True, False, True, True])


def test_laser_bpa_tails_continuous_and_printed() -> None:
    p = BpaParams()
    lo = p.w_min - p.dw
    eps = 1e-9
    inside = laser_bpa(lo, p).t
    below = laser_bpa(lo - eps, p).t
    assert below == pytest.approx(inside, abs=1e-6)  # continuous variant has no jump
    printed = laser_bpa(lo - eps, "xue2018_printed").t
    assert printed == pytest.approx(0.9 * np.exp(-2 * p.dw * 1000 / 10), rel=1e-6)
    # Upper tail: 10 mm above the band drops by a factor e.
    assert laser_bpa(p.w_max + p.dw + 0.010, p).t == pytest.approx(0.9 / np.e, rel=1e-9)
    # Monotone non-increasing away from the band.
    w = np.linspace(0.0, 0.5, 501)
    t = laser_bpa(w, p).t
    assert np.all(np.diff(t[w <= p.w_min]) >= -1e-15)
    assert np.all(np.diff(t[w >= p.w_max]) <= 1e-15)
    assert laser_bpa(np.nan, p).t == 0.0


@settings(max_examples=200, deadline=None)
@given(_mass_strategy(), _mass_strategy())
def test_dempster_properties(a: tuple[float, float, float], b: tuple[float, float, float]) -> None:
    m1, m2 = Mass(*a), Mass(*b)
    c12, c21 = combine_dempster(m1, m2), combine_dempster(m2, m1)
    np.testing.assert_allclose(c12.conflict, c21.conflict, atol=1e-12)
    if c12:
        np.testing.assert_allclose(c12.mass.as_array(), c21.mass.as_array(), atol=1e-9)
        assert float(c12.mass.as_array().sum()) == pytest.approx(1.0, abs=1e-12)
    # The vacuous mass is the neutral element.
    cv = combine_dempster(m1, Mass.vacuous())
    assert cv
    np.testing.assert_allclose(cv.mass.as_array(), m1.as_array(), atol=1e-9)


def test_total_conflict_is_falsy_with_reason() -> None:
    c = combine_dempster(
        Mass([1.0, 0.5], [0.0, 0.5], [0.0, 0.0]), Mass([0.0, 0.5], [1.0, 0.5], [0.0, 0.0])
    )
    assert not c
    assert c.ok.tolist() == [False, True]
    assert "total conflict" in c.reason
    assert c.mass.theta[0] == 1.0  # undefined -> vacuous, never zeros


def test_bad_inputs() -> None:
    with pytest.raises(InputError, match="sum to 1"):
        Mass(0.5, 0.6, 0.0)
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        Mass(1.2, -0.2, 0.0)
    with pytest.raises(InputError, match="one shape"):
        Mass([0.5], [0.5, 0.5], [0.0])
    with pytest.raises(InputError, match="alpha"):
        vision_bpa([1.5])
    with pytest.raises(ConfigError, match="preset"):
        laser_bpa(0.1, "nope")
    with pytest.raises(ConfigError, match="w_min"):
        BpaParams(w_min=0.3, w_max=0.2)
    with pytest.raises(ConfigError, match="k2"):
        vision_bpa([0.8], BpaParams(k2=1.0))
    with pytest.raises(ConfigError):
        decide_xue2018(Mass(1.0, 0.0, 0.0), eps2=0.0)
    assert "xue2018" in PRESETS


def test_table2_band_is_the_papers() -> None:
    """Table 2 alone holds for any band containing 0.17-0.18 m: pin the band (issue 13).

    Xue 2018 eq. 13 with W = [130, 185] mm and dw = 20 mm: k1 = 0.9 on [110, 205] mm, falling
    by e per 10 mm outside. A preset with another band fails here even if Table 2 passes.
    """
    p = PRESETS["xue2018"]
    assert (p.w_min, p.w_max, p.dw) == (0.13, 0.185, 0.02)
    w = np.array([0.1095, 0.1105, 0.2045, 0.2055, 0.215, 0.100])
    t = laser_bpa(w, "xue2018").t
    np.testing.assert_allclose(t[1:3], 0.9, atol=0)
    np.testing.assert_allclose(t[0], 0.9 * np.exp(-0.05), rtol=1e-9)  # 0.5 mm below 110 mm
    np.testing.assert_allclose(t[3], 0.9 * np.exp(-0.05), rtol=1e-9)  # 0.5 mm above 205 mm
    np.testing.assert_allclose(t[4], 0.9 / np.e, rtol=1e-9)
    np.testing.assert_allclose(t[5], 0.9 / np.e, rtol=1e-9)
    # the paper's four laser widths (169.6-183.6 mm) sit inside the band
    widths = np.array(list(WIDTHS.values()))
    assert np.all((widths > p.w_min) & (widths < p.w_max))
