"""Conventions of other tools' exports: length units and the up axis.

stemmap measures in metres with z up (clouds) and in metres and radians (2D scans). Other
tools write millimetres (scanner SDKs, CAD, some photogrammetry), feet (US survey data, LAS
files in a State Plane CRS) or Y-up clouds (photogrammetry, Unity, some SLAM tools). Read as
metres Z-up, such a cloud gives no stems (millimetres, Y-up plots) or silently wrong ones
(feet: every diameter x3.28, measured at 0.8-2.0 ft instead of 0.8-2.0 m; a Y-up single tree:
a 25.5 cm pine came out 8.6 cm). docs/reliability.md, "Input conventions", lists the cases
measured on the real clouds.

:class:`CloudConvention` converts coordinates as they are read (the readers of
:mod:`stemmap.io.clouds` take it); :func:`crs_unit` reads the linear unit a LAS CRS
declares, so that a cloud in feet is refused rather than measured as metres;
:func:`check_scan_ranges` refuses 2D scans whose returns can only be millimetres or
centimetres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError

__all__ = [
    "UNIT_SCALES",
    "UP_AXES",
    "CloudConvention",
    "check_scan_ranges",
    "crs_unit",
    "unit_for_factor",
    "unit_scale",
]

#: Metres per unit of each length unit a user may name (``--units``, ``--range-unit``).
#: ``ft`` is the international foot, ``us-ft`` the US survey foot (1200/3937 m) of
#: State Plane CRSs.
UNIT_SCALES: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "ft": 0.3048,
    "us-ft": 1200.0 / 3937.0,
}

#: The file axis that points up: ``z`` (stemmap's, LAS's), ``y`` (photogrammetry, Unity,
#: many SLAM tools), ``x``.
UP_AXES = ("z", "y", "x")


def unit_scale(unit: str, option: str = "--units") -> float:
    """Metres per ``unit``; ConfigError naming ``option`` and the choices otherwise."""
    try:
        return UNIT_SCALES[unit]
    except KeyError:
        raise ConfigError(
            f"{option} must be one of {', '.join(UNIT_SCALES)}, got {unit!r}."
        ) from None


@dataclass(frozen=True)
class CloudConvention:
    """How a cloud file's coordinates map onto stemmap's metres, z up.

    ``units``: the file's length unit (a key of :data:`UNIT_SCALES`). ``up_axis``: the file
    axis pointing up. The conversion is a scale and a proper rotation (right-handed frames
    stay right-handed): ``y`` up maps file ``(x, y, z)`` to ``(x, -z, y)`` (a +90 degree turn
    about x), ``x`` up maps it to ``(-z, y, x)`` (-90 degrees about y). Results are in the
    converted frame.
    """

    units: str = "m"
    up_axis: str = "z"

    def __post_init__(self) -> None:
        unit_scale(self.units)
        if self.up_axis not in UP_AXES:
            raise ConfigError(
                f"--up-axis must be one of {', '.join(UP_AXES)}, got {self.up_axis!r}."
            )

    @property
    def is_identity(self) -> bool:
        return self.units == "m" and self.up_axis == "z"

    @property
    def scale(self) -> float:
        """Metres per file unit."""
        return UNIT_SCALES[self.units]

    def apply(self, xyz: NDArray[Any]) -> NDArray[np.float64]:
        """``xyz`` (N, 3) in the file's convention -> metres, z up (a new float64 array;
        ``xyz`` itself when the convention is the identity)."""
        if self.is_identity:
            return np.asarray(xyz, dtype=np.float64)
        a = np.asarray(xyz, dtype=np.float64)
        if self.up_axis == "y":
            out = np.column_stack((a[:, 0], -a[:, 2], a[:, 1]))
        elif self.up_axis == "x":
            out = np.column_stack((-a[:, 2], a[:, 1], a[:, 0]))
        else:
            out = a.copy()
        if self.scale != 1.0:
            out *= self.scale
        return out

    def describe(self) -> str:
        """One line for a run summary: what was converted."""
        parts = []
        if self.units != "m":
            parts.append(f"{self.units} -> m (x{self.scale:g})")
        if self.up_axis != "z":
            turn = "(x, -z, y)" if self.up_axis == "y" else "(-z, y, x)"
            parts.append(f"{self.up_axis} up -> z up: file (x, y, z) -> {turn}")
        return "; ".join(parts) or "metres, z up (as read)"


def crs_unit(crs: str | None) -> tuple[str, float] | None:
    """The linear unit of a projected CRS (name, metres per unit), or None when unknown.

    A LAS file in a State Plane CRS in US survey feet holds its coordinates in feet; pyproj
    reads the unit from the CRS's first axis.
    """
    if not crs:
        return None
    try:
        import pyproj

        c = pyproj.CRS.from_user_input(crs)
        axes = c.axis_info
    except Exception:  # an unparsable CRS is reported by the georeferencing code
        return None
    if not axes:
        return None
    factor = axes[0].unit_conversion_factor
    if not (isinstance(factor, float) and math.isfinite(factor) and factor > 0):
        return None
    return str(axes[0].unit_name), float(factor)


def unit_for_factor(factor: float) -> str | None:
    """The :data:`UNIT_SCALES` key of ``factor`` metres per unit (within 1e-6), or None."""
    for name, f in UNIT_SCALES.items():
        if abs(f - factor) <= 1e-6 * f:
            return name
    return None


#: Median valid range above which a 2D scan's returns cannot be metres: no 2D laser scanner
#: in use sees a forest whose median return is 500 m away (long-range 2D scanners reach
#: 80-250 m); in millimetres a return 0.5 m away already reads 500.
SCAN_MEDIAN_RANGE_LIMIT_M = 500.0


def check_scan_ranges(ranges: NDArray[Any], source: str) -> None:
    """InputError when the scans' median valid return is farther than
    :data:`SCAN_MEDIAN_RANGE_LIMIT_M` metres: the ranges are millimetres or centimetres.

    Read as metres, such scans give no trunks without a word (a real scan of the FORTLS plot
    in millimetres: 0 detections, 19 in metres). Centimetres and millimetres overlap (a median
    of 800 is 8 m in cm or 0.8 m in mm), so the unit is not guessed: the message names
    ``--range-unit``.
    """
    r = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        valid = r[np.isfinite(r) & (r > 0)]
    if valid.size == 0:
        return
    # a sample keeps this cheap on long logs (the median of 100 000 returns is exact enough)
    step = max(1, valid.size // 100_000)
    med = float(np.median(valid[::step]))
    if med > SCAN_MEDIAN_RANGE_LIMIT_M:
        raise InputError(
            f"{source}: the median return is {med:.6g} m away; no 2D laser scanner sees a "
            f"forest at over {SCAN_MEDIAN_RANGE_LIMIT_M:g} m, so the ranges are not metres "
            "(millimetres? centimetres?). Pass --range-unit mm (or cm) to `stemmap detect`, or "
            "convert the file for `stemmap map` with `stemmap io convert-scans --range-unit mm`."
        )
