"""A scan's beam layout as the detector reads it: the beam angles, their cosines and sines,
which beams lie inside the field of view, where the field of view ends and whether a 360-degree
scan wraps (:func:`_beam_geometry`, cached per layout); the chi-square quantile table of the
straightness test for up to N returns (:func:`_chi2_table`); and the ranges as an (S, N)
array of scans (:func:`_as_scans`).

Split from :mod:`stemmap.scan.detect` (which imports every name here; ``_chi2_table`` also
:mod:`stemmap.scan._pieces`): what a scan's layout makes of its beams is one concept, the
pipeline that runs on them another.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import chdtri

from stemmap.errors import ConfigError, InputError
from stemmap.scan.features import _chi2_upper
from stemmap.types import FloatArray, wrap_angle


class _BeamGeometry(NamedTuple):
    """What a scan's beam layout and the field of view make of its beams (shared by every
    scan of one sensor, so it is computed once: :func:`_beam_geometry`)."""

    angles: FloatArray  # (N,) radians
    cos: FloatArray  # np.cos / np.sin of the angles (the compiled path's return coordinates)
    sin: FloatArray
    inside: NDArray[np.bool_]  # (N,) beams inside the field of view
    first_beam: int  # first / last beam of the field of view; -1 / N for a 360 deg scan
    last_beam: int
    wrap: bool  # 360 deg scan: beam 0 and beam N-1 are neighbours


@functools.lru_cache(maxsize=64)
def _beam_geometry(
    n: int, angle_min: float, angle_increment: float, fov_deg: tuple[float, float] | None
) -> _BeamGeometry:
    angles = angle_min + angle_increment * np.arange(n, dtype=np.float64)
    first_beam, last_beam, wrap = 0, n - 1, False
    if fov_deg is not None:
        a_lo, a_hi = math.radians(fov_deg[0]), math.radians(fov_deg[1])
        wa = wrap_angle(angles)
        inside = (wa >= a_lo) & (wa <= a_hi)
        idx = np.flatnonzero(inside)
        if idx.size == 0:
            raise ConfigError(f"field of view {fov_deg} deg contains none of the scan's beams.")
        first_beam, last_beam = int(idx[0]), int(idx[-1])
    else:
        inside = np.ones(n, dtype=bool)
        if abs(n * angle_increment) >= 2 * math.pi - 0.5 * abs(angle_increment):
            first_beam, last_beam, wrap = -1, n, True  # no field-of-view edge: never truncated
    geo = _BeamGeometry(angles, np.cos(angles), np.sin(angles), inside, first_beam, last_beam, wrap)
    for a in (geo.angles, geo.cos, geo.sin, geo.inside):
        a.setflags(write=False)
    return geo


@functools.lru_cache(maxsize=8)
def _chi2_table(n_beams: int) -> FloatArray:
    """Upper 1 % chi-square quantiles (``is_straight``'s default alpha) for 0..max(1023, N)
    degrees of freedom: a segment has at most N returns."""
    base = _chi2_upper(0.01)
    if n_beams < base.shape[0]:
        return base
    extra = chdtri(np.arange(base.shape[0], n_beams + 1, dtype=np.float64), 0.01)
    out: FloatArray = np.concatenate((base, extra))
    out.setflags(write=False)
    return out


def _as_scans(ranges: ArrayLike) -> FloatArray:
    r = np.asarray(ranges, dtype=np.float64)
    if r.ndim == 1:
        r = r[None, :]
    if r.ndim != 2 or r.shape[1] == 0:
        raise InputError(f"ranges must have shape (S, N) with N > 0, got {r.shape}.")
    return r
