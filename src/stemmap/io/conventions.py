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

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError

log = logging.getLogger(__name__)

__all__ = [
    "UNIT_SCALES",
    "UP_AXES",
    "CloudConvention",
    "check_scan_period",
    "check_scan_ranges",
    "check_times",
    "check_turns",
    "crs_unit",
    "unit_for_factor",
    "unit_scale",
    "up_axis_hint",
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
        return "; ".join(parts) or "metres, z up (as read; not guessed: --units, --up-axis)"


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


#: Thresholds of :func:`up_axis_hint`, chosen on the real clouds (docs/reliability.md, "Input
#: conventions"): the Z-up single trees have their first principal axis within 14 degrees of
#: vertical (|cos| >= 0.97) and the Z-up plots' ground plane its normal vertical; turned Y up,
#: the trees' first axis is within 8 degrees of horizontal (|cos| <= 0.13) and 2.4-15x longer
#: than the second.
_LYING_COS = 0.5
_LYING_ELONGATION = 2.0
_LYING_MAX_STEMS = 5
_WALL_COS = 0.3
_WALL_FLATNESS = 0.35


def up_axis_hint(xyz: NDArray[Any], n_stems: int) -> str | None:
    """A warning when a cloud read z up has the shape of one whose up axis is another, else
    None. ``xyz``: the cloud's points (a sample of up to a few 100 000 is enough), metres,
    as read; ``n_stems``: the stems found.

    Two shapes, each a warning only (the up axis is never guessed):

    * a tree lying on its side: the cloud's first principal axis within 60 degrees of
      horizontal and at least twice as long (standard deviation) as the second, with at most
      :data:`_LYING_MAX_STEMS` stems, and no level dominant plane (a single tree is tallest
      along its stem; a long strip of a mobile drive is long horizontally too, but holds many
      stems and lies on its level ground);
    * a standing plane: the third principal axis (the normal of a dominant plane, the ground
      of a plot) within 17 degrees of horizontal, its deviation under 0.35 of the second's.

    A cloud under 1 m tall (a slice) is not judged: it is flat by construction.
    """
    a = np.asarray(xyz, dtype=np.float64)
    a = a[np.all(np.isfinite(a), axis=1)]
    if a.shape[0] < 100:
        return None
    z = a[:, 2]
    if float(np.percentile(z, 99.5) - np.percentile(z, 0.5)) < 1.0:
        return None
    w, v = np.linalg.eigh(np.cov((a - a.mean(axis=0)).T))
    sd = np.sqrt(np.maximum(w[::-1], 0.0))
    v = v[:, ::-1]
    if not sd[1] > 0:
        return None
    first, third = v[:, 0], v[:, 2]
    axis = "xyz"[int(np.argmax(np.abs(first[:2])))]
    flat = sd[2] <= _WALL_FLATNESS * sd[1]  # a dominant plane (a plot's ground)
    if (
        abs(first[2]) < _LYING_COS
        and sd[0] >= _LYING_ELONGATION * sd[1]
        and n_stems <= _LYING_MAX_STEMS
        and not (flat and abs(third[2]) >= 1.0 - _WALL_COS)
    ):
        return (
            f"the cloud is longest along a horizontal axis ({axis}: {sd[0]:.1f} m std against "
            f"{sd[1]:.1f} m across; z: {abs(first[2]):.2f} of it), like a tree lying on its "
            f"side: if its {axis} axis points up (photogrammetry, Unity), pass --up-axis {axis}; "
            "read z up, a Y-up tree gives a wrong diameter or none."
        )
    if abs(third[2]) < _WALL_COS and flat:
        normal = "xyz"[int(np.argmax(np.abs(third)))]
        return (
            f"the cloud's dominant plane (its ground?) stands vertical, facing {normal}: if "
            f"its {normal} axis points up (photogrammetry, Unity), pass --up-axis {normal}."
        )
    return None


#: Largest time (s) a log in seconds can hold: 1e11 s after the Unix epoch is the year 5138.
#: Unix times in ms, us and ns are 1.7e12, 1.7e15 and 1.7e18.
MAX_TIME_S = 1e11
#: Largest median step (s) between consecutive records a log in seconds can have here: a
#: record a day apart; relative times in us or ns step by 1e4-1e8 per record.
MAX_MEDIAN_STEP_S = 86_400.0


def check_times(times: NDArray[Any], source: str, what: str = "time") -> None:
    """InputError for times that cannot be seconds: a value past :data:`MAX_TIME_S` (Unix
    time in ms, us or ns) or a median step past :data:`MAX_MEDIAN_STEP_S` (relative times in
    us or ns). Read as seconds, such a log's dead reckoning integrates each speed over
    1e8 "seconds": `stemmap map` on a real loop log stamped in ns gave 0 trees, exit 0."""
    t = np.asarray(times, dtype=np.float64)
    t = t[np.isfinite(t)]
    if t.size == 0:
        return
    big = float(np.max(np.abs(t)))
    steps = np.diff(t)
    steps = steps[steps > 0]
    med = float(np.median(steps)) if steps.size else 0.0
    if big <= MAX_TIME_S and med <= MAX_MEDIAN_STEP_S:
        return
    guess = "nanoseconds" if (big > 1e17 or med > 1e6) else "microseconds or milliseconds"
    shown = f"reach {big:.6g}" if big > MAX_TIME_S else f"step by a median of {med:.6g}"
    raise InputError(
        f"{source}: the {what} values {shown}, which cannot be seconds ({guess}?). stemmap "
        "reads times in seconds: divide them (by 1e9 for ns, 1e6 for us, 1e3 for ms)."
    )


#: Longest median step (s) between consecutive scans of a 2D laser scanner read in seconds:
#: 2D scanners turn at 5-100 Hz (0.01-0.2 s; the slowest here, Victoria Park's SICK LMS200,
#: 0.21 s between scans), so a median step of 5 s is 23 x that period. Times counted in
#: milliseconds from the log's start step by 10-200 per scan (Victoria Park's raw scan times
#: by 214): read as seconds, each looks 10-200 s long. A log thinned to one scan per 5 s also
#: passes the bound, so this warns and does not refuse.
MAX_SCAN_PERIOD_S = 5.0


def check_scan_period(times: NDArray[Any], source: str) -> str | None:
    """A warning (also logged) when the scans' median step exceeds
    :data:`MAX_SCAN_PERIOD_S`: relative times in milliseconds (absolute ones are refused by
    :func:`check_times`); None otherwise."""
    t = np.asarray(times, dtype=np.float64)
    t = t[np.isfinite(t)]
    steps = np.diff(t)
    steps = steps[steps > 0]
    if steps.size == 0:
        return None
    med = float(np.median(steps))
    if med <= MAX_SCAN_PERIOD_S:
        return None
    text = (
        f"{source}: the scans are a median of {med:.6g} s apart, but 2D laser scanners scan at "
        f"5-100 Hz (0.01-0.2 s): are the times milliseconds (a 10 Hz log counted in ms steps "
        "by 100)? stemmap reads seconds: divide them by 1e3. (A log thinned to one scan per "
        f"{MAX_SCAN_PERIOD_S:g} s or more is read as it is.)"
    )
    log.warning("%s", text)
    return text


#: Largest 99th percentile of the heading change between consecutive odometry rows (rad):
#: dead reckoning holds each row's yaw rate until the next, so a turn of over half a turn
#: between two rows cannot be followed (its sense is ambiguous, as a wheel filmed at the
#: frame rate). Victoria Park's odometry (40 Hz, seconds): 0.012 rad; its raw dead reckoning
#: stamped in milliseconds (aa3_dr.mat, relative ms): 11.9 rad.
MAX_TURN_PER_ROW = math.pi
#: Largest 99th percentile of the lateral acceleration |speed x yaw_rate| (m/s^2) of a
#: ground vehicle: 1 g, the friction limit of tyres and tracks (mu <= ~1). Victoria Park's
#: utility car: 1.27 m/s^2 (max 2.0). A yaw rate in deg/s reads 57.3 x the acceleration.
MAX_LATERAL_ACCELERATION = 9.81


def _many(bad: NDArray[np.bool_]) -> bool:
    """Over 1 % of the rows, and at least 3: a unit, not one odd row (a short log's 99th
    percentile is its largest value)."""
    k = int(np.count_nonzero(bad))
    return k >= 3 and k > 0.01 * bad.size


def check_turns(
    times: NDArray[Any], speed: NDArray[Any], yaw_rate: NDArray[Any], source: str
) -> None:
    """InputError for an odometry log (``time_s`` s, ``speed`` m/s, ``yaw_rate`` rad/s, each
    row held until the next) that no vehicle can have driven:

    * the heading change between consecutive rows, ``|yaw_rate| x dt``, above
      :data:`MAX_TURN_PER_ROW` (half a turn) in over 1 % of the rows (and at least 3): times
      in milliseconds counted from the log's start (absolute ones are refused by
      :func:`check_times`), or a yaw rate in deg/s;
    * the lateral acceleration ``|speed x yaw_rate|`` above :data:`MAX_LATERAL_ACCELERATION`
      (1 g) in over 1 % of the rows (and at least 3): a yaw rate in deg/s -- a slow turn in
      deg/s (under 3.1 deg/s, which the yaw rate bound cannot see) is caught when the
      vehicle drives faster than ~3.2 m/s while turning; slower, it is not.
    """
    t = np.asarray(times, dtype=np.float64)
    v = np.abs(np.asarray(speed, dtype=np.float64))
    w = np.abs(np.asarray(yaw_rate, dtype=np.float64))
    if t.size < 2:
        return
    turn = w[:-1] * np.diff(t)
    p_turn = float(np.percentile(turn, 99))
    if _many(turn > MAX_TURN_PER_ROW):
        raise InputError(
            f"{source}: 1 % of the rows turn by more than {p_turn:.3g} rad before the next "
            f"row (yaw_rate x the time step), over half a turn ({MAX_TURN_PER_ROW:.3g} rad), "
            "which dead reckoning cannot follow: are the times milliseconds (divide time_s "
            "by 1e3) or the yaw rates in deg/s (multiply yaw_rate by pi/180)?"
        )
    p_acc = float(np.percentile(v * w, 99))
    if _many(v * w > MAX_LATERAL_ACCELERATION):
        raise InputError(
            f"{source}: 1 % of the rows turn with a lateral acceleration (speed x yaw_rate) "
            f"above {p_acc:.3g} m/s^2, beyond the 1 g ({MAX_LATERAL_ACCELERATION:g} m/s^2) "
            "any ground vehicle can hold: is yaw_rate in degrees per second? stemmap reads "
            "rad/s: multiply it by pi/180 (or is speed not in m/s?)."
        )
