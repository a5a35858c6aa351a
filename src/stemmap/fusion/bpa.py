"""Basic probability assignments (BPAs) of laser and vision regions of interest.

Laser RoIs get their evidence from the measured trunk width (Xue et al. 2018, eq. 13; the
width itself, eq. 12, is :func:`stemmap.scan.circle.chord_width`); vision
RoIs from the stripping segmentation's matching level alpha (eq. 14-15, eq. 18). Regions seen by
one sensor only get the paper's "no support" mass from the other (§3.2.4).

References
----------
Xue J. et al. (2018). Trunk detection based on laser radar and vision data fusion. Int J Agric &
Biol Eng 11(6): 20-26.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError, InputError
from stemmap.fusion.evidence import Mass

__all__ = [
    "PRESETS",
    "BpaParams",
    "laser_bpa",
    "laser_bpa_ours",
    "no_support_mass",
    "vision_bpa",
]


@dataclass(frozen=True)
class BpaParams:
    """Parameters of the laser and vision BPAs.

    Parameters
    ----------
    w_min, w_max : float, metres
        Expected trunk width range W = [w_min, w_max] (eq. 13).
    dw : float, metres
        Width measurement error Delta w (eq. 13).
    k1, k2 : float in (0, 1]
        Maximum belief of laser (eq. 13) and vision (eq. 14) evidence.
    k3 : float > 0
        Gain of the matching level alpha = min(1, k3 A_B / A_BB) (eq. 18).
    decay_mm : float, millimetres
        e-folding width of eq. 13's exponential tails (the paper divides millimetres by 10).
    variant : "continuous" or "printed"
        Eq. 13's lower tail as printed, k1 exp((w - w_min - dw)/10), jumps at the boundary
        w = w_min - dw (from k1 to k1 exp(-2 dw / 10)). "continuous" (default) uses
        k1 exp((w - (w_min - dw))/10), which equals k1 at the boundary -- the evident intent.
        Widths inside the band (all of the paper's Table 2) get k1 either way.
    """

    w_min: float = 0.13
    w_max: float = 0.185
    dw: float = 0.02
    k1: float = 0.9
    k2: float = 0.9
    k3: float = 2.0
    decay_mm: float = 10.0
    variant: Literal["continuous", "printed"] = "continuous"

    def __post_init__(self) -> None:
        if not (0.0 < self.w_min <= self.w_max):
            raise ConfigError(
                f"BPA width band must satisfy 0 < w_min <= w_max, "
                f"got [{self.w_min}, {self.w_max}] m."
            )
        if self.dw < 0:
            raise ConfigError(f"BPA dw (width error) must be >= 0 m, got {self.dw}.")
        for name in ("k1", "k2"):
            v = getattr(self, name)
            if not 0.0 < v <= 1.0:
                raise ConfigError(f"BPA {name} must be in (0, 1], got {v}.")
        if not self.k3 > 0:
            raise ConfigError(f"BPA k3 must be > 0, got {self.k3}.")
        if not self.decay_mm > 0:
            raise ConfigError(f"BPA decay_mm must be > 0, got {self.decay_mm}.")
        if self.variant not in ("continuous", "printed"):
            raise ConfigError(
                f"BPA variant must be 'continuous' or 'printed', got {self.variant!r}."
            )


#: Published parameter sets. ``xue2018``: k1 = k2 = 0.9 (§3.2.4), k3 = 2 (§3.2.2); the pear
#: trunks' widths were "mainly 130-185 mm" (§3.2.3); Delta w is not printed -- 20 mm is our
#: choice (the paper's width error was 6-16.7 % of ~160 mm, i.e. 10-27 mm).
PRESETS: dict[str, BpaParams] = {
    "xue2018": BpaParams(),
    "xue2018_printed": BpaParams(variant="printed"),
    # Forest stems (our simulated stands: DBH 0.08-0.6 m).
    "forest": BpaParams(w_min=0.08, w_max=0.6, dw=0.03),
}


def _params(params: BpaParams | str | None) -> BpaParams:
    if params is None:
        return PRESETS["xue2018"]
    if isinstance(params, str):
        try:
            return PRESETS[params]
        except KeyError:
            raise ConfigError(
                f"unknown BPA preset {params!r}; choose one of {sorted(PRESETS)}."
            ) from None
    return params


def laser_bpa(widths: ArrayLike, params: BpaParams | str | None = None) -> Mass:
    """Laser BPA from trunk width (Xue et al. 2018, eq. 13), with m1(Omega) = 0.

    m1(T) = k1                                  if w in [w_min - dw, w_max + dw]
          = k1 exp((w - (w_min - dw)) / 10 mm)  if w < w_min - dw
          = k1 exp((w_max + dw - w) / 10 mm)    if w > w_max + dw
    m1(NT) = 1 - m1(T).

    Parameters
    ----------
    widths : array_like, metres
        Measured chord widths (eq. 12). Non-finite widths give m1(T) = 0.
    params : BpaParams or preset name, default "xue2018"

    Returns
    -------
    Mass

    Examples
    --------
    >>> m = laser_bpa([0.1836, 0.05])
    >>> np.round(m.t, 4).tolist()
    [0.9, 0.0022]
    """
    p = _params(params)
    w_mm = np.asarray(widths, dtype=np.float64) * 1000.0
    lo = (p.w_min - p.dw) * 1000.0
    hi = (p.w_max + p.dw) * 1000.0
    lo_exp = lo + (2.0 * p.dw * 1000.0 if p.variant == "printed" else 0.0)
    finite = np.isfinite(w_mm)
    w = np.where(finite, w_mm, lo)
    t = np.where(
        w < lo,
        p.k1 * np.exp(np.minimum(w - lo_exp, 0.0) / p.decay_mm),
        np.where(w > hi, p.k1 * np.exp((hi - w) / p.decay_mm), p.k1),
    )
    t = np.where(finite, t, 0.0)
    return Mass(t, 1.0 - t, np.zeros_like(t))


def laser_bpa_ours(
    widths: ArrayLike, params: BpaParams | str | None = None, *, k_t: float = 0.65
) -> Mass:
    """Our laser BPA: a trunk-like width is necessary, not sufficient.

    With f = m1(T) / k1 from eq. 13 (1 inside the width band, decaying outside):
    m(T) = k_t f, m(NT) = 1 - k1 f, m(Omega) = (k1 - k_t) f.

    Inside the band Xue's eq. 13 puts all of k1 on T, so the laser alone accepts every
    trunk-wide object (bushes, poles) with certainty 0.9 and no combination can overturn it
    without near-total conflict. Here the in-band belief k1 is split between T (k_t) and
    ignorance, while out-of-band widths keep eq. 13's strong NT: geometry rules objects *out*
    reliably, and *in* only tentatively.

    Examples
    --------
    >>> np.round(laser_bpa_ours([0.16, 1.0]).as_array(), 3).tolist()
    [[0.65, 0.1, 0.25], [0.0, 1.0, 0.0]]
    """
    p = _params(params)
    if not 0.0 < k_t <= p.k1:
        raise ConfigError(f"k_t must be in (0, k1 = {p.k1}], got {k_t}.")
    f = laser_bpa(widths, p).t / p.k1
    return Mass(k_t * f, 1.0 - p.k1 * f, (p.k1 - k_t) * f)


def vision_bpa(alpha: ArrayLike, params: BpaParams | str | None = None) -> Mass:
    """Vision BPA from the matching level alpha (Xue et al. 2018, eqs. 14-15).

    m2(T) = k2 alpha;  m2(Omega) = (1 - alpha) / alpha if 0.8 <= alpha <= 1, else 0.1;
    m2(NT) = 1 - m2(T) - m2(Omega).

    Parameters
    ----------
    alpha : array_like in [0, 1]
    params : BpaParams or preset name, default "xue2018"

    Returns
    -------
    Mass

    Raises
    ------
    InputError
        If an alpha lies outside [0, 1] or is not finite.
    ConfigError
        If k2 makes m2(NT) negative (k2 alpha + m2(Omega) > 1).

    Notes
    -----
    Eq. 15 jumps at alpha = 0.8 (from 0.1 to 0.25); we implement it as printed because Table 1
    depends on it (alpha = 1 gives m2(Omega) = 0).

    Examples
    --------
    >>> m = vision_bpa([0.64, 1.0])
    >>> np.round(m.as_array(), 3).tolist()
    [[0.576, 0.324, 0.1], [0.9, 0.1, 0.0]]
    """
    p = _params(params)
    a = np.asarray(alpha, dtype=np.float64)
    if not np.all(np.isfinite(a)) or np.any((a < 0) | (a > 1)):
        raise InputError(f"matching levels alpha must be finite and in [0, 1]; got {a}.")
    t = p.k2 * a
    with np.errstate(divide="ignore", invalid="ignore"):
        theta = np.where(a >= 0.8, (1.0 - a) / np.where(a > 0, a, 1.0), 0.1)
    nt = 1.0 - t - theta
    if np.any(nt < -1e-12):
        raise ConfigError(
            f"k2 = {p.k2} makes m2(NT) negative for some alpha; use k2 <= 0.95 (eq. 14-15)."
        )
    return Mass(t, np.maximum(nt, 0.0), theta)


def no_support_mass(shape: int | tuple[int, ...] = ()) -> Mass:
    """Mass given by a sensor that sees nothing where the other sensor has a region:
    m(T) = 0, m(NT) = 1 (Xue et al. 2018, §3.2.4, vision region 5 without laser data)."""
    z = np.zeros(shape)
    return Mass(z, np.ones(shape), z.copy())
