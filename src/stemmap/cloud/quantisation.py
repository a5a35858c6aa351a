"""Coordinate quantisation: the step a cloud's coordinates were rounded to, measured from the
points, and the refusal of a cloud too coarse to measure diameters in.

Two exports quantise coordinates without saying so where stemmap can see it:

* **float32 at large values.** A float32 holds a 24-bit mantissa, so its step (ulp) at a
  value ``v`` is ``2**(floor(log2 |v|) - 23)``: 3.1 cm at a UTM easting of 500 000 m, 50 cm at
  a northing of 6 200 000 m. A PLY, PCD or NumPy export written in float32 without the
  exporter's global shift keeps only that grid -- also when the numbers are printed to text
  (XYZ) or promoted to float64 later.
* **A coarse LAS scale factor.** LAS stores integers times the header's scale: a 0.1 m scale
  snaps every point to a 10 cm grid.

The readers see the first only when the file itself stores float32 (they warn:
:func:`stemmap.io.clouds._float32_warning`) and never the second in text, so the step is
measured on the coordinates themselves (:func:`coordinate_step`), on the slice band the
diameters are measured in, whatever the format or the caller (file, array, tile engine).

The bound (:data:`MAX_COORDINATE_STEP`, 2 cm; docs/algorithms/cloud.md "Coordinate
quantisation"): every real cloud of ../shared/datasets written to LAS at scales of 0.5-2 cm
keeps its issue-11 targets, at 3 cm treels spruce is 2.0 cm off its ring, at 5 cm treels
pine_plot's DBH RMSE is 2.9 cm and at 10 cm treels pine is 11.1 cm off -- silently. Rounding
to a step ``q`` moves each coordinate by up to ``q / 2`` (standard deviation ``q / sqrt(12)``,
5.8 mm at 2 cm, below the slice noise floors of the real clouds, 7-21 mm), and at 2 cm the
smallest stem measured (``StemConfig.min_diameter``, 4 cm) still spans two steps.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import InputError

__all__ = [
    "MAX_COORDINATE_STEP",
    "QuantisedCoordinatesError",
    "check_coordinate_step",
    "coordinate_step",
    "naming_the_source",
]

#: Largest coordinate step (m) at which stem diameters are measured (module docstring).
MAX_COORDINATE_STEP = 0.02

#: A magnitude class (sign and binary exponent) is tested when it holds this share of the values.
_MIN_SHARE = 0.1


class QuantisedCoordinatesError(InputError):
    """The cloud's coordinates are rounded to a step too coarse for stem diameters
    (:func:`check_coordinate_step`); ``steps`` are the measured x and y steps (m)."""

    def __init__(self, message: str, steps: tuple[float, float]) -> None:
        super().__init__(message)
        self.steps = steps


def _grid_step(gaps: np.ndarray) -> float:
    """The smallest of ``gaps`` when at least 90 % of them are whole multiples of it (within
    10 % of it: a float32 grid printed to 1 mm in a text file is 3 % off); else 0. On
    unrounded values the gaps' ratios to the smallest are not whole numbers (about 20 % fall
    within 10 % of one by chance), so a sparse cloud is not mistaken for a coarse one."""
    q = float(gaps.min())
    if not q > 0:
        return 0.0
    k = gaps / q
    return q if float(np.mean(np.abs(k - np.round(k)) <= 0.1)) >= 0.9 else 0.0


def coordinate_step(values: ArrayLike) -> float:
    """The step the values were rounded to: 0 when they are not on a grid, inf when every
    value is the same, NaN for fewer than two finite values.

    On a grid of step ``q`` every difference between distinct values is a whole multiple of
    ``q``, and a cloud dense enough to measure stems in occupies neighbouring grid nodes, so
    the smallest difference is ``q`` (:func:`_grid_step`). The float32 step doubles at every
    power of two, so the test is repeated per magnitude class (sign and binary exponent) of
    the classes holding at least 10 % of the values and 10 differences, and the largest step
    is reported: a float32 cloud straddling a power of two (part at one step, part at twice
    it) reports the coarser one.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size < 2:
        return math.nan
    u, counts = np.unique(v, return_counts=True)
    if u.size < 2:
        return math.inf
    gaps = np.diff(u)  # from each distinct value (but the last) to the next
    step = _grid_step(gaps)
    _, exp = np.frexp(u[:-1])
    cls = np.sign(u[:-1]).astype(np.int64) * (exp.astype(np.int64) + 2000)
    for c in np.unique(cls):
        in_c = cls == c
        if in_c.sum() >= 10 and counts[:-1][in_c].sum() >= _MIN_SHARE * v.size:
            step = max(step, _grid_step(gaps[in_c]))
    return step


def _describe(step: float) -> str:
    return f"by {step:.3f} m" if math.isfinite(step) else "not at all (one value)"


def check_coordinate_step(
    xy: ArrayLike, max_step: float | None = MAX_COORDINATE_STEP
) -> tuple[float, float]:
    """The x and y steps of ``xy`` (N, 2) (:func:`coordinate_step`);
    :class:`QuantisedCoordinatesError` (an InputError) when either is
    above ``max_step`` (None: no check) -- the diameters would be numbers nobody can trust.

    Only x and y are read: a diameter is measured in the horizontal plane, z only places the
    slices (20 cm or thicker)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    sx, sy = coordinate_step(p[:, 0]), coordinate_step(p[:, 1])
    if max_step is None:
        return sx, sy
    worst = max((s for s in (sx, sy) if math.isfinite(s)), default=0.0)
    if worst > max_step:
        raise QuantisedCoordinatesError(
            f"the coordinates are quantised: near the stems (the slice band) x steps "
            f"{_describe(sx)} and y {_describe(sy)} (the smallest difference between distinct "
            "values); "
            f"stem diameters need steps of at most {max_step:.3f} m, so none are measured. "
            "Usual causes: float32 coordinates at map-sized values (a PLY, PCD, NumPy or text "
            "export of UTM coordinates without the exporter's global shift: float32 steps "
            "are 3 cm at 500 000 m and 50 cm at 6 200 000 m), or a LAS scale factor of "
            "0.1 m. Re-export in float64, with the coordinates shifted near 0, or as LAS/LAZ "
            "with a scale of 0.001 m.",
            (sx, sy),
        )
    return sx, sy


@contextmanager
def naming_the_source(source: str) -> Iterator[None]:
    """A :class:`QuantisedCoordinatesError` raised inside the block names ``source`` (the
    file) first."""
    try:
        yield
    except QuantisedCoordinatesError as exc:
        raise QuantisedCoordinatesError(f"{source}: {exc}", exc.steps) from None
