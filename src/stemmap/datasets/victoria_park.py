"""Loader for the ACFR Victoria Park dataset (Guivant & Nebot), text redistribution.

Files read (all whitespace-separated, one record per line, common time base in seconds):

* ``inputs.dat``: ``t speed_m_s steering_rad``, 40 Hz. Speed of the LEFT REAR wheel
  (encoder), front steering angle positive to the left.
* ``measurements.dat``: ``t range_m bearing_rad diameter_m``, one row per tree detected in a
  scan (ACFR's own detector). Dataset bearing: 0..pi, 0 = right of the vehicle, pi/2 = straight
  ahead. Only scans with at least one detection appear (7,230 of 7,249).
* ``gps.dat``: ``t x_m y_m`` (shifted and rotated by the redistributor: align before comparing).

Conventions adopted (see docs/algorithms/slam.md):

* Bearing: ours = dataset - pi/2 (CCW from the laser's forward axis). Tested against the data:
  with this convention dead-reckoned world positions of the same tree seen in consecutive scans
  agree; with the mirrored one (pi/2 - dataset) they drift apart when the car turns.
* Vehicle: :class:`~stemmap.slam.motion.AckermannModel` with L = 2.83 m, H = 0.76 m, laser at
  a = 3.78 m ahead of the rear axle (info.txt gives 0.95 m measured from the FRONT axle:
  2.83 + 0.95 = 3.78) and b = 0.50 m to the left.
* Scans without detections: the scan period is 0.2135 s; gaps of k periods between detection
  times are filled with k - 1 empty frames, which recovers all 7,249 scans.

Bad input: a missing file is an :class:`~stemmap.errors.InputError`; malformed rows (wrong field
count, non-numeric, non-finite, out-of-range values, time going backwards) are skipped with a
logged warning and counted in ``VictoriaPark.skipped``; if more than ``max_bad_fraction`` of a
file is bad, loading fails with an InputError naming the file and the first bad line.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from stemmap.datasets import find_datasets_dir
from stemmap.errors import InputError
from stemmap.slam.base import Controls, SlamProblem, TreeFrames
from stemmap.slam.motion import AckermannModel
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.slam.gnss import GnssFixes

__all__ = [
    "GPS_SIGMA_M",
    "LASER_TIME_OFFSET_S",
    "SCAN_PERIOD_S",
    "STEER_OFFSET_RAD",
    "VictoriaPark",
    "dataset_bearing_to_ours",
    "estimate_steer_offset",
    "load_victoria_park",
    "reobservation_consistency",
    "victoria_park_model",
]

#: m, 1-sigma error of one GPS fix: the GPS disagrees with itself by 1.49 m RMS at revisits
#: where the trees overlay to 0.1 m, i.e. ~1.05 m per fix (docs/algorithms/slam.md, "Where the
#: iSAM2 error against the GPS comes from"; measured before GNSS fusion existed).
GPS_SIGMA_M = 1.0

log = logging.getLogger(__name__)

#: Nominal laser scan period (s), median of detection-time differences.
SCAN_PERIOD_S = 0.2135
#: Detector range limit of the laser (m): the SICK LMS returns up to 80 m.
MAX_RANGE_M = 80.0
#: Largest time (s) the laser scans may extend past either end of the odometry. The original
#: files start with a 0.18 s head gap (first scan 0.797 s, first control 0.973 s); a scan more
#: than 1 s (~5 scans, 40 control periods) outside the odometry means a truncated inputs.dat.
SPAN_TOLERANCE_S = 1.0


#: Laser time-stamp correction (s) added to every scan time: the scans were acquired ~55 ms
#: before their stamps relative to the odometry clock. Estimated without GPS (minimum of
#: :func:`reobservation_consistency` over shifts, full run: 0.115 m at 0 -> 0.104 m at -0.055 s
#: for a 1-s lag, 0.270 -> 0.241 m for a 5-s lag).
LASER_TIME_OFFSET_S = -0.055

#: Steering-sensor offset (rad) estimated from the data without GPS by
#: :func:`estimate_steer_offset` on the full run (grid optimum 0.0055 rad = 0.32 deg).
STEER_OFFSET_RAD = 0.0055


def victoria_park_model(
    sigma_speed: float = 0.10, sigma_steer: float = 0.02, steer_offset: float = STEER_OFFSET_RAD
) -> AckermannModel:
    """The car of Victoria Park (Guivant & Nebot): L 2.83, H 0.76, laser at (3.78, 0.50) m,
    steering offset :data:`STEER_OFFSET_RAD` (pass 0.0 for the raw steering signal)."""
    return AckermannModel(
        L=2.83,
        H=0.76,
        a=3.78,
        b=0.50,
        sigma_speed=sigma_speed,
        sigma_steer=sigma_steer,
        steer_offset=steer_offset,
    )


def reobservation_consistency(
    data: VictoriaPark, model: AckermannModel | None = None, *, lag: int = 5, stride: int = 1
) -> float:
    """GPS-free calibration statistic: place every detection in the world by dead reckoning
    and return the median distance (m) between a tree seen in scan f and the nearest detection
    in scan f + ``lag`` (pairs farther than 3 m ignored). Right geometry, conventions and
    odometry calibration make a tree land on itself; errors grow with ``lag``.
    """
    from scipy.spatial import cKDTree

    from stemmap.slam.base import observation_to_world
    from stemmap.slam.motion import preintegrate

    m = model or data.model
    fr = data.frames
    pre = preintegrate(m, data.controls, fr.times)
    w = observation_to_world(pre.poses[fr.frame_index], fr.ranges, fr.bearings, m.sensor_offset)
    d = []
    for f in range(0, len(fr) - lag, stride):
        A = w[fr.ptr[f] : fr.ptr[f + 1]]
        B = w[fr.ptr[f + lag] : fr.ptr[f + lag + 1]]
        if len(A) and len(B):
            dd, _ = cKDTree(A).query(B)
            d.append(dd[dd < 3.0])
    if not d:
        return math.nan
    return float(np.median(np.concatenate(d)))


def estimate_steer_offset(
    data: VictoriaPark,
    *,
    lag: int = 25,
    lo: float = -0.02,
    hi: float = 0.02,
    tol: float = 2e-4,
) -> float:
    """Steering-sensor offset (rad) that minimises :func:`reobservation_consistency` at a
    5-s lag (golden-section search on [lo, hi]); uses only odometry and tree detections."""
    model = data.model

    def cost(off: float) -> float:
        return reobservation_consistency(data, replace(model, steer_offset=off), lag=lag, stride=2)

    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = cost(c), cost(d)
    while b - a > tol:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = cost(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = cost(d)
    return 0.5 * (a + b)


def dataset_bearing_to_ours(bearing: Any) -> FloatArray:
    """Dataset bearing (0 = right, pi/2 = ahead) -> ours (CCW from forward, (-pi, pi])."""
    return np.asarray(bearing, dtype=np.float64) - 0.5 * math.pi


@dataclass(frozen=True, eq=False)
class VictoriaPark:
    """The loaded run.

    Attributes
    ----------
    controls : Controls (kind "ackermann")
    frames : TreeFrames
        One frame per laser scan (including empty ones), detections in the laser frame.
    gps_times : ndarray (G,), s
    gps_xy : ndarray (G, 2), m (redistributor's frame)
    model : AckermannModel
    path : Path
    skipped : dict of file name to number of rows skipped
    """

    controls: Controls
    frames: TreeFrames
    gps_times: FloatArray
    gps_xy: FloatArray
    model: AckermannModel
    path: Path
    skipped: dict[str, int] = field(default_factory=dict)

    def check_time_spans(self) -> None:
        """Refuse laser scans the odometry does not cover (a truncated or foreign file).

        Dead reckoning past the last control extrapolates the last speed and steering, which
        put the EKF/FastSLAM/treedb/Forestrix paths 166-445 m off on a run whose inputs.dat
        was cut at 7 s (issue 13) and left iSAM2 with an indeterminate system. The spans must
        agree within :data:`SPAN_TOLERANCE_S`; odometry running past the last scan is only
        logged (the map simply ends earlier).

        Raises
        ------
        InputError
            Naming both files, their time spans and the ``--t-end`` / :meth:`slice` that maps
            the common span.
        """
        tc = self.controls.times
        tf = self.frames.times
        if len(tc) < 2 or len(tf) == 0:
            raise InputError(
                f"Victoria Park in {self.path}: {len(tc)} odometry row(s) and {len(tf)} scan(s); "
                "need at least 2 controls and 1 scan."
            )
        c0, c1, f0, f1 = float(tc[0]), float(tc[-1]), float(tf[0]), float(tf[-1])
        if f1 > c1 + SPAN_TOLERANCE_S or f0 < c0 - SPAN_TOLERANCE_S:
            lo, hi = max(c0, f0), min(c1, f1)
            fix = (
                f"map only the common span with --t-end {hi:.1f} (library: .slice({lo:.1f}, "
                f"{hi:.1f}))"
                if hi > lo
                else "the spans do not overlap at all"
            )
            raise InputError(
                f"Victoria Park in {self.path}: the odometry (inputs.dat) covers "
                f"{c0:.1f}-{c1:.1f} s but the laser scans (measurements.dat) cover "
                f"{f0:.1f}-{f1:.1f} s; inputs.dat is truncated or the files do not belong "
                f"together: {fix}."
            )
        if c1 > f1 + SPAN_TOLERANCE_S:
            log.warning(
                "Victoria Park in %s: the laser scans end at %.1f s, %.1f s before the odometry "
                "(measurements.dat truncated?); the map ends there.",
                self.path,
                f1,
                c1 - f1,
            )

    def problem(self, *, model: AckermannModel | None = None, name: str = "") -> SlamProblem:
        """A :class:`SlamProblem` (vehicle starts at the origin heading along +x).

        Raises InputError if the odometry does not cover the scans (:meth:`check_time_spans`).
        """
        self.check_time_spans()
        m = model or self.model
        return SlamProblem(
            controls=self.controls,
            frames=self.frames,
            motion=m,
            sensor_offset=(m.a, m.b),
            initial_pose=(0.0, 0.0, 0.0),
            name=name or f"victoria_park[{self.frames.times[0]:.1f}-{self.frames.times[-1]:.1f}]",
            max_range=MAX_RANGE_M,
            fov=(-0.5 * math.pi, 0.5 * math.pi),
        )

    def screened_gps(self) -> NDArray[np.bool_]:
        """(G,) mask of the GPS fixes kept by :func:`stemmap.eval.trajectory.screen_gps` (a rule
        that looks only at the GPS and the wheel odometry, never at a SLAM result)."""
        from stemmap.eval.trajectory import screen_gps
        from stemmap.slam.base import sensor_poses
        from stemmap.slam.motion import preintegrate

        # poses and distances only: the per-segment covariances cost ~260 MB on a 10x replay
        pre = preintegrate(self.model, self.controls, self.gps_times, with_covariance=False)
        sp = sensor_poses(pre.poses, self.model.sensor_offset)
        dist = np.concatenate(([0.0], np.cumsum(pre.distance)))
        return np.asarray(screen_gps(self.gps_times, self.gps_xy, sp[:, :2], dist).keep)

    def gnss_split(
        self, every: int = 10, sigma: float = GPS_SIGMA_M
    ) -> tuple[GnssFixes, NDArray[np.bool_]]:
        """Every ``every``-th screened fix as :class:`~stemmap.slam.gnss.GnssFixes` to fuse, and
        the (G,) mask of the screened fixes NOT fused (to score on, without alignment).

        The antenna is at the laser (docs/algorithms/slam.md, "Trajectory evaluation": scoring
        the laser point fits the GPS best, a least-squares lever arm relative to it is
        (0.01, 0.03) m), so the lever arm is the laser offset. ``sigma`` (m) defaults to
        :data:`GPS_SIGMA_M`, the GPS's disagreement with itself at revisits.
        """
        from stemmap.slam.gnss import GnssFixes as _Fixes

        if every < 1:
            raise InputError(f"gnss_split: every must be >= 1, got {every}.")
        kept = np.flatnonzero(self.screened_gps())
        fused = kept[::every]
        unused = np.zeros(self.gps_times.shape[0], dtype=bool)
        unused[kept] = True
        unused[fused] = False
        fx = _Fixes(
            self.gps_times[fused],
            self.gps_xy[fused],
            np.full(fused.size, float(sigma)),
            self.model.sensor_offset,
        )
        return fx, unused

    def slice(self, t0: float, t1: float) -> VictoriaPark:
        """The part of the run with ``t0 <= t <= t1`` (for short tests)."""
        if not t1 > t0:
            raise InputError(f"slice needs t1 > t0, got [{t0}, {t1}].")
        frames = self.frames.slice(t0, t1)
        if len(frames) == 0:
            raise InputError(f"no Victoria Park scans between {t0} s and {t1} s.")
        g = (self.gps_times >= t0) & (self.gps_times <= t1)
        return replace(
            self,
            controls=self.controls.slice(t0, t1),
            frames=frames,
            gps_times=self.gps_times[g],
            gps_xy=self.gps_xy[g],
        )


def _read_table(
    path: Path, ncols: int, max_bad_fraction: float, skipped: dict[str, int]
) -> FloatArray:
    """Read a whitespace table; skip (and count) malformed lines; time column must not go back."""
    if not path.is_file():
        raise InputError(
            f"Victoria Park file {path} is missing; expected the text redistribution "
            "(inputs.dat, measurements.dat, gps.dat) in that folder."
        )
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read Victoria Park file {path}: {exc}.") from exc
    lines = text.splitlines()
    rows: list[list[float]] = []
    bad: list[tuple[int, str]] = []
    try:  # fast path: a clean file
        arr = np.loadtxt(lines, ndmin=2) if lines else np.zeros((0, ncols))
        if arr.shape[1] != ncols or not np.all(np.isfinite(arr)):
            raise ValueError
    except ValueError:
        for ln, line in enumerate(lines, start=1):
            parts = line.split()
            if not parts:
                continue
            if len(parts) != ncols:
                bad.append((ln, f"{len(parts)} fields instead of {ncols}"))
                continue
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                bad.append((ln, "non-numeric field"))
                continue
            if not all(math.isfinite(v) for v in vals):
                bad.append((ln, "non-finite value"))
                continue
            rows.append(vals)
        arr = np.array(rows, dtype=np.float64).reshape(-1, ncols)
    # time going backwards: drop rows earlier than any row before them
    if arr.shape[0] > 1:
        prev_max = np.maximum.accumulate(np.concatenate(([-np.inf], arr[:-1, 0])))
        back = arr[:, 0] < prev_max
        if np.any(back):
            for k in np.flatnonzero(back)[:5]:
                bad.append((-1, f"time {arr[k, 0]} s goes backwards (after {prev_max[k]} s)"))
            n_back = int(back.sum())
            if n_back > 5:
                bad.append((-1, f"... and {n_back - 5} more rows going back in time"))
            arr = arr[~back]
            skipped[path.name + ":backwards"] = n_back
    n_total = max(len([ln for ln in lines if ln.strip()]), 1)
    n_bad = len([b for b in bad if b[0] > 0]) + skipped.get(path.name + ":backwards", 0)
    if n_bad:
        first = bad[0]
        where = f"line {first[0]}" if first[0] > 0 else "a row"
        msg = (
            f"{path}: skipped {n_bad} malformed row(s) of {n_total}; first at {where}: {first[1]}."
        )
        if n_bad / n_total > max_bad_fraction:
            raise InputError(
                msg
                + f" That is more than {max_bad_fraction:.0%} of the file: is it the right file?"
            )
        log.warning(msg)
        skipped[path.name] = n_bad
    if arr.shape[0] == 0:
        raise InputError(f"Victoria Park file {path} has no valid rows.")
    return arr


def _fill_empty_scans(times: FloatArray, period: float) -> FloatArray:
    """Detection-frame times plus inferred times of the scans that detected nothing."""
    d = np.diff(times)
    k = np.rint(d / period).astype(np.int64)
    gaps = np.flatnonzero(k >= 2)
    extra = [times[i] + d[i] * np.arange(1, k[i]) / k[i] for i in gaps]
    if not extra:
        return times
    return np.sort(np.concatenate([times, *extra]))


def load_victoria_park(
    path: str | os.PathLike[str] | None = None,
    *,
    model: AckermannModel | None = None,
    fill_empty_scans: bool = True,
    max_bad_fraction: float = 0.01,
    laser_time_offset: float = LASER_TIME_OFFSET_S,
) -> VictoriaPark:
    """Load the Victoria Park run into core SLAM types.

    Parameters
    ----------
    path : path-like, optional
        Folder holding ``inputs.dat``, ``measurements.dat``, ``gps.dat``. Default:
        ``<find_datasets_dir()>/victoria_park``.
    model : AckermannModel, optional
        Vehicle model; default :func:`victoria_park_model`.
    fill_empty_scans : bool
        Insert empty frames for the scans that detected no tree (see module notes).
    max_bad_fraction : float
        Largest fraction of malformed rows tolerated per file before failing.
    laser_time_offset : float, s
        Added to every scan time (default :data:`LASER_TIME_OFFSET_S`; 0 keeps the file's
        stamps).

    Returns
    -------
    VictoriaPark

    Raises
    ------
    InputError
        Missing folder/file, a file with no valid rows or too many malformed rows.
    """
    if path is None:
        base = find_datasets_dir()
        if base is None:
            raise InputError(
                "no datasets folder found: pass the Victoria Park folder (the one holding "
                "inputs.dat, measurements.dat and gps.dat; `stemmap map --dataset victoria-park "
                "--data FOLDER`) or set STEMMAP_DATASETS to the folder holding victoria_park/."
            )
        folder = base / "victoria_park"
    else:
        folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"Victoria Park folder {folder} does not exist.")
    skipped: dict[str, int] = {}
    inp = _read_table(folder / "inputs.dat", 3, max_bad_fraction, skipped)
    meas = _read_table(folder / "measurements.dat", 4, max_bad_fraction, skipped)
    gps = _read_table(folder / "gps.dat", 3, max_bad_fraction, skipped)

    # physically impossible detections are bad rows too
    ok = (
        (meas[:, 1] > 0)
        & (meas[:, 1] <= MAX_RANGE_M)
        & (meas[:, 2] >= 0)
        & (meas[:, 2] <= math.pi)
        & (meas[:, 3] > 0)
    )
    if not np.all(ok):
        n = int((~ok).sum())
        log.warning(
            "%s: skipped %d detection(s) with range outside (0, %g] m, bearing outside "
            "[0, pi] or diameter <= 0.",
            folder / "measurements.dat",
            n,
            MAX_RANGE_M,
        )
        skipped["measurements.dat:invalid"] = n
        meas = meas[ok]

    controls = Controls(inp[:, 0], inp[:, 1], inp[:, 2], "ackermann")
    det_times = np.unique(meas[:, 0])
    frame_times = _fill_empty_scans(det_times, SCAN_PERIOD_S) if fill_empty_scans else det_times
    fidx = np.searchsorted(frame_times, meas[:, 0])
    frame_times = frame_times + laser_time_offset
    counts = np.bincount(fidx, minlength=frame_times.shape[0])
    ptr = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    order = np.argsort(fidx, kind="stable")
    frames = TreeFrames(
        frame_times,
        ptr,
        meas[order, 1],
        dataset_bearing_to_ours(meas[order, 2]),
        meas[order, 3],
    )
    log.info(
        "Victoria Park: %d controls, %d scans (%d with detections), %d detections, %d GPS fixes.",
        len(controls),
        len(frames),
        det_times.shape[0],
        frames.n_detections,
        gps.shape[0],
    )
    return VictoriaPark(
        controls=controls,
        frames=frames,
        gps_times=gps[:, 0].copy(),
        gps_xy=gps[:, 1:3].copy(),
        model=model or victoria_park_model(),
        path=folder,
        skipped=skipped,
    )
